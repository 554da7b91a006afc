"""Camera views in an episode store: one convention for every reader and writer.

A store holds any number of named views of each frame. The first view is ``data/img`` (so
every tool that reads one camera, Diffusion Policy's single-camera configs included, reads
it unchanged); each further view ``<name>`` is ``data/img_<name>`` beside it, the same
(N, H, W, 3) uint8 layout. The root attribute ``cameras`` lists the views' names in order
(the first names ``data/img``). A store without it has one view, named by its ``camera``
attribute where an import recorded one, else :data:`DEFAULT_CAMERA`; so every store written
before views existed reads as one view.

In memory, a frame of V views is one array stacked along the channels, (..., H, W, 3V),
view v in channels 3v..3v+2 (:func:`stack_views`); what the Gymnasium envs observe is
``{camera: (H, W, 3)}`` (:func:`split_views`, :func:`first_view`).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from iwsim.core.errors import InputError

DEFAULT_CAMERA = "top"  # the tabletop tasks' one camera, and the name of a store's only view
IMAGE_KEY = "img"  # the first view's array
VIEW_PREFIX = "img_"  # a further view <name> is data/img_<name>
_NAME = re.compile(r"[a-z0-9][a-z0-9_]{0,31}")


def check_cameras(cameras: Iterable[str], what: str = "cameras") -> tuple[str, ...]:
    """``cameras`` as a tuple of distinct view names (lower-case letters, digits and ``_``,
    at most 32 characters), or an InputError naming the first bad one."""
    names = tuple(cameras)
    if not names:
        raise InputError(f"{what}: name at least one camera.")
    for name in names:
        if not isinstance(name, str) or not _NAME.fullmatch(name):
            raise InputError(f"{what}: camera name {name!r} must be 1-32 lower-case letters, digits or '_' "
                             "(starting with a letter or digit).")
    if len(set(names)) != len(names):
        raise InputError(f"{what}: camera names must be distinct, got {list(names)}.")
    return names


def parse_cameras(text: str) -> tuple[str, ...]:
    """The ``--cameras top,side`` flag's value as checked names."""
    return check_cameras([c.strip() for c in text.split(",")], "--cameras")


def view_key(cameras: tuple[str, ...], name: str) -> str:
    """The data array of view ``name`` in a store whose views are ``cameras``."""
    if name not in cameras:
        raise InputError(f"no camera {name!r}; the views are {', '.join(cameras)}.")
    return IMAGE_KEY if name == cameras[0] else VIEW_PREFIX + name


def view_keys(cameras: tuple[str, ...]) -> dict[str, str]:
    """{view name: data array} in view order."""
    return {name: view_key(cameras, name) for name in cameras}


def store_cameras(attrs: Mapping[str, Any], keys: Iterable[str] | None = None) -> tuple[str, ...]:
    """The views of a store with root attributes ``attrs`` (and, when given, data arrays
    ``keys``, checked to hold every view). A store without ``cameras`` has one view, named by
    its ``camera`` attribute (its last dotted part, without ``img_``: ``observation.images.top``
    and ``img_top`` are ``top``), else :data:`DEFAULT_CAMERA`."""
    raw = attrs.get("cameras")
    if raw is None:
        name = attrs.get("camera")
        name = name.rsplit(".", 1)[-1].lower() if isinstance(name, str) else DEFAULT_CAMERA
        name = name[len(VIEW_PREFIX):] if name.startswith(VIEW_PREFIX) else name  # a store's view imported alone
        cameras: tuple[str, ...] = (name if _NAME.fullmatch(name) else DEFAULT_CAMERA,)
    elif isinstance(raw, list | tuple):
        cameras = check_cameras(raw, "the store's 'cameras' attribute")
    else:
        raise InputError(f"the store's 'cameras' attribute must list camera names, got {raw!r}.")
    if keys is not None:
        have = set(keys)
        missing = [k for k in view_keys(cameras).values() if k not in have]
        if missing and len(cameras) > 1:
            raise InputError(f"the store names the views {list(cameras)} but holds no {', '.join(missing)}.")
    return cameras


def split_views(pixels: Any, cameras: tuple[str, ...]) -> dict[str, Any]:
    """An observation's ``pixels`` as {view: frame}: one array is the only view's frame, a
    mapping must name exactly ``cameras``."""
    if isinstance(pixels, Mapping):
        if set(pixels) != set(cameras):
            raise InputError(f"expected the views {list(cameras)}, got {list(pixels)}.")
        return {name: pixels[name] for name in cameras}
    if len(cameras) != 1:
        raise InputError(f"expected the views {list(cameras)} as a mapping, got one array.")
    return {cameras[0]: pixels}


def first_view(pixels: Any) -> Any:
    """The first view's frame of an observation's ``pixels`` (an array, or {view: frame}):
    what a one-camera reader (a pixel scorer, a scripted pixel policy) looks at."""
    return next(iter(pixels.values())) if isinstance(pixels, Mapping) else pixels


def stack_views(frames: list[np.ndarray]) -> np.ndarray:
    """The views' frames [(..., H, W, 3)] as one frame stacked along the channels (..., H, W, 3V)."""
    return frames[0] if len(frames) == 1 else np.concatenate(frames, axis=-1)


def unstack_views(frames: np.ndarray, views: int) -> list[np.ndarray]:
    """A frame of ``views`` views stacked along the channels (..., H, W, 3V) -> [(..., H, W, 3)]."""
    return [frames] if views == 1 else [frames[..., 3 * v:3 * v + 3] for v in range(views)]


def tile_views(frames: np.ndarray) -> np.ndarray:
    """Frames of views stacked along the channels (..., H, W, 3V) as pictures, the views one
    above the other: (..., V*H, W, 3)."""
    return np.concatenate(unstack_views(frames, frames.shape[-1] // 3), axis=-3)
