"""The episode store: recorded episodes in Zarr, laid out like Diffusion Policy's ReplayBuffer.

On disk (Zarr format 2, so that Diffusion Policy's zarr-2 + numcodecs stack opens it)::

    root/.zattrs               task description, image size, per-episode ``seeds``, ...
    root/data/<key>            (N, ...) arrays concatenated over episodes, e.g. ``img``
                               (N, H, W, 3) uint8, ``state`` (N, 4) and ``action`` (N, 4) f32
    root/meta/episode_ends     (E,) int64, cumulative: episode i is frames
                               ``[episode_ends[i-1], episode_ends[i])``

``episode_ends`` is the commit record. An append resizes and writes the data arrays first
and grows ``episode_ends`` last, and every file Zarr writes is replaced atomically (written
to a temporary name, then renamed), so a process killed at any point leaves a store whose
``episode_ends`` describes only whole episodes. Readers take ``episode_ends[-1]`` as the
length of the data (arrays may hold a few uncommitted frames past it) and ignore a trailing
entry that is not yet written (it reads as the fill value 0, so ends must strictly
increase). Opening in mode ``"a"`` repairs such leftovers before anything is appended.
Anything else that does not add up (ends that do not increase, a chunk file missing or not
decodable, sizes the files do not hold, metadata that is not JSON) is damage: every reader
and writer refuses the store with a StoreError naming it, and nothing is changed. Every
chunk is written, even one of fill values, so a missing chunk file is always damage.

One writer at a time: mode ``"a"`` holds the store's lock (``root/.iwsim.lock``, see
:mod:`iwsim.core.lock`) until :meth:`EpisodeStore.close`; a second writer is refused, or
waits with ``wait=True``. Readers take no lock.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np
import zarr
from numcodecs import Blosc
from numcodecs.compat import ensure_contiguous_ndarray
from numcodecs.registry import register_codec

from iwsim.core.errors import InputError
from iwsim.core.lock import DirLock, LockedError, remove_stale_temps, temp_sibling
from iwsim.core.resources import read_capped

log = logging.getLogger(__name__)

class _CheckedBlosc(Blosc):
    """Blosc that checks a chunk's header against its length before decoding: c-blosc reads
    past the end of a truncated or damaged buffer and can crash the process (numcodecs
    issue 228), where a damaged chunk must be an error that names it."""

    def decode(self, buf: Any, out: Any = None) -> Any:
        view = memoryview(ensure_contiguous_ndarray(buf)).cast("B")
        # the 16-byte header: ..., nbytes (uint32 LE at 4), blocksize (8), cbytes (12)
        if len(view) < 16 or int.from_bytes(view[12:16], "little") != len(view):
            said = int.from_bytes(view[12:16], "little") if len(view) >= 16 else "a 16-byte header and more"
            raise RuntimeError(f"a Blosc chunk of {len(view)} bytes whose header says {said}: truncated or damaged")
        return super().decode(buf, out)


# Every Zarr array opened from now on decodes Blosc through the checked codec.
register_codec(_CheckedBlosc, "blosc")

STORE_VERSION = 1  # layout version, stored as the ``store_version`` attribute
# uint8 frames: zstd alone (byte shuffling is a no-op at itemsize 1); ~90x on rendered frames.
IMAGE_COMPRESSOR = Blosc(cname="zstd", clevel=5, shuffle=Blosc.NOSHUFFLE)
LOWDIM_COMPRESSOR = Blosc(cname="zstd", clevel=5, shuffle=Blosc.SHUFFLE)
CHUNK_BYTES = 1 << 20  # target uncompressed chunk size: 64 frames at 64x64, 16 at 128x128
MAX_CHUNK_FRAMES = 4096
ENDS_CHUNK = 4096  # episode_ends entries per chunk
_EXPECTED = "an episode store (a Zarr format 2 group with data/ and meta/episode_ends)"


class StoreError(InputError):
    """A path that is not a usable episode store, or an episode that does not fit it."""


class StoreLockedError(StoreError):
    """Another process is writing the store."""


def conditioning_key(keys: list[str]) -> str:
    """The array a world model is conditioned on: ``target``, the motion the robot executed
    (e.g. rate-limited pusher setpoints), when the store records it, else ``action``."""
    return "target" if "target" in keys else "action"


def chunk_frames(frame_shape: tuple[int, ...], dtype: np.dtype) -> int:
    """Frames per chunk: the largest power of two whose chunk stays within ``CHUNK_BYTES``."""
    frame_bytes = max(1, int(np.prod(frame_shape, dtype=np.int64)) * np.dtype(dtype).itemsize)
    n = max(1, CHUNK_BYTES // frame_bytes)
    return min(MAX_CHUNK_FRAMES, 1 << (n.bit_length() - 1))


def dir_size(path: str | os.PathLike[str]) -> int:
    """Bytes of all regular files under ``path``."""
    total = 0
    for dirpath, _, files in os.walk(path):
        for f in files:
            try:
                total += os.lstat(os.path.join(dirpath, f)).st_size
            except FileNotFoundError:  # removed while walking
                pass
    return total


def _committed_ends(raw: np.ndarray, path: Path) -> np.ndarray:
    """``raw`` without an entry that is not yet written: positive and strictly increasing.

    A crash between growing ``episode_ends`` and writing its new entry leaves one trailing
    fill value 0, which this drops. Anything else that does not increase is damage, not an
    interrupted append, and is refused (nothing is cut).
    """
    ok = np.diff(raw, prepend=0) > 0
    if ok.all():
        return raw
    if ok[:-1].all() and raw[-1] == 0:
        return raw[:-1]
    i = int(np.argmin(ok))
    raise StoreError(f"{path} is damaged: meta/episode_ends must increase strictly, but entry {i} is {raw[i]} "
                     f"after {raw[i - 1] if i else 0}; `iwsim data validate` lists what is wrong.")


def _chunk_rows(arr: zarr.Array, directory: Path) -> set[int]:
    """The row-chunk indices of ``arr`` (a Zarr format 2 array in ``directory``) that have a file."""
    rows = set()
    with os.scandir(directory) as it:
        for entry in it:
            head = entry.name.split("/" if entry.is_dir() else ".", 1)[0]
            if head.isdigit():
                rows.add(int(head))
    return rows


def _missing_chunk(arr: zarr.Array, directory: Path, n: int) -> int | None:
    """The first row chunk of ``arr`` holding any of its first ``n`` rows whose file is
    missing (such rows would read as the fill value), or None. Counts, never allocates per
    declared row, so a shape edited to 10^12 costs one directory listing."""
    step = arr.chunks[0]
    need = -(-n // step)
    if not need:
        return None
    rows = _chunk_rows(arr, directory)
    return next((i for i in range(min(need, len(rows) + 1)) if i not in rows), None)


ZARR_META_MAX_BYTES = 64 << 20  # a .zattrs, .zarray or .zgroup larger than this is not one Zarr wrote
_ZARR_META = (".zgroup", ".zattrs", ".zarray")


def _check_metadata_files(path: Path) -> None:
    """Every Zarr metadata file of the store (root, meta/, data/ and their arrays) is a
    JSON object in a regular file of a sane size: Zarr reads them whole (a symlink to
    ``/dev/zero`` would be read until memory ran out) and, reading a group's members
    concurrently, fails on a bad one with tasks left pending."""
    dirs = [path, path / "meta", path / "meta" / "episode_ends", path / "data"]
    if (path / "data").is_dir():
        dirs += [p for p in (path / "data").iterdir() if p.is_dir()]
    for d in dirs:
        for name in _ZARR_META:
            f = d / name
            if not os.path.lexists(f):
                continue
            try:
                ok = isinstance(json.loads(read_capped(f, ZARR_META_MAX_BYTES, StoreError)), dict)
            except StoreError as e:
                raise StoreError(f"{path} is damaged: {e}") from None
            except (OSError, ValueError):
                ok = False
            if not ok:
                raise StoreError(f"{path} is damaged: {f.relative_to(path)} is not a JSON object.")


class CheckedArray:
    """Read access to a data array that turns a chunk that cannot be decoded (truncated,
    another dtype than ``.zarray`` declares, ...) into a StoreError naming the array."""

    def __init__(self, arr: zarr.Array, where: str) -> None:
        self._arr, self._where = arr, where

    def __getattr__(self, name: str) -> Any:
        return getattr(self._arr, name)

    def __len__(self) -> int:
        return self._arr.shape[0]  # zarr 3's Array has no __len__

    def _read(self, read: Callable[[], Any]) -> Any:
        try:
            return read()
        except (RuntimeError, ValueError, TypeError, KeyError, OSError) as e:
            if isinstance(e, InputError):
                raise
            why = " ".join(str(e).split())[:160] or type(e).__name__
            raise StoreError(f"{self._where} is damaged: a chunk cannot be read ({why}); "
                             "`iwsim data validate` lists what is wrong.") from None

    def __getitem__(self, selection: Any) -> np.ndarray:
        return self._read(lambda: self._arr[selection])

    @property
    def oindex(self) -> _CheckedIndex:
        return _CheckedIndex(self)


class _CheckedIndex:
    def __init__(self, checked: CheckedArray) -> None:
        self._checked = checked

    def __getitem__(self, selection: Any) -> np.ndarray:
        return self._checked._read(lambda: self._checked._arr.oindex[selection])


def _settable(attrs: Mapping[str, Any]) -> dict[str, Any]:
    """``attrs`` as a dict, checked to be root attributes a caller may set: JSON-serialisable,
    without the store's own ``seeds`` and ``store_version``."""
    attrs = dict(attrs)
    if "seeds" in attrs or "store_version" in attrs:
        raise InputError("attrs must not set 'seeds' or 'store_version'; the store manages them.")
    try:
        json.dumps(attrs)
    except TypeError as e:
        raise InputError(f"store attributes must be JSON-serialisable: {e}.") from None
    return attrs


