"""Image metrics on batches of frames in [0, 1], shape (B, C, H, W): one value per image.

MSE, PSNR, SSIM (Gaussian 11 x 11 window, sigma 1.5, as Wang et al. define it) and UIQI
are computed here. The learned and distribution metrics
(LPIPS, FID, FVD) need pretrained networks: see :mod:`iwsim.eval.features`.
"""

from __future__ import annotations

import torch
from torch.nn import functional as F

from iwsim.core.errors import InputError


def _check(a: torch.Tensor, b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    if a.ndim != 4 or a.shape != b.shape:
        raise InputError(f"expected two image batches (B, C, H, W) of one shape, got {tuple(a.shape)} and "
                         f"{tuple(b.shape)}.")
    return a.float(), b.float()


def mse(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Mean squared error per image; (B,)."""
    a, b = _check(a, b)
    return ((a - b) ** 2).flatten(1).mean(1)


def psnr(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Peak signal-to-noise ratio (dB) for images in [0, 1]; (B,). Identical images
    give 100 dB (the MSE is floored at 1e-10)."""
    return 10 * torch.log10(1.0 / mse(a, b).clamp_min(1e-10))


def ssim(a: torch.Tensor, b: torch.Tensor, sigma: float = 1.5, k1: float = 0.01, k2: float = 0.03) -> torch.Tensor:
    """Structural similarity (Wang et al. 2004) per image; (B,): 11 x 11 Gaussian window
    (sigma 1.5), K1 = 0.01, K2 = 0.03, data range 1, averaged over channels and pixels.

    Computed as torchmetrics' ``structural_similarity_index_measure`` does (the images are
    reflect-padded by half the window, so every pixel has a value; variances are floored at
    0), to float precision: a test holds the two together. Ours because importing
    torchmetrics takes seconds (scipy.signal, matplotlib), paid by every process that
    evaluates a codec.
    """
    a, b = _check(a, b)
    c, half = a.shape[1], int(3.5 * sigma + 0.5)
    x = torch.arange(-half, half + 1, dtype=a.dtype, device=a.device)
    g = torch.exp(-((x / sigma) ** 2) / 2)
    g = g / g.sum()
    window = (g[:, None] * g[None, :]).expand(c, 1, 2 * half + 1, 2 * half + 1)
    a, b = (F.pad(t, (half,) * 4, mode="reflect") for t in (a, b))
    mu_a, mu_b, aa, bb, ab = F.conv2d(torch.cat([a, b, a * a, b * b, a * b]), window, groups=c).chunk(5)
    var_a, var_b = (aa - mu_a**2).clamp_min(0), (bb - mu_b**2).clamp_min(0)
    c1, c2 = k1**2, k2**2
    s = (2 * mu_a * mu_b + c1) * (2 * (ab - mu_a * mu_b) + c2) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    return s.flatten(1).mean(1)


def uiqi(a: torch.Tensor, b: torch.Tensor, window: int = 8, tol: float = 1e-10) -> torch.Tensor:
    """Universal image quality index (Wang & Bovik 2002) per image; (B,).

    Q = 4 cov mu_a mu_b / ((var_a + var_b)(mu_a^2 + mu_b^2)) over sliding 8 x 8 windows
    (valid positions), averaged over windows and channels. Where a denominator term
    vanishes the authors' reference code defines Q by the remaining factor, and Q = 1
    where both vanish (identical flat patches). torchmetrics scores such patches 0 instead,
    so identical frames with a flat background would score below 1; hence our own.
    """
    a, b = (x.double() for x in _check(a, b))
    c = a.shape[1]
    k = torch.full((c, 1, window, window), 1.0 / window**2, dtype=torch.float64, device=a.device)
    mu_a, mu_b, aa, bb, ab = F.conv2d(torch.cat([a, b, a * a, b * b, a * b]), k, groups=c).chunk(5)
    var_a, var_b = (aa - mu_a**2).clamp_min(0), (bb - mu_b**2).clamp_min(0)
    cov = ab - mu_a * mu_b
    spread, level = var_a + var_b, mu_a**2 + mu_b**2
    flat, dark = spread <= tol, level <= tol
    q = torch.where(flat | dark, torch.ones_like(spread), 4 * cov * mu_a * mu_b / (spread * level).clamp_min(tol**2))
    q = torch.where(flat & ~dark, 2 * mu_a * mu_b / level.clamp_min(tol), q)
    q = torch.where(~flat & dark, 2 * cov / spread.clamp_min(tol), q)
    return q.flatten(1).mean(1).float()
