"""What this machine lets a command use: CPU threads and memory.

Threads are chosen, not inherited: PyTorch's default (one thread per core of the machine)
oversubscribes the cores when another job runs beside it, and on a 2-core CPU with one
core busy elsewhere that made a world-model step 80x slower (1.7 s instead of 0.02 s).
So every ``iwsim`` command sets torch's thread count from the cores this process may run
on (its CPU affinity), or from ``OMP_NUM_THREADS`` when set, or from ``--threads``.

Memory: flags that size allocations (batch sizes, image sizes, steps) are checked against
the memory the kernel says is available before anything is allocated, so a typo gets one
line instead of the OOM killer.
"""

from __future__ import annotations

import contextlib
import logging
import os
import stat
import sys
from collections.abc import Iterator

from iwsim.core.errors import InputError, IwsimError

log = logging.getLogger(__name__)

GiB = 1 << 30
MiB = 1 << 20


def read_capped(path: str | os.PathLike, limit: int, error: type[Exception] = InputError) -> bytes:
    """The bytes of the file ``path``, which must be a regular file of at most ``limit``
    bytes (``error`` naming it otherwise): a small file a user names (a config, a token, a
    symlink to ``/dev/zero`` by mistake) is never read until memory runs out. A missing
    file is a FileNotFoundError."""
    path = os.fspath(path)
    # non-blocking: opening a FIFO must not wait for a writer (a regular file ignores it)
    with os.fdopen(os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC), "rb") as f:
        if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
            raise error(f"{path}: not a regular file.")
        data = f.read(limit + 1)
    if len(data) > limit:
        raise error(f"{path}: larger than {human_bytes(limit)}, more than such a file holds.")
    return data


class ResourceError(IwsimError):
    """A request the machine cannot serve (more memory or threads than it has)."""


def available_cores() -> int:
    """CPU cores this process may run on (its affinity mask; ``os.cpu_count()`` elsewhere)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # not Linux
        return max(1, os.cpu_count() or 1)


def choose_threads(requested: int | None = None) -> int:
    """Threads for torch: ``requested`` if given, else ``OMP_NUM_THREADS`` if set (the
    convention every OpenMP program follows, and what ``torchrun`` sets per rank), else the
    cores this process may use."""
    if requested is not None:
        if requested < 1:
            raise InputError(f"--threads must be a positive integer, got {requested}.")
        return requested
    env = os.environ.get("OMP_NUM_THREADS", "").strip()
    if env:
        try:
            n = int(env)
        except ValueError:
            n = 0
        if n >= 1:
            return n
        log.warning("ignoring OMP_NUM_THREADS=%r (expected a positive integer)", env)
    return available_cores()


def set_threads(requested: int | None = None) -> int:
    """Set torch's intra-op thread count (see :func:`choose_threads`); returns it.

    Before torch is imported this only sets ``OMP_NUM_THREADS``, which torch reads when it
    starts (and child processes inherit), so commands that never use torch do not pay for
    importing it."""
    n = choose_threads(requested)
    if n > available_cores():
        log.warning("using %d threads on %d available cores: they will compete with each other", n,
                    available_cores())
    torch = sys.modules.get("torch")
    if torch is None:
        os.environ["OMP_NUM_THREADS"] = str(n)
    else:
        torch.set_num_threads(n)
    return n


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """torch's intra-op thread count set to ``n`` inside the block, restored after it."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def available_memory() -> int | None:
    """Bytes of memory available to new allocations without swapping (``MemAvailable`` of
    /proc/meminfo, else free physical pages), or None if unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def human_bytes(n: float) -> str:
    """``n`` bytes as B, KiB, MiB, GiB or TiB."""
    size = float(n)
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if size < 1024 or unit == "TiB":
            return f"{size:.0f} {unit}" if unit == "B" else f"{size:.1f} {unit}"
        size /= 1024
    raise AssertionError("unreachable")


def require_memory(need: float, what: str) -> None:
    """Raise ResourceError when ``need`` bytes exceed the available memory; ``what`` names
    the request (e.g. "--batch-size 100000 (about 25 MiB per sample)")."""
    have = available_memory()
    if have is not None and need > have:
        raise ResourceError(f"{what} would need about {human_bytes(need)} of memory; this machine has "
                            f"{human_bytes(have)} available.")
