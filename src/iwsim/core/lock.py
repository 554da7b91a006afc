"""One writer per directory: an advisory ``flock`` on a lock file inside it.

Writers of an episode store (``iwsim collect``, ``iwsim play --record-to``) hold
``<store>/.iwsim.lock`` for as long as they may append; readers never take it, so they
never block. ``flock`` locks belong to an open file, so the kernel drops them when the
holder exits, however it exits: a lock left by a killed process is simply free again. The
file also says who holds it (PID, command, since when) for the error a second writer gets;
a holder that lets go clears it, so the next holder is never named after the last one.

The same lock marks temporary directories that are still being written: a hidden
``.NAME.<hex>.tmp`` next to ``NAME`` whose lock is free was left by a killed process and
is removed by the next run that writes ``NAME`` (:func:`remove_stale_temps`).
"""

from __future__ import annotations

import errno
import fcntl
import logging
import os
import shutil
import sys
import time
import uuid
from pathlib import Path

log = logging.getLogger(__name__)

LOCK_NAME = ".iwsim.lock"
UNLOCKED_GRACE_S = 60.0  # an unlocked temporary directory younger than this may still be starting


class LockedError(OSError):
    """Another process holds the lock; the message names it."""


class DirLock:
    """An exclusive advisory lock on ``directory/.iwsim.lock`` (created if missing).

    ``wait=False`` raises :class:`LockedError` at once when another process (or another
    open lock in this process) holds it; ``wait=True`` logs who holds it and blocks until
    it is free (``hint`` ends the refusal: what to do instead). Release with :meth:`release`
    or by leaving a ``with`` block.
    """

    def __init__(self, directory: str | os.PathLike, *, wait: bool = False, what: str = "writing",
                 hint: str = "wait for it to finish, or pass --wait-for-lock to queue behind it.") -> None:
        self.path = Path(directory) / LOCK_NAME
        self._fd: int | None = None  # set first: __del__ runs even when the open below fails
        self._owned = False  # whether this process took the lock (and so wrote the holder's text)
        # Opened without truncating: the holder's text must survive until we own the lock.
        self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            try:
                fcntl.flock(self._fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as e:
                if e.errno not in (errno.EWOULDBLOCK, errno.EACCES):
                    raise
                holder = self._wait_for_holder() or "another process"
                if not wait:
                    raise LockedError(errno.EWOULDBLOCK, f"{directory} is being written by {holder}; one writer "
                                      f"at a time: {hint}") from None
                log.warning("%s is being written by %s; waiting for it to finish", directory, holder)
                fcntl.flock(self._fd, fcntl.LOCK_EX)
            self._owned = True
            text = f"pid {os.getpid()} ({_command()}), {what} since {time.strftime('%Y-%m-%d %H:%M:%S')}\n".encode()
            os.pwrite(self._fd, text, 0)  # then cut what is left of an earlier holder's text:
            os.ftruncate(self._fd, len(text))  # the file is never empty while it is rewritten
        except BaseException:
            self.release()
            raise

    def _wait_for_holder(self, seconds: float = 1.0) -> str:
        """The holder's text. A holder that has just taken the lock writes it a moment later;
        until then the file is empty, or names a killed holder. Either is read again for up
        to ``seconds``, and a dead process is never named."""
        deadline = time.monotonic() + seconds
        while not _names_a_live_process(text := self.holder()):
            if time.monotonic() >= deadline:
                return ""
            time.sleep(0.02)
        return text

    def holder(self) -> str:
        """Who holds the lock, as its file says: empty while nobody does, unless the last
        holder was killed (then its name stays until the next holder writes its own)."""
        try:
            return self.path.read_text(errors="replace").strip()[:200]
        except OSError:
            return ""

    @property
    def held(self) -> bool:
        return self._fd is not None

    def unlink(self) -> None:
        """Remove the lock file (still holding the lock) if it is still ours, e.g. before a
        finished temporary directory becomes a result that should not carry it."""
        if self._fd is None:
            return
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            return
        mine = os.fstat(self._fd)
        if (st.st_dev, st.st_ino) == (mine.st_dev, mine.st_ino):
            self.path.unlink()

    def release(self) -> None:
        if self._fd is not None:
            fd, self._fd = self._fd, None
            if self._owned:  # still holding it: clear our name before letting go
                self._owned = False
                try:
                    os.ftruncate(fd, 0)
                except OSError:
                    pass
            os.close(fd)  # closing the last descriptor of the open file drops the flock

    def __enter__(self) -> DirLock:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def __del__(self) -> None:
        self.release()


def _names_a_live_process(text: str) -> bool:
    """Whether a lock file's text ("pid N (...), ...") names a process that is running here."""
    words = text.split()
    if len(words) < 2 or words[0] != "pid" or not words[1].isdigit():
        return False
    try:
        os.kill(int(words[1]), 0)
    except (ProcessLookupError, OverflowError):
        return False
    except OSError:  # it exists, but is not ours to signal
        pass
    return True


def is_locked(directory: str | os.PathLike) -> bool:
    """Whether some open :class:`DirLock` holds ``directory`` (without taking it)."""
    try:
        fd = os.open(Path(directory) / LOCK_NAME, os.O_RDONLY | os.O_CLOEXEC)
    except FileNotFoundError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError:
        return True
    finally:
        os.close(fd)
    return False


def temp_sibling(path: Path) -> Path:
    """A fresh hidden temporary name next to ``path``: ``.NAME.<hex>.tmp``."""
    return path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")


def remove_stale_temps(path: Path) -> None:
    """Remove the ``.NAME.<hex>.tmp`` siblings of ``path`` that no live process is writing
    (their lock is free, or they never got one)."""
    if not path.parent.is_dir():
        return
    for tmp in path.parent.glob(f".{path.name}.*.tmp"):
        if not tmp.is_dir() or tmp.is_symlink() or is_locked(tmp):
            continue
        # A directory without a lock file may be one another run has just made and not yet
        # locked (or one from before locks existed): only an old one is certainly stale.
        if not (tmp / LOCK_NAME).exists() and time.time() - tmp.stat().st_mtime < UNLOCKED_GRACE_S:
            continue
        log.warning("removing %s, left behind by an interrupted run", tmp)
        shutil.rmtree(tmp, ignore_errors=True)


def _command() -> str:
    """``iwsim collect``, ``iwsim play``, ...: the program and its subcommands, no flags (they
    may hold paths or secrets)."""
    prog = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else "python"
    words = [w for w in (sys.argv[1:3] if sys.argv else []) if not w.startswith("-")][:2]
    if prog == "__main__.py":  # python -m PACKAGE
        prog = os.path.basename(os.path.dirname(sys.argv[0]))
    return " ".join(["iwsim" if prog == "cli.py" else prog, *words])
