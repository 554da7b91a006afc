"""The codecs by kind: build one from its config, load one from a stage-1 or world-model checkpoint."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Protocol

import torch

from iwsim.core.checkpoint import CheckpointError, build_within_memory, load_json, load_model_dir
from iwsim.core.config import from_dict
from iwsim.core.errors import InputError
from iwsim.world_model.codecs.base import DEFAULT_KIND, KIND, Codec
from iwsim.world_model.codecs.consistency import Autoencoder
from iwsim.world_model.codecs.conv import ConvCodec

WM_KIND = "world_model"  # a world-model checkpoint's kind (iwsim.world_model.model.KIND)


class CodecClass(Protocol):
    """A codec's class: its name in checkpoints, its config's class, and the codec from a config."""

    kind: str

    @property
    def config_class(self) -> type: ...

    def __call__(self, cfg: Any) -> Codec: ...


CODECS: dict[str, CodecClass] = {cls.kind: cls for cls in (Autoencoder, ConvCodec)}


def codec_class(kind: str) -> CodecClass:
    if kind not in CODECS:
        raise InputError(f"unknown codec {kind!r}; expected one of {', '.join(CODECS)}.")
    return CODECS[kind]


def kind_of(cfg: Any) -> str:
    """The kind of codec a config (an ``AE_PRESETS`` entry) is for."""
    for kind, cls in CODECS.items():
        if type(cfg) is cls.config_class:
            return kind
    raise InputError(f"no codec takes a {type(cfg).__name__}.")


def build_codec(kind: str, config: dict[str, Any]) -> Codec:
    """A codec of ``kind`` with fresh weights from its config as ``to_dict`` wrote it."""
    cls = codec_class(kind)
    return cls(from_dict(cls.config_class, config))


def world_model_codec(config: dict[str, Any]) -> tuple[str, Any, Any]:
    """(weights prefix, codec kind, codec config) of a world-model ``config.json``, the last
    two as the JSON holds them (unchecked, possibly None); a checkpoint from before the codec
    seam holds the consistency autoencoder as ``ae``."""
    if "codec" in config:
        part = config["codec"] if isinstance(config["codec"], dict) else {}
        return "codec", part.get("kind"), part.get("config")
    return "ae", DEFAULT_KIND, config.get("ae")


def load_codec(path: str | Path, device: str | torch.device = "cpu") -> Codec:
    """A stage-1 run's checkpoint (``model.safetensors`` + ``config.json`` of kind
    ``autoencoder``, naming its codec; none named: the consistency autoencoder), or the
    codec of a world-model checkpoint."""
    path = Path(path)
    is_world_model = (path / "config.json").is_file() and load_json(path / "config.json").get("kind") == WM_KIND
    config, tensors = load_model_dir(path, WM_KIND if is_world_model else KIND)
    if is_world_model:
        prefix, kind, cfg = world_model_codec(config)
        tensors = {k[len(prefix) + 1:]: v for k, v in tensors.items() if k.startswith(prefix + ".")}
    else:
        kind, cfg = config.get("codec", DEFAULT_KIND), config.get("model")
    try:
        codec = build_within_memory(lambda: build_codec(kind, cfg), f"the codec of {path}")
    except (TypeError, ValueError, KeyError, AttributeError) as e:
        raise CheckpointError(f"{path / 'config.json'} is not a codec config: {e}") from None
    try:
        codec.load_state_dict(tensors)
    except RuntimeError as e:
        raise CheckpointError(f"{path / 'model.safetensors'} does not match its config: "
                              f"{' '.join(str(e).split())[:200]}") from None
    return codec.to(device).eval()
