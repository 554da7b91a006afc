"""The figures of the evaluation: frames side by side, metric curves over rollout steps,
stability over a long rollout, PSNR per step. Written atomically, rendered off-screen."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

FIGURE_COLUMNS = 5  # frames a row: the context, then evenly spaced to the last step


def figure_steps(horizon: int, columns: int = FIGURE_COLUMNS) -> list[int]:
    """The steps a frames figure shows for a rollout of ``horizon`` steps: step 0 (the
    context frame), then ``columns - 1`` evenly spaced steps ending at ``horizon``
    (0, 48, 96, 144, 192 for 192 steps)."""
    return sorted({round(horizon * k / (columns - 1)) for k in range(columns)}) if horizon > 0 else [0]


def save_figure(fig, path: Path, dpi: int = 110) -> None:  # noqa: ANN001  (a matplotlib Figure)
    """Write ``fig`` to ``path`` atomically and close it."""
    import matplotlib.pyplot as plt

    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    os.replace(tmp, path)


def pyplot():  # noqa: ANN202  (the matplotlib.pyplot module)
    """matplotlib.pyplot on the off-screen Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def frames_figure(context: np.ndarray, truth: np.ndarray, preds: dict[str, np.ndarray], path: Path,
                  episodes: tuple[int, ...] = (0, 1)) -> None:
    """Rows truth, then each model, at :func:`figure_steps` of the rollout's length (step 0
    is the context frame), for the given episode indices. context (E, H, W, 3); truth and
    preds (E, S, H, W, 3)."""
    plt = pyplot()
    steps = figure_steps(truth.shape[1])
    episodes = tuple(e for e in episodes if e < len(truth))
    names = ["MuJoCo (truth)", *preds]
    fig, axes = plt.subplots(len(names) * len(episodes), len(steps), squeeze=False,
                             figsize=(1.3 * len(steps) + 1.6, 1.3 * len(names) * len(episodes)))
    for j, e in enumerate(episodes):
        for i, (name, video) in enumerate(zip(names, [truth, *preds.values()])):
            for k, s in enumerate(steps):
                ax = axes[j * len(names) + i, k]
                ax.imshow(context[e] if s == 0 else video[e, s - 1], interpolation="nearest")
                ax.set_xticks([])
                ax.set_yticks([])
                if j == 0 and i == 0:
                    ax.set_title(f"step {s}", fontsize=8)
                if k == 0:
                    ax.set_ylabel(f"{name}\nep. {j}" if i == 0 else name, fontsize=7, rotation=0, ha="right",
                                  va="center")
    fig.tight_layout()
    save_figure(fig, path)


def curves_figure(per_step: dict[str, dict[str, np.ndarray]], path: Path) -> None:
    """PSNR, SSIM and IoU error against rollout step, one line per model (+- std band)."""
    plt = pyplot()
    keys = [("psnr", "PSNR (dB)"), ("ssim", "SSIM"), ("iou_err", "|IoU pred - IoU true|")]
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for ax, (k, label) in zip(axes, keys):
        for name, v in per_step.items():
            m, s = v[k].mean(0), v[k].std(0)
            x = np.arange(1, len(m) + 1)
            ax.plot(x, m, label=name, lw=1.2)
            ax.fill_between(x, m - s, m + s, alpha=0.12)
        ax.set_xlabel("rollout step")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path)


def stability_figure(rows: dict[str, dict[str, np.ndarray]], path: Path, window: int = 50) -> None:
    """Frame mean, frame std, block pixels and block detectability over a long rollout
    (moving averages over ``window`` recorded points), one line per model and MuJoCo."""
    plt = pyplot()
    fig, axes = plt.subplots(4, 1, figsize=(9, 10), sharex=True)
    for name, r in rows.items():
        k = max(1, min(window, len(r["step"])))

        def smooth(y: np.ndarray, k: int = k) -> np.ndarray:
            return np.convolve(y.astype(np.float64), np.ones(k) / k, mode="valid")

        x = r["step"][k - 1:]
        style = {"color": "black", "lw": 1.5} if name == "mujoco" else {"lw": 1}
        for ax, key in zip(axes, ("mean", "std", "block", "detected")):
            ax.plot(x, smooth(r[key]), label="MuJoCo (same actions)" if name == "mujoco" else name, **style)
    for ax, label in zip(axes, ("frame mean", "frame std", "block pixels", "block detected (T fit IoU >= 0.8)")):
        ax.set_ylabel(label, fontsize=8)
        ax.grid(alpha=0.3)
    axes[3].set_ylim(-0.02, 1.02)
    axes[0].legend(fontsize=7, loc="upper right")
    axes[3].set_xlabel(f"rollout step (moving average over {window} points)")
    fig.tight_layout()
    save_figure(fig, path)


def plot_psnr(curves: dict[str, np.ndarray], path: Path, bands: dict[str, np.ndarray] | None = None,
              target: float | None = None) -> Path:
    """PSNR (dB) against rollout step, one line per curve (optional +-std bands)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for name, y in curves.items():
        x = np.arange(1, len(y) + 1)
        ax.plot(x, y, label=name)
        if bands and name in bands:
            ax.fill_between(x, y - bands[name], y + bands[name], alpha=0.2)
    if target is not None:
        ax.axhline(target, color="grey", linestyle="--", linewidth=1, label=f"target {target:g} dB")
    ax.set_xlabel("rollout step")
    ax.set_ylabel("PSNR (dB)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    save_figure(fig, path, dpi=120)
    return path

