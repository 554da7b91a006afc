"""What every format shares: episodes as dicts of arrays, one-line errors, atomic outputs,
frame resizing and writing an episode store from imported episodes.

An episode, between a format and the store, is ``{"img": (T, H, W, 3) uint8, "state":
(T, S) float32, "action": (T, A) float32, ...}`` with T >= 1 (other keys are kept). A
source with several cameras gives one more ``img_<name>`` array per further camera, laid
out like ``img``, and the reader's attributes name the views (``cameras``, see
:mod:`iwsim.data.views` and :class:`SourceViews`).
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import re
import shutil
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from iwsim.core.errors import InputError
from iwsim.core.lock import LOCK_NAME, DirLock, remove_stale_temps, temp_sibling
from iwsim.core.resources import read_capped, require_memory
from iwsim.data import views
from iwsim.data.store import EpisodeStore

REQUIRED = ("img", "state", "action")


class FormatError(InputError):
    """A file that does not follow its format; the message names the file, key and episode."""


# A camera frame larger than this is not one (robot cameras give a few megapixels; imports
# resize to the model's 64-128 px): a frame's declared size is checked before it is decoded.
MAX_IMAGE_PIXELS = 4096 * 4096
EIGHT_BIT_MODES = ("1", "L", "LA", "P", "PA", "RGB", "RGBA", "RGBX", "CMYK", "YCbCr")  # Pillow's 8-bit modes


def decode_images(cells: Sequence[bytes], at: str, formats: tuple[str, ...] | None = None,
                  ids: Sequence[int] | None = None) -> np.ndarray:
    """Encoded frames (PNG, JPEG, ...; ``formats`` limits which) -> (T, H, W, 3) uint8 RGB.
    Each frame's declared size is bounded (:data:`MAX_IMAGE_PIXELS`) and the T frames' decoded
    bytes checked against the memory available before anything is decoded; frames must be
    of one size and 8 bits a channel (16-bit ones would be clipped to 255). A FormatError
    names the frame (``ids[k]``, else k) otherwise."""
    from PIL import Image

    frames: list[np.ndarray] = []
    for k, data in enumerate(cells):
        t = k if ids is None else ids[k]
        try:
            with Image.open(io.BytesIO(data), formats=formats) as im:
                (w, h), mode = im.size, im.mode
                if w * h > MAX_IMAGE_PIXELS:
                    raise FormatError(f"{at}: frame {t} is {w} x {h} pixels, more than a camera frame iwsim imports "
                                      f"({MAX_IMAGE_PIXELS} pixels).")
                if frames and (h, w) != frames[0].shape[:2]:
                    raise FormatError(f"{at}: frame {t} is {w} x {h} pixels, the first is {frames[0].shape[1]} x "
                                      f"{frames[0].shape[0]}.")
                if mode not in EIGHT_BIT_MODES:
                    raise FormatError(f"{at}: frame {t} has {mode!r} pixels; expected 8 bits a channel (RGB, RGBA, "
                                      "grey or palette).")
                if not frames:
                    require_memory(len(cells) * w * h * 3, f"{at}: {len(cells)} frames of {w} x {h} pixels")
                frames.append(np.asarray(im.convert("RGB")))
        except InputError:
            raise
        except Image.DecompressionBombError as e:  # Pillow's own bound, above ours, at opening
            raise FormatError(f"{at}: frame {t} declares more pixels than a camera frame iwsim imports "
                              f"({MAX_IMAGE_PIXELS}): {reason(e)}") from None
        except (OSError, ValueError, SyntaxError, TypeError) as e:
            what = formats[0] if formats is not None and len(formats) == 1 else "image"
            raise FormatError(f"{at}: frame {t} is not a readable {what} ({reason(e)}).") from None
    if not frames:
        raise FormatError(f"{at}: the episode is empty.")
    return np.stack(frames)


META_MAX_BYTES = 256 << 20  # a metadata file (info.json, episodes.jsonl, ...) larger than this is not one


def read_meta(path: Path) -> str:
    """The text of a metadata file, read with a size cap: a FormatError for anything but a
    regular file (a symlink to ``/dev/zero`` would be read until memory ran out) or a file
    over :data:`META_MAX_BYTES`. A missing file is a FileNotFoundError, as for ``read_text``."""
    return read_capped(path, META_MAX_BYTES, FormatError).decode()


def where(path: str | os.PathLike, key: str | None = None, episode: int | None = None) -> str:
    """``path`` [key 'k'] [episode i], for error messages."""
    out = str(path)
    if key is not None:
        out += f" key '{key}'"
    if episode is not None:
        out += f" (episode {episode})"
    return out


def reason(e: BaseException) -> str:
    """The first line of an exception's message (or its type), for one-line errors."""
    lines = str(e).strip().strip("\"'").splitlines()
    return lines[0] if lines else type(e).__name__