def attrs_mismatch(store: EpisodeStore, attrs: Mapping[str, Any], keys: Iterable[str],
                   absent: Mapping[str, Any] | None = None) -> str | None:
    """How ``store``'s root attributes differ from ``attrs`` on ``keys``, for the message
    that refuses to append to it (``"policy='a', steps=300, not policy='b', steps=100"``);
    None when they agree. ``absent``: the values a store written before a key existed has."""
    stored = {**(absent or {}), **store.attrs}
    diffs = [k for k in keys if stored.get(k) != attrs[k]]
    if not diffs:
        return None
    have = ", ".join(f"{k}={stored.get(k)!r}" for k in diffs)
    want = ", ".join(f"{k}={attrs[k]!r}" for k in diffs)
    return f"{have}, not {want}"


def lock_store(path: str | os.PathLike, wait: bool = False) -> DirLock:
    """The writer's lock of the store at ``path`` (see :mod:`iwsim.core.lock`); raises
    StoreLockedError naming the holder, or waits for it with ``wait``."""
    try:
        return DirLock(path, wait=wait, what="appending")
    except LockedError as e:
        raise StoreLockedError(e.strerror) from None
    except OSError as e:
        raise StoreError(f"cannot lock {path} for writing: {e.strerror or e}.") from None


class EpisodeStore:
    """Episodes in a Zarr directory; open with :meth:`create` or :meth:`open`.

    ``episode(i)`` returns ``{key: (T_i, ...) array}``; ``append(episode, seed)`` adds one.
    A store opened for appending holds the store's lock until :meth:`close` (or the end of
    a ``with`` block, or the process).
    """

    def __init__(self, root: zarr.Group, path: Path, mode: Literal["r", "a"], lock: DirLock | None = None) -> None:
        self._root = root
        self.path = path
        self.mode = mode
        self._lock = lock
        ends_array, data = root["meta/episode_ends"], root["data"]
        assert isinstance(ends_array, zarr.Array) and isinstance(data, zarr.Group)  # checked by _open
        self._ends_array, self._data = ends_array, data
        self._load()

    def _load(self) -> None:
        """Read (again) what is on disk: the arrays, the attributes and the committed ends."""
        path = self.path
        # every chunk is written, even one of fill values: a missing chunk file is then damage
        self._arrays: dict[str, zarr.Array] = {
            k: a.with_config({"write_empty_chunks": True}) for k, a in self._data.arrays()}
        self._attrs: dict[str, Any] = dict(self._root.attrs)
        # the declared length is checked against the files before anything is allocated
        ends_dir = path / "meta" / "episode_ends"
        declared = self._ends_array.shape[0]
        written = max(_chunk_rows(self._ends_array, ends_dir), default=-1) + 1 if ends_dir.is_dir() else 0
        if declared > written * self._ends_array.chunks[0] + 1:  # + 1: an end not yet written
            raise StoreError(f"{path} is damaged: meta/episode_ends declares {declared} entries but its chunk "
                             f"files hold at most {written * self._ends_array.chunks[0]}.")
        if not np.issubdtype(self._ends_array.dtype, np.integer):
            raise StoreError(f"{path} is damaged: meta/episode_ends holds {self._ends_array.dtype}, not integers.")
        raw = np.asarray(self._ends_array[:], dtype=np.int64)
        self._ends = _committed_ends(raw, path)
        self._n_uncommitted_ends = len(raw) - len(self._ends)
        n = self.n_frames
        for key, arr in self._arrays.items():
            if arr.ndim == 0:
                raise StoreError(f"{path} is damaged: data/{key} is a scalar, not one entry per frame.")
            if arr.shape[0] < n:
                raise StoreError(
                    f"{path} is damaged: meta/episode_ends counts {n} frames but data/{key} holds only {arr.shape[0]}."
                )
            missing = _missing_chunk(arr, path / "data" / key, n)
            if missing is not None:
                step = arr.chunks[0]
                raise StoreError(f"{path} is damaged: the chunk file of data/{key} holding frames {missing * step}.."
                                 f"{min(n, (missing + 1) * step) - 1} is missing.")
        if n and not self._arrays:
            raise StoreError(f"{path} is damaged: meta/episode_ends counts {n} frames but data/ holds no arrays.")
        seeds = self._attrs.get("seeds", [])
        if not isinstance(seeds, list) or len(seeds) < len(self._ends):
            raise StoreError(f"{path} is damaged: its 'seeds' attribute does not list one seed per episode.")

    # --- opening -----------------------------------------------------------------------
    @classmethod
    def create(cls, path: str | os.PathLike, attrs: Mapping[str, Any] | None = None) -> EpisodeStore:
        """Create an empty store at ``path`` (which must not exist) with root ``attrs``,
        open for appending (it holds the store's lock).

        The store is built under a temporary name next to ``path`` and renamed into place,
        so ``path`` never holds a half-created store. Parent directories are created;
        temporary stores that killed runs left next to ``path`` are removed.
        """
        path = Path(path)
        attrs = _settable(attrs or {})
        if path.exists():
            raise StoreError(f"cannot create an episode store at {path}: it already exists.")
        tmp = temp_sibling(path)
        lock = None
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            remove_stale_temps(path)
            tmp.mkdir()
            # renamed with the directory, so the new store is locked from the start
            lock = DirLock(tmp, what="appending")
            root = zarr.open_group(tmp, mode="a", zarr_format=2)  # "w" would clear the lock file
            root.require_group("data")
            meta = root.require_group("meta")
            # Like Diffusion Policy: episode_ends uncompressed, int64.
            meta.create_array(
                "episode_ends", shape=(0,), chunks=(ENDS_CHUNK,), dtype="int64", compressors=None, fill_value=0
            )
            root.attrs.update({**attrs, "store_version": STORE_VERSION, "seeds": []})
            os.rename(tmp, path)
        except OSError as e:
            shutil.rmtree(tmp, ignore_errors=True)
            if lock is not None:
                lock.release()
            if path.exists():  # another process created it meanwhile
                raise StoreError(f"cannot create an episode store at {path}: it already exists.") from None
            raise StoreError(f"cannot create an episode store at {path}: {e.strerror or e}.") from e
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            if lock is not None:
                lock.release()
            raise
        log.debug("created episode store %s", path)
        return cls.open(path, "a", lock=lock)

    @classmethod
    def open(cls, path: str | os.PathLike, mode: Literal["r", "a"] = "r", *, wait: bool = False,
             lock: DirLock | None = None) -> EpisodeStore:
        """Open an existing store, read-only (``"r"``) or for appending (``"a"``).

        Mode ``"a"`` takes the store's lock first (``lock``, when the caller already holds
        it): another writer means a StoreLockedError naming it, or with ``wait`` a wait
        until it is done. Then it repairs what an interrupted append left behind (frames
        past ``episode_ends[-1]``, an unwritten trailing end, temporary files).
        """
        if mode not in ("r", "a"):
            raise InputError(f"mode must be 'r' or 'a', got {mode!r}.")
        path = Path(path)
        if not path.exists():
            raise StoreError(f"{path} does not exist; expected {_EXPECTED}.")
        if not path.is_dir():
            raise StoreError(f"{path} is a file, not {_EXPECTED}.")
        if mode == "a" and lock is None:
            lock = lock_store(path, wait=wait)
        try:
            return cls._open(path, mode, lock)
        except BaseException:
            if lock is not None:
                lock.release()
            raise

    @classmethod
    def open_or_create(cls, path: str | os.PathLike, attrs: Mapping[str, Any], *,
                       check: Callable[[EpisodeStore], None] | None = None, wait: bool = False,
                       blank: Callable[[EpisodeStore], bool] | None = None) -> EpisodeStore:
        """The store at ``path`` open for appending: created with ``attrs`` when missing,
        else locked, then ``check``-ed read-only (it raises if this writer must not append,
        and nothing is touched), then opened. Locking comes before reading, so what
        ``check`` sees cannot change until :meth:`close`. A store that holds no episodes
        (and, where ``blank`` says so, nothing else its writer keeps) is the leftover of a
        writer stopped before its first episode: it is not checked but takes ``attrs``."""
        path = Path(path)
        if not path.exists():
            try:
                return cls.create(path, attrs)
            except StoreError:
                if not path.exists():
                    raise
                # another process created it meanwhile: append to it like to any existing store
        if not (path / ".zgroup").is_file():  # not a store: say why before a lock file is left in it
            cls._open(path, "r", None)
        lock = lock_store(path, wait=wait)
        try:
            existing = cls._open(path, "r", None)
            if not existing.n_episodes and (blank is None or blank(existing)):
                store = cls.open(path, "a", lock=lock)
                store._describe_anew(attrs)
                return store
            if check is not None:
                check(existing)
            return cls.open(path, "a", lock=lock)
        except BaseException:
            lock.release()
            raise

    @classmethod
    def _open(cls, path: Path, mode: Literal["r", "a"], lock: DirLock | None) -> EpisodeStore:
        _check_metadata_files(path)
        try:
            root = zarr.open_group(path, mode="r" if mode == "r" else "r+")
        except (OSError, ValueError, KeyError, TypeError):
            raise StoreError(f"{path} is not {_EXPECTED}: it holds no readable Zarr group.") from None
        if root.metadata.zarr_format != 2:
            raise StoreError(f"{path} is a Zarr format {root.metadata.zarr_format} group, not {_EXPECTED}.")
        ends = root.get("meta/episode_ends")
        if not isinstance(ends, zarr.Array) or ends.ndim != 1:
            raise StoreError(f"{path} is a Zarr group without meta/episode_ends, not {_EXPECTED}.")
        if not isinstance(root.get("data"), zarr.Group):
            raise StoreError(f"{path} is a Zarr group without data/, not {_EXPECTED}.")
        try:
            store = cls(root, path, mode, lock)
        except (ValueError, KeyError, TypeError) as e:  # a .zarray or .zattrs that is not what Zarr wrote
            if isinstance(e, StoreError):
                raise
            raise StoreError(f"{path} is damaged: its Zarr metadata cannot be read ({' '.join(str(e).split())[:160]})."
                             ) from None
        if mode == "a":
            store._repair()
        elif store._n_uncommitted_ends or store._n_uncommitted_frames():
            log.warning("%s holds leftovers of an interrupted append; they are ignored", path)
        return store

    def close(self) -> None:
        """Release the store's lock (a no-op when read-only); the store is read-only after."""
        if self._lock is not None:
            self._lock.release()
            self._lock = None
        self.mode = "r"

    def __enter__(self) -> EpisodeStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _n_uncommitted_frames(self) -> int:
        return max((a.shape[0] - self.n_frames for a in self._arrays.values()), default=0)

    def _repair(self) -> None:
        """Undo the visible effects of an interrupted append (see the module docstring)."""
        for tmp in self.path.rglob("*.partial"):  # Zarr's temporary files of a killed write
            tmp.unlink(missing_ok=True)
        extra = self._n_uncommitted_frames()
        if self._n_uncommitted_ends:
            self._ends_array.resize((len(self._ends),))
            self._n_uncommitted_ends = 0
        n = self.n_frames
        for arr in self._arrays.values():
            if arr.shape[0] != n:
                arr.resize((n, *arr.shape[1:]))
        if len(self._attrs["seeds"]) != self.n_episodes:
            self._set_attr("seeds", self._attrs["seeds"][: self.n_episodes])
        if extra:
            log.warning("%s: discarded %d frames of an episode whose append was interrupted", self.path, extra)

    # --- reading -----------------------------------------------------------------------
    @property
    def n_episodes(self) -> int:
        return len(self._ends)

    @property
    def n_frames(self) -> int:
        return int(self._ends[-1]) if len(self._ends) else 0

    @property
    def episode_ends(self) -> np.ndarray:
        """(E,) int64 cumulative frame counts of the whole episodes."""
        return self._ends.copy()

    @property
    def attrs(self) -> dict[str, Any]:
        """Root attributes; ``seeds`` lists one seed (or None) per stored episode."""
        return {**self._attrs, "seeds": self.seeds}

    @property
    def seeds(self) -> list[int | None]:
        return list(self._attrs["seeds"][: self.n_episodes])

    @property
    def keys(self) -> list[str]:
        """Names of the arrays under ``data/``."""
        return sorted(self._arrays)

    def __len__(self) -> int:
        return self.n_episodes

    def array(self, key: str) -> CheckedArray:
        """The (N, ...) Zarr array ``data/<key>`` for chunked reads; only its first
        ``n_frames`` rows are committed."""
        if key not in self._arrays:
            raise StoreError(f"{self.path} has no array data/{key}; it has {self.keys}.")
        return CheckedArray(self._arrays[key], f"{self.path} data/{key}")

    def __repr__(self) -> str:
        return f"EpisodeStore({str(self.path)!r}, episodes={self.n_episodes}, frames={self.n_frames})"

    def episode(self, i: int) -> dict[str, np.ndarray]:
        """Episode ``i`` (negative counts from the end) as ``{key: (T_i, ...) array}``."""
        n = self.n_episodes
        if not -n <= i < n:
            raise IndexError(f"episode index {i} out of range for a store of {n} episodes.")
        i %= n
        start = int(self._ends[i - 1]) if i else 0
        stop = int(self._ends[i])
        return {k: self.array(k)[start:stop] for k in self._arrays}

    def content_hash(self, episodes: int | None = None, chunk: int = 4096) -> str:
        """A short hash of what the first ``episodes`` episodes (None: all) hold: the task,
        their lengths and every array's decoded values, not where the store lies or how it
        is compressed. Two copies of a store, at any paths, hash alike; a store that grew
        hashes alike over its old episodes."""
        n = self.n_episodes if episodes is None else episodes
        if not 0 <= n <= self.n_episodes:
            raise InputError(f"{self.path} holds {self.n_episodes} episodes, not {n}.")
        ends = self._ends[:n]
        described = {"task": self._attrs.get("task"), "ends": ends.tolist()}
        h = hashlib.sha256(json.dumps(described, sort_keys=True).encode())
        stop = int(ends[-1]) if n else 0
        for key in self.keys:
            arr = self.array(key)
            h.update(f"{key} {arr.dtype} {arr.shape[1:]}".encode())
            for i in range(0, stop, chunk):
                h.update(np.ascontiguousarray(arr[i:min(i + chunk, stop)]).tobytes())
        return h.hexdigest()[:16]

    def info(self) -> dict[str, Any]:
        """Summary: episodes, frames, per-array shape/dtype/chunks, fps, task, image size,
        bytes on disk (the whole directory) and the remaining attributes."""
        n = self.n_frames
        return {
            "path": str(self.path),
            "episodes": self.n_episodes,
            "frames": n,
            "arrays": {
                k: {"shape": (n, *a.shape[1:]), "dtype": str(a.dtype), "chunks": tuple(a.chunks)}
                for k, a in sorted(self._arrays.items())
            },
            "fps": self._attrs.get("fps"),
            "task": self._attrs.get("task"),
            "image_size": self._attrs.get("image_size"),
            "bytes_on_disk": dir_size(self.path),
            "attrs": {k: v for k, v in self._attrs.items() if k != "seeds"},
        }

    # --- writing -----------------------------------------------------------------------
    def append(self, episode: Mapping[str, np.ndarray], seed: int | None = None) -> None:
        """Append one episode ``{key: (T, ...) array}`` (T >= 1), all-or-nothing for readers.

        The keys, trailing shapes and dtype kinds must match the stored arrays (the first
        episode defines them).
        """
        if self.mode != "a":
            raise StoreError(f"{self.path} is open read-only; open it with mode 'a' to append.")
        episode = self._check_episode(episode)
        n0 = self.n_frames
        t = next(iter(episode.values())).shape[0]
        try:
            if self.n_episodes == 0:
                self._define_arrays(episode)
            # 1. data: grow every array to exactly n0 + t (this also drops any uncommitted tail)
            for key, value in episode.items():
                arr = self._arrays[key]
                arr.resize((n0 + t, *arr.shape[1:]))
                arr[n0:] = value
            # 2. seeds: an entry past n_episodes means nothing until episode_ends commits it
            self._set_attr("seeds", [*self._attrs["seeds"][: self.n_episodes], None if seed is None else int(seed)])
            # 3. commit
            self._commit(n0 + t)
        except BaseException:
            # e.g. a full disk: what reached the disk is uncommitted, so readers see the store
            # as it was; this object forgets what it believed and reads the disk again, so the
            # next append (which overwrites any uncommitted tail) starts from what is there
            self._load()
            raise

    def _commit(self, end: int) -> None:
        """Grow episode_ends by one entry: the single step that makes an append visible."""
        e = self.n_episodes
        self._ends_array.resize((e + 1,))
        self._ends_array[e] = end
        self._ends = np.append(self._ends, np.int64(end))

    def _check_episode(self, episode: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        if not episode:
            raise StoreError("an episode must hold at least one array.")
        out = {k: np.asarray(v) for k, v in episode.items()}
        lengths = {k: (v.shape[0] if v.ndim else 0) for k, v in out.items()}
        if len(set(lengths.values())) != 1 or min(lengths.values()) < 1:
            raise StoreError(f"episode arrays must share a leading length T >= 1, got lengths {lengths}.")
        if self.n_episodes == 0:
            return out
        if set(out) != set(self._arrays):
            raise StoreError(f"episode keys {sorted(out)} do not match the store's arrays {self.keys}.")
        for k, v in out.items():
            arr = self._arrays[k]
            if v.shape[1:] != arr.shape[1:] or not np.can_cast(v.dtype, arr.dtype, casting="same_kind"):
                raise StoreError(
                    f"episode array {k!r} is {v.shape[1:]} {v.dtype} per frame; "
                    f"the store holds {arr.shape[1:]} {arr.dtype}."
                )
            out[k] = v.astype(arr.dtype, copy=False)
        return out

    def _define_arrays(self, episode: Mapping[str, np.ndarray]) -> None:
        """(Re)create data arrays to match the first episode (an empty store may hold stale
        arrays from an interrupted first append)."""
        for key, value in episode.items():
            arr = self._arrays.get(key)
            if arr is not None and arr.shape[1:] == value.shape[1:] and arr.dtype == value.dtype:
                continue
            if arr is not None:
                del self._data[key]
            image_like = value.dtype == np.uint8 and value.ndim == 4
            self._arrays[key] = self._data.create_array(
                key,
                shape=(0, *value.shape[1:]),
                chunks=(chunk_frames(value.shape[1:], value.dtype), *value.shape[1:]),
                dtype=value.dtype,
                compressors=IMAGE_COMPRESSOR if image_like else LOWDIM_COMPRESSOR,
                fill_value=0,
                # an array the group does not list may still be half on disk (a first append
                # that failed between writing its metadata files): in an empty store it is stale
                overwrite=True,
            ).with_config({"write_empty_chunks": True})
        for key in set(self._arrays) - set(episode):
            del self._data[key]
            del self._arrays[key]

    def update_attrs(self, attrs: Mapping[str, Any]) -> None:
        """Set root attributes (JSON-serialisable) in one atomic rewrite of ``.zattrs``;
        ``seeds`` and ``store_version`` are the store's own and cannot be set."""
        if self.mode != "a":
            raise StoreError(f"{self.path} is open read-only; open it with mode 'a' to set attributes.")
        attrs = _settable(attrs)
        self._root.attrs.update(attrs)
        self._attrs.update(attrs)

    def _describe_anew(self, attrs: Mapping[str, Any]) -> None:
        """Replace every root attribute of this store, which holds no episodes, by ``attrs``."""
        assert self.mode == "a" and not self.n_episodes
        new = {**_settable(attrs), "store_version": self._attrs.get("store_version", STORE_VERSION), "seeds": []}
        if new != self._attrs:
            self._root.attrs.put(new)
            self._attrs = dict(self._root.attrs)

    def _set_attr(self, key: str, value: Any) -> None:
        self._root.attrs[key] = value  # rewrites .zattrs atomically
        self._attrs[key] = value
