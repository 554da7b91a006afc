"""The numeric path a network runs on: float32, or bf16 autocast where the hardware has it.

On a CPU, bf16 pays only where the cores have the instructions: AMX (``amx_bf16``, Intel
Xeons since Sapphire Rapids, whose oneDNN kernels run bf16 convolutions and matrix
products several times faster than float32) or AVX-512-BF16 (``avx512_bf16``, e.g. AMD
EPYC Zen 4, which gains less). Elsewhere PyTorch emulates bf16 and it is many times
slower, so the flags are read at run time (``/proc/cpuinfo``), never assumed. CUDA always
has it.

A :class:`Precision` is what a run or a model uses: bf16 autocast or not (the weights stay
float32, so a checkpoint is the same whichever path trained it or runs it). What it pays on
which step is measured by ``bench/speed.py`` (``bench/results/speed/``); a training run
records the path it took in every row of its ``metrics.jsonl``.
"""

from __future__ import annotations

import contextlib
import functools
import platform
from dataclasses import dataclass
from pathlib import Path

import torch

from iwsim.core.errors import InputError


@dataclass(frozen=True)
class CpuInfo:
    """The CPU's model name and instruction-set flags (as ``lscpu`` shows them)."""

    model: str
    flags: frozenset[str]

    @property
    def bf16(self) -> str | None:
        """The fastest bf16 instructions: "amx", "avx512_bf16" or None (bf16 would be emulated)."""
        if "amx_bf16" in self.flags:
            return "amx"
        if "avx512_bf16" in self.flags:
            return "avx512_bf16"
        return None


@functools.cache
def cpu_info() -> CpuInfo:
    """This machine's CPU, from ``/proc/cpuinfo`` (Linux); elsewhere no flags, so no bf16."""
    model, flags = platform.processor() or platform.machine(), frozenset[str]()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name":
                model = value.strip()
            elif key.strip() == "flags":
                flags = frozenset(value.split())
            if model and flags:
                break
    return CpuInfo(model, flags)


def bf16_available(device: torch.device) -> bool:
    """Whether bf16 autocast runs at hardware speed on ``device``."""
    return device.type == "cuda" or (device.type == "cpu" and cpu_info().bf16 is not None)


def require_bf16(device: torch.device, what: str) -> None:
    """Refuse ``what`` (a flag, in the user's words) on a device without bf16 instructions."""
    if not bf16_available(device):
        raise InputError(f"{what}: this CPU ({cpu_info().model}) has neither AMX nor AVX-512-BF16, so bf16 would be "
                         "emulated and many times slower than float32; leave it out (float32 is the default).")


@dataclass(frozen=True)
class Precision:
    """bf16 autocast on or off (see the module docstring). The layout is the networks' own:
    channels-last activations paid for the codec's decoder, not for a training step
    (``bench/results/speed``: PyTorch's GroupNorm on channels-last bf16 costs more than the
    convolutions gain)."""

    bf16: bool = False

    def autocast(self, device: torch.device) -> contextlib.AbstractContextManager:
        """The autocast context of this path on ``device`` (a no-op for float32)."""
        if not self.bf16:
            return contextlib.nullcontext()
        return torch.autocast(device.type, dtype=torch.bfloat16)
