"""Measure stage 1 (autoencoder): held-out reconstruction quality and speed.

    .venv/bin/python bench/bench_ae.py --run runs/ae [--frames 2000]

Reads a run directory made by `iwsim train ae` and writes bench/results/ae.json, ae.md,
ae_curve.png (held-out PSNR against training wall-clock) and ae_recon.png. Quality: PSNR
and SSIM of 1, 2 and 3-jump decodes of held-out frames (from the run's recorded split),
with the final checkpoint's EMA weights. Speed: batch-1 encode and 1-jump decode latency
(median of 200 calls, 2 threads) and training images/s from the run's log. Run it alone:
the two cores are shared by everything running.
"""

from __future__ import annotations

import argparse
import json
import platform
from pathlib import Path

import numpy as np
import torch

from iwsim.core.checkpoint import resolve_checkpoint
from iwsim.core.errors import reporting_errors
from iwsim.core.metrics import psnr, ssim
from iwsim.data.frames import FrameSource, to_model, to_uint8
from iwsim.data.store import EpisodeStore
from iwsim.eval.profiling import latency_ms
from iwsim.eval.records import command_line, with_command
from iwsim.world_model.codecs import load_codec
from iwsim.world_model.codecs.base import Codec, reconstruct

RESULTS = Path(__file__).parent / "results"


def quality(ae: Codec, frames: np.ndarray, jumps: tuple[int, ...]) -> tuple[dict, dict]:
    x = to_model(frames)
    out, recon = {}, {}
    with torch.inference_mode():
        for k in jumps:
            recon[k] = reconstruct(ae, x, k, chunk=100)
            a, b = (x + 1) / 2, (recon[k] + 1) / 2
            p, s = psnr(a, b), ssim(a, b)
            out[k] = {"psnr": p.mean().item(), "psnr_p5": p.quantile(0.05).item(), "ssim": s.mean().item()}
    return out, recon


def plot_curve(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    evals = [r for r in rows if "eval/psnr_1jump" in r]
    fig, ax = plt.subplots(figsize=(6.5, 4))
    for k in (1, 2, 3):
        key = f"eval/psnr_{k}jump"
        if key in evals[0]:
            ax.plot([r["elapsed_s"] / 60 for r in evals], [r[key] for r in evals], marker="o", ms=3,
                    label=f"{k} jump(s)")
    ax.axhline(32, color="k", ls=":", lw=1, label="target 32 dB")
    ax.set(xlabel="training wall-clock (min, 2 CPU cores)", ylabel="held-out PSNR (dB)",
           title="Stage 1 reconstruction during training")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", type=Path, default=Path("runs/ae"))
    ap.add_argument("--frames", type=int, default=2000, help="held-out frames to score")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    torch.set_num_threads(2)
    args.out.mkdir(parents=True, exist_ok=True)

    config = json.loads((args.run / "config.json").read_text())
    ckpt = resolve_checkpoint(args.run)
    ae = load_codec(ckpt)
    store = EpisodeStore.open(config["data"])
    held = FrameSource(store, config["split"]["heldout_episodes"])
    pick = np.linspace(0, len(held) - 1, min(args.frames, len(held))).round().astype(int)
    frames = held.frames(pick)
    scores, recon = quality(ae, frames, (1, 2, 3))

    x1 = to_model(frames[:1])
    speed = {}
    for mode in ("eager", "frozen"):
        if mode == "frozen":
            ae.freeze_for_inference()
        with torch.inference_mode():
            z1 = ae.encode(x1)
            g = torch.Generator().manual_seed(0)
            speed[mode] = {"encode_ms": latency_ms(lambda: ae.encode(x1)),  # noqa: B023  (timed right here)
                           "decode_1jump_ms": latency_ms(lambda: ae.decode(z1, None, 1, g.manual_seed(0)))}  # noqa: B023
    enc_ms, dec_ms = speed["eager"]["encode_ms"], speed["eager"]["decode_1jump_ms"]
    rows = [json.loads(line) for line in (args.run / "metrics.jsonl").read_text().splitlines()]
    train_rows = [r for r in rows if "images_per_s" in r]
    evals = [r for r in rows if "eval/psnr_1jump" in r]
    reached = next((r for r in evals if r["eval/psnr_1jump"] >= 32 and r["eval/ssim_1jump"] >= 0.95), None)
    plot_curve(rows, args.out / "ae_curve.png")
    n = 8
    import imageio.v2 as imageio

    grid = [np.concatenate(list(frames[:n]), axis=1)] + [np.concatenate(list(to_uint8(recon[k][:n])), axis=1)
                                                         for k in (1, 2, 3)]
    imageio.imwrite(args.out / "ae_recon.png", np.repeat(np.repeat(np.concatenate(grid), 2, 0), 2, 1))

    result = {
        "machine": f"{platform.machine()}, {torch.get_num_threads()} threads",
        "run": str(args.run), "checkpoint": ckpt.name, "config": config["model"],
        "heldout_frames": len(frames), "heldout_episodes": len(config["split"]["heldout_episodes"]),
        "quality": scores,
        "latency_batch1": speed,
        "train_images_per_s_median": float(np.median([r["images_per_s"] for r in train_rows])),
        "train_minutes": train_rows[-1]["elapsed_s"] / 60,
        "first_eval_meeting_target": reached and {"step": reached["step"], "minutes": reached["elapsed_s"] / 60},
    }
    command = command_line(__file__)
    (args.out / "ae.json").write_text(json.dumps(with_command(command, result), indent=2) + "\n")
    lines = [
        "# Stage 1 benchmark (`bench/bench_ae.py`)",
        "",
        f"`{command}`",
        "",
        f"Run `{args.run}` ({result['machine']}), checkpoint {ckpt.name}, trained "
        f"{result['train_minutes']:.1f} min at a median {result['train_images_per_s_median']:.0f} images/s.",
        f"Scored on {len(frames)} frames of {result['heldout_episodes']} held-out episodes.",
        "",
        "| decode | PSNR (dB) | PSNR 5th pct | SSIM |",
        "|---|---|---|---|",
    ]
    lines += [f"| {k} jump(s) | {v['psnr']:.2f} | {v['psnr_p5']:.2f} | {v['ssim']:.4f} |" for k, v in scores.items()]
    target = result["first_eval_meeting_target"]
    lines += [
        "",
        "Target (1 jump: PSNR >= 32 dB and SSIM >= 0.95 within 45 min): "
        + (f"first met at step {target['step']}, {target['minutes']:.1f} min." if target else "**not met**."),
        "",
        f"Latency at batch 1 (median of 200): encode **{enc_ms:.2f} ms**, 1-jump decode **{dec_ms:.2f} ms**; "
        f"after `Autoencoder.freeze_for_inference()`: encode {speed['frozen']['encode_ms']:.2f} ms, "
        f"decode {speed['frozen']['decode_1jump_ms']:.2f} ms.",
        "",
        "![curve](ae_curve.png)",
        "",
        "Held-out frames (top) and their 1, 2 and 3-jump reconstructions:",
        "",
        "![recon](ae_recon.png)",
        "",
    ]
    (args.out / "ae.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    raise SystemExit(reporting_errors("bench_ae.py", main))