def positive_int(value: Any) -> int | None:
    """``value`` as an integer >= 1 (rounded), or None if it is not one (attributes of
    other tools' files are often floats, strings or arrays)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return int(round(v)) if math.isfinite(v) and v >= 1 else None


def check_episode(ep: Mapping[str, np.ndarray], at: str, view_keys: Sequence[str] = (views.IMAGE_KEY,)
                  ) -> dict[str, np.ndarray]:
    """An episode with the required arrays (and the frames of every view in ``view_keys``,
    ``img`` first), equal lengths T >= 1, RGB uint8 frames and finite float state and action
    (cast to float32); else a FormatError naming ``at``."""
    missing = [k for k in (*REQUIRED, *view_keys) if k not in ep]
    if missing:
        raise FormatError(f"{at}: missing {', '.join(dict.fromkeys(missing))}.")
    out = {k: np.asarray(v) for k, v in ep.items()}
    for key in view_keys:
        img = out[key]
        if img.dtype != np.uint8 or img.ndim != 4 or img.shape[-1] != 3:
            what = "frames" if key == views.IMAGE_KEY else f"'{key}' frames"
            raise FormatError(f"{at}: {what} must be uint8 (T, H, W, 3), got {img.dtype} {img.shape}.")
    counts = {k: len(out[k]) for k in view_keys}
    if len(set(counts.values())) != 1:
        raise FormatError(f"{at}: the views differ in frame count: "
                          f"{', '.join(f'{k} {n}' for k, n in counts.items())}; every view needs one frame a step.")
    lengths = {k: (len(v) if v.ndim else 0) for k, v in out.items()}
    if len(set(lengths.values())) != 1:
        raise FormatError(f"{at}: arrays differ in length: {lengths}.")
    if lengths["img"] < 1:
        raise FormatError(f"{at}: the episode is empty.")
    for k in ("state", "action"):
        v = out[k]
        if v.ndim == 1:
            v = v[:, None]
        if v.ndim != 2 or not np.issubdtype(v.dtype, np.number):
            raise FormatError(f"{at}: '{k}' must be numbers of shape (T, D), got {v.dtype} {v.shape}.")
        v = v.astype(np.float32)
        if not np.isfinite(v).all():
            raise FormatError(f"{at}: '{k}' holds non-finite values.")
        out[k] = v
    return out


_NOT_NAME = re.compile(r"[^a-z0-9_]+")


def view_name(source: str, prefixes: Sequence[str] = (), suffixes: Sequence[str] = ()) -> str:
    """A source's camera name as a view name (:func:`iwsim.data.views.check_cameras`): its last
    dotted part (as :func:`~iwsim.data.views.store_cameras` reads a ``camera`` attribute),
    without the first of ``prefixes`` / ``suffixes`` it has (kept when nothing would remain),
    lower-cased, every run of other characters as one ``_``, at most 32 characters:
    ``observation.images.wrist_left`` -> ``wrist_left``, with the suffix ``_image``
    ``agentview_image`` -> ``agentview``, ``Cam-High`` -> ``cam_high``."""
    name = source.rsplit(".", 1)[-1]
    for p in prefixes:
        if name.startswith(p) and len(name) > len(p):
            name = name[len(p):]
            break
    for x in suffixes:
        if name.endswith(x) and len(name) > len(x):
            name = name[:-len(x)]
            break
    name = _NOT_NAME.sub("_", name.lower()).strip("_")[:32].rstrip("_")
    return name or "camera"


@dataclass(frozen=True)
class SourceViews:
    """The cameras a reader takes from a source, first view first: ``sources`` their names
    in the source, ``names`` the store's view names (distinct, valid)."""

    sources: tuple[str, ...]
    names: tuple[str, ...]

    @classmethod
    def of(cls, sources: Sequence[str], names: Sequence[str] | None = None, *, prefixes: Sequence[str] = (),
           suffixes: Sequence[str] = ()) -> SourceViews:
        """Views of ``sources``, named ``names`` or, by default, by :func:`view_name`; a name
        that two cameras would share gets ``_2``, ``_3``, ... on the later ones."""
        if names is None:
            names = [view_name(s, prefixes, suffixes) for s in sources]
        unique: list[str] = []
        for name in names:
            candidate, k = name, 2
            while candidate in unique:
                suffix = f"_{k}"
                candidate, k = name[:32 - len(suffix)] + suffix, k + 1
            unique.append(candidate)
        return cls(tuple(sources), views.check_cameras(unique))

    @property
    def keys(self) -> dict[str, str]:
        """{source camera: the episode's array}: ``img`` for the first, ``img_<name>`` after."""
        return dict(zip(self.sources, views.view_keys(self.names).values()))

    def attrs(self) -> dict[str, Any]:
        """The store attributes that record them: one camera as ever (``camera``: its source
        name), several as ``cameras`` (view names) and ``source_cameras`` (source names)."""
        if len(self.sources) == 1:
            return {"camera": self.sources[0]}
        return {"cameras": list(self.names), "source_cameras": list(self.sources)}


