"""The benchmark's video metrics: per-frame scores (MSE, PSNR, SSIM, UIQI, LPIPS) and the
distances between sets of videos (FID, FVD), with the networks they need when their
weights are present (:mod:`iwsim.eval.features`)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from iwsim.core.errors import InputError
from iwsim.core.metrics import mse, psnr, ssim, uiqi
from iwsim.data.frames import to_model
from iwsim.eval import features as feats

log = logging.getLogger(__name__)

FRAME_METRICS = ("mse", "psnr", "ssim", "uiqi", "lpips")  # one value per frame
SET_METRICS = ("fid", "fvd")  # one value per model (distances between sets)
METRICS = (*FRAME_METRICS, *SET_METRICS, "iou_err")
LOWER_IS_BETTER = {"mse", "lpips", "fid", "fvd", "iou_err"}
NEEDS = {"lpips": feats.LPIPS_FILE, "fid": feats.INCEPTION_FILE, "fvd": feats.I3D_FILE}
FVD_CLIP = 16  # frames per FVD clip (Unterthiner et al. 2018)


@dataclass
class FeatureNets:
    """The pretrained networks found in the weights directory; ``missing`` maps each
    metric without its network to the reason shown in the report."""

    lpips: torch.nn.Module | None = None
    inception: torch.nn.Module | None = None
    i3d: torch.nn.Module | None = None
    missing: dict[str, str] = field(default_factory=dict)

    @classmethod
    def load(cls, directory: Path | None = None, device: torch.device | str = "cpu") -> FeatureNets:
        out = cls()
        for metric, attr, loader in (("lpips", "lpips", feats.load_lpips), ("fid", "inception", feats.load_inception),
                                     ("fvd", "i3d", feats.load_i3d)):
            try:
                setattr(out, attr, loader(directory, device))
            except feats.WeightsMissing as e:
                out.missing[metric] = f"unavailable: {e.filename} not found"
        return out


def _images(frames: np.ndarray, device: torch.device) -> torch.Tensor:
    """uint8 (N, H, W, 3) -> float (N, 3, H, W) in [0, 1]."""
    return ((to_model(frames) + 1) / 2).to(device)


@torch.inference_mode()
def frame_metrics(truth: np.ndarray, pred: np.ndarray, nets: FeatureNets | None = None,
                  chunk: int = 256, device: torch.device | str = "cpu") -> dict[str, np.ndarray]:
    """Per-frame MSE, PSNR, SSIM, UIQI (and LPIPS when its network is given) of uint8
    videos (E, S, H, W, 3) on [0, 1] images; each (E, S)."""
    if truth.shape != pred.shape or truth.ndim != 5:
        raise InputError(f"expected two videos (E, S, H, W, 3) of one shape, got {truth.shape} and {pred.shape}.")
    fns: dict[str, Callable] = {"mse": mse, "psnr": psnr, "ssim": ssim, "uiqi": uiqi}
    if nets is not None and nets.lpips is not None:
        fns["lpips"] = nets.lpips
    lead = truth.shape[:2]
    t, p = truth.reshape(-1, *truth.shape[2:]), pred.reshape(-1, *pred.shape[2:])
    out: dict[str, list] = {k: [] for k in fns}
    dev = torch.device(device)
    for i in range(0, len(t), chunk):
        a, b = _images(t[i:i + chunk], dev), _images(p[i:i + chunk], dev)
        for k, fn in fns.items():
            out[k].append(fn(b, a).float().cpu())
    return {k: torch.cat(v).numpy().reshape(lead) for k, v in out.items()}


@torch.inference_mode()
def inception_features(net: torch.nn.Module, video: np.ndarray, chunk: int = 64) -> np.ndarray:
    """FID features (N, 2048) of every frame of uint8 videos (..., H, W, 3)."""
    frames = video.reshape(-1, *video.shape[-3:])
    dev = next(net.parameters()).device
    return np.concatenate([net(_images(frames[i:i + chunk], dev)).double().cpu().numpy()
                           for i in range(0, len(frames), chunk)])


@torch.inference_mode()
def i3d_features(net: torch.nn.Module, video: np.ndarray, clip: int = FVD_CLIP, chunk: int = 4) -> np.ndarray:
    """FVD features (N, 400) of the non-overlapping ``clip``-frame clips of uint8 videos
    (E, S, H, W, 3): E * (S // clip) clips."""
    e, s = video.shape[:2]
    if s < clip:
        raise InputError(f"FVD needs videos of at least {clip} frames, got {s}.")
    clips = video[:, :s // clip * clip].reshape(-1, clip, *video.shape[2:])
    dev = next(net.parameters()).device
    out = []
    for i in range(0, len(clips), chunk):
        x = _images(clips[i:i + chunk].reshape(-1, *video.shape[2:]), dev)
        out.append(net(x.unflatten(0, (-1, clip))).double().cpu().numpy())
    return np.concatenate(out)


def set_metrics(truth_feats: dict[str, np.ndarray], pred: np.ndarray, nets: FeatureNets) -> dict[str, float]:
    """FID and FVD of predicted videos against the truth's features (those available)."""
    out = {}
    if nets.inception is not None:
        out["fid"] = feats.frechet_distance(truth_feats["fid"], inception_features(nets.inception, pred))
    if nets.i3d is not None:
        out["fvd"] = feats.frechet_distance(truth_feats["fvd"], i3d_features(nets.i3d, pred))
    return out


def summarize(per_frame: dict[str, np.ndarray], sets: dict[str, float]) -> dict[str, dict[str, float]]:
    """Mean and std over episodes of each per-episode mean, and the mean at the last step."""
    out = {}
    for k, v in per_frame.items():
        ep = v.mean(1)
        out[k] = {"mean": float(ep.mean()), "std": float(ep.std()), "last": float(v[:, -1].mean()),
                  "last_std": float(v[:, -1].std())}
    for k, value in sets.items():
        out[k] = {"mean": float(value)}
    return out