def store_views(store: EpisodeStore) -> dict[str, str]:
    """{view name: data array} of ``store`` in view order (checked to hold every view)."""
    return views.view_keys(views.store_cameras(store.attrs, store.keys))


@contextlib.contextmanager
def output_dir(out: str | os.PathLike, force: bool = False) -> Iterator[Path]:
    """A temporary directory next to ``out``, renamed to ``out`` when the block succeeds and
    removed when it fails, so ``out`` never holds a half-written result.

    The temporary directory is locked while it is written (see :mod:`iwsim.core.lock`), so
    the next run for ``out`` can tell those of killed runs from live ones and removes them."""
    out = Path(out)
    if out.exists() and not force:
        raise FileExistsError(f"{out} already exists; choose another output path.")
    out.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(out)
    tmp = temp_sibling(out)
    tmp.mkdir()
    try:
        with DirLock(tmp) as lock:
            yield tmp
            lock.unlink()  # not part of the result
            if out.exists():
                shutil.rmtree(out)
            os.rename(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


RESIZE_BYTES_PER_VALUE = 9  # the float32 interpolation, its rounded float32 copy, the uint8 result


def check_resize_memory(frames: int, size: int, what: str, n_views: int = 1) -> None:
    """Refuse to resize ``frames`` frames of each of ``n_views`` views to ``size`` x ``size``
    when the buffers cannot fit (counted for all views at once: an upper bound)."""
    require_memory(frames * n_views * size * size * 3 * RESIZE_BYTES_PER_VALUE, what)


def resize_frames(frames: np.ndarray, size: int) -> np.ndarray:
    """uint8 (T, H, W, 3) -> (T, size, size, 3): a centred square crop, then area
    averaging when shrinking (bilinear when growing)."""
    import torch
    from torch.nn import functional as F

    t, h, w, _ = frames.shape
    if (h, w) == (size, size):
        return frames
    s = min(h, w)
    top, left = (h - s) // 2, (w - s) // 2
    x = torch.from_numpy(np.ascontiguousarray(frames[:, top:top + s, left:left + s])).permute(0, 3, 1, 2).float()
    mode = "area" if s >= size else "bilinear"
    y = F.interpolate(x, size=(size, size), mode=mode, **({} if mode == "area" else {"align_corners": False}))
    return y.round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1).numpy()


def store_episodes(store: EpisodeStore) -> Iterator[dict[str, np.ndarray]]:
    """The store's episodes, one at a time."""
    for i in range(store.n_episodes):
        yield store.episode(i)


def write_store(out: str | os.PathLike, episodes: Iterable[tuple[dict[str, np.ndarray], int | None]],
                attrs: Mapping[str, Any], image_size: int | None = None, progress: bool = True,
                total: int | None = None, force: bool = False) -> EpisodeStore:
    """An episode store at ``out`` from ``(episode, seed)`` pairs (the frames of every view
    that ``attrs`` names resized to ``image_size`` when given), written under a temporary
    name and renamed at the end. The views' frames must be of one size."""
    from tqdm import tqdm

    cameras = views.store_cameras(attrs)
    keys = views.view_keys(cameras)
    with output_dir(out, force) as tmp:
        store = EpisodeStore.create(tmp / "store.zarr", dict(attrs))
        for i, (ep, seed) in enumerate(tqdm(episodes, total=total, unit="ep", desc=f"import {Path(out).name}",
                                            disable=not progress)):
            missing = [k for k in keys.values() if k not in ep]
            if missing:
                raise FormatError(f"episode {i}: holds no {', '.join(missing)} for the views {list(cameras)}.")
            if image_size is not None:
                t = len(ep[views.IMAGE_KEY])
                check_resize_memory(t, image_size, f"resizing an episode of {t} frames"
                                    f"{f' of {len(keys)} views' if len(keys) > 1 else ''} to "
                                    f"{image_size}x{image_size}", n_views=len(keys))
                ep = {**ep, **{k: resize_frames(ep[k], image_size) for k in keys.values()}}
            sizes = {name: ep[k].shape[1:3] for name, k in keys.items()}
            if len(set(sizes.values())) > 1:
                raise FormatError(f"episode {i}: the views' frames differ in size ("
                                  f"{', '.join(f'{n} {h}x{w}' for n, (h, w) in sizes.items())}); import with "
                                  "--image-size to give them one size.")
            store.append(ep, seed=seed)
        if store.n_episodes == 0:
            raise FormatError(f"no episodes to write to {out}.")
        store.close()
        for child in (tmp / "store.zarr").iterdir():
            if child.name == LOCK_NAME:  # the store was only ever ours; tmp's own lock stays in place
                child.unlink()
                continue
            os.rename(child, tmp / child.name)
        (tmp / "store.zarr").rmdir()
    return EpisodeStore.open(out, "r")
