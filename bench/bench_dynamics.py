"""Measure stage 2 (the world model): open-loop accuracy, speed and long-rollout stability.

    .venv/bin/python bench/bench_dynamics.py --checkpoint runs/dyn/checkpoints/last [--run runs/dyn]

Writes bench/results/dynamics.{json,md} and the plots dynamics_psnr.png,
dynamics_rollout.png and dynamics_stability.png. Run it alone: the two cores are shared.

- Accuracy: 192-step open-loop rollouts of the held-out episodes of the run's split
  (context = the first frame, then the recorded actions), PSNR and SSIM per step against
  the recorded frames, and the pixel-IoU error.
- Speed: ``WorldModel.step`` (dynamics + 1-jump decode) at batch 1 and 64, the streaming
  dynamics step alone, and, for comparison, one uncached forward over a whole window.
- Stability: a long rollout (9000 steps = 10 min at 15 FPS) under the scripted play
  policy's actions, driven by MuJoCo, with memory, block detection and frame statistics
  over time against the MuJoCo frames of the same actions.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from iwsim.data.store import EpisodeStore
from iwsim.envs import make_env
from iwsim.envs.pixels import block_fraction, estimate_block_pose, pixel_iou
from iwsim.envs.policies import make_policy
from iwsim.eval.rollout import frame_scores, open_loop, plot_psnr
from iwsim.world_model import WorldModel

from bench_ae import latency_ms  # bench/ is on the path when a script here runs

RESULTS = Path(__file__).parent / "results"


def rss_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def speed(wm: WorldModel, frame: np.ndarray, n: int = 200) -> dict[str, float]:
    out = {}
    a1 = np.zeros((1, 4), np.float32)
    wm.reset(frame[None])
    out["step_ms_batch1"] = latency_ms(lambda: wm.step(a1), n)
    a1n = wm.normalize_actions(a1)
    out["dynamics_step_ms_batch1"] = latency_ms(lambda: wm.step_latent(a1n), n)
    z = wm.encode(frame[None])
    out["decode_ms_batch1"] = latency_ms(lambda: wm.decode_latents(z), n)
    # what a step would cost without the cache: one pass over a whole window
    cfg = wm.cfg.dynamics
    w = cfg.window
    x = torch.randn(1, w, cfg.latent_channels, *z.shape[-2:])
    lv = torch.full((1, w), 15)
    acts, known = torch.zeros(1, w, cfg.action_dim), torch.ones(1, w)
    times, is_ctx = torch.arange(w), torch.tensor([True] * (w - 1) + [False])
    with torch.inference_mode():
        out["uncached_window_forward_ms_batch1"] = latency_ms(
            lambda: wm.dynamics(x, lv, lv, acts, known, times, is_ctx), n // 4)
    b = 64
    wm.reset(np.repeat(frame[None], b, 0))
    a64 = np.zeros((b, 4), np.float32)
    ms = latency_ms(lambda: wm.step(a64), 20)
    out["step_ms_batch64"] = ms
    out["frames_per_s_batch1"] = 1000 / out["step_ms_batch1"]
    out["frames_per_s_batch64"] = b * 1000 / ms
    return out


def stability(wm: WorldModel, steps: int, seed: int) -> dict:
    """Drive MuJoCo with the play policy and feed the same actions to the world model."""
    env = make_env("pusht", wm.image_size)
    pol = make_policy("play", seed)
    obs, info = env.reset(seed=seed)
    pol.reset(obs, info)
    wm.reset(obs["pixels"][None], seed=seed)
    rows = {k: [] for k in ("wm_mean", "wm_std", "wm_block", "true_mean", "true_std", "true_block", "found",
                            "fit_iou", "iou_pred", "iou_true")}
    mem = []
    t0 = time.perf_counter()
    try:
        for t in tqdm(range(steps), desc="stability"):
            action = np.asarray(pol(obs, info), dtype=np.float32)
            obs, _, _, _, info = env.step(action)
            frame = wm.step(action[None])[0]
            for name, f in (("wm", frame), ("true", obs["pixels"])):
                g = f.astype(np.float32) / 255
                rows[f"{name}_mean"].append(float(g.mean()))
                rows[f"{name}_std"].append(float(g.std()))
                rows[f"{name}_block"].append(float(block_fraction(f).sum()))
            est = estimate_block_pose(frame)
            rows["found"].append(bool(est.found))
            rows["fit_iou"].append(est.fit_iou)
            rows["iou_pred"].append(float(pixel_iou(frame)))
            rows["iou_true"].append(float(info["iou"]))
            if t % 250 == 0 or t == steps - 1:
                mem.append((t, rss_mib()))
    finally:
        env.close()
    rows = {k: np.asarray(v) for k, v in rows.items()}
    detected = rows["found"] & (rows["fit_iou"] >= 0.8)
    return {"rows": rows, "memory_mib": mem, "seconds": time.perf_counter() - t0,
            "block_found_fraction": float(rows["found"].mean()),
            "block_detected_fraction": float(detected.mean()),
            "memory_first_mib": mem[1][1] if len(mem) > 1 else mem[0][1], "memory_last_mib": mem[-1][1]}


def plot_stability(st: dict, real: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = st["rows"]
    fig, axes = plt.subplots(4, 1, figsize=(8, 9), sharex=True)
    k = max(1, min(100, len(rows["wm_mean"])))  # moving-average window

    def smooth(y: np.ndarray) -> np.ndarray:
        return np.convolve(y, np.ones(k) / k, mode="valid")

    x = np.arange(k, len(rows["wm_mean"]) + 1)
    for ax, key, label in zip(axes[:3], ("mean", "std", "block"),
                              ("frame mean", "frame std", "block pixels")):
        ax.plot(x, smooth(rows[f"true_{key}"]), label="MuJoCo, same actions", lw=1)
        ax.plot(x, smooth(rows[f"wm_{key}"]), label="world model", lw=1)
        lo, hi = real[key]
        ax.axhspan(lo, hi, color="grey", alpha=0.15, label="play data, 5-95th pct")
        ax.set_ylabel(label)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[3].plot(x, smooth(rows["fit_iou"]), lw=1, label="T fit IoU of the block found in the frame")
    axes[3].plot([m[0] for m in st["memory_mib"]],
                 np.asarray([m[1] for m in st["memory_mib"]]) / max(m[1] for m in st["memory_mib"]),
                 lw=1, label="RSS / max RSS")
    axes[3].set_ylim(0, 1.05)
    axes[3].legend(loc="lower right", fontsize=8)
    axes[3].set_xlabel(f"rollout step (moving average over {k})")
    fig.suptitle(f"{len(rows['wm_mean'])}-step world-model rollout under play actions")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def rollout_figure(result, path: Path, steps: tuple[int, ...] = (1, 48, 96, 144, 192), n: int = 3) -> None:
    import imageio.v2 as imageio

    cols = [s - 1 for s in steps if s <= result.truth.shape[1]]
    blocks = []
    for i in range(min(n, len(result.episodes))):
        truth = np.concatenate(list(result.truth[i, cols]), axis=1)
        pred = np.concatenate(list(result.pred[i, cols]), axis=1)
        blocks += [truth, pred, np.full((4, truth.shape[1], 3), 255, np.uint8)]
    img = np.concatenate(blocks[:-1])
    imageio.imwrite(path, np.repeat(np.repeat(img, 3, 0), 3, 1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", type=Path, default=Path("runs/dyn/checkpoints/last"))
    ap.add_argument("--run", type=Path, help="the stage-2 run (for training time); default: the checkpoint's run")
    ap.add_argument("--data", type=Path, help="episode store (default: the one the run trained on)")
    ap.add_argument("--steps", type=int, default=192)
    ap.add_argument("--stability-steps", type=int, default=9000)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    torch.set_num_threads(2)
    args.out.mkdir(parents=True, exist_ok=True)
    ckpt = args.checkpoint.resolve()
    config = json.loads((ckpt / "config.json").read_text())
    wm = WorldModel.load(ckpt)
    store = EpisodeStore.open(args.data or config["data"])
    held = config["split"]["heldout_episodes"]
    result = {"machine": f"{platform.machine()}, {torch.get_num_threads()} threads", "checkpoint": str(ckpt),
              "heldout_episodes": held}

    # accuracy
    t = time.perf_counter()
    ol = open_loop(wm, store, held, args.steps, progress=True)
    summary = ol.summary()
    per_step = {"psnr_mean": ol.psnr.mean(0), "psnr_std": ol.psnr.std(0), "ssim_mean": ol.ssim.mean(0)}
    result["open_loop"] = {**summary, "episodes": len(held), "steps": args.steps,
                           "psnr_episode_means": ol.psnr.mean(1).round(3).tolist(),
                           "psnr_per_step": per_step["psnr_mean"].round(3).tolist(),
                           "ssim_per_step": per_step["ssim_mean"].round(4).tolist(),
                           "seconds": time.perf_counter() - t}
    # reference: a "model" that repeats the context frame
    first = np.stack([store.episode(e)["img"][0] for e in held])
    still_p, still_s = frame_scores(ol.truth, np.repeat(first[:, None], ol.truth.shape[1], 1))
    result["open_loop"]["copy_first_frame"] = {"psnr": float(still_p.mean()), "ssim": float(still_s.mean()),
                                               "psnr_last": float(still_p[:, -1].mean())}
    plot_psnr({f"{len(held)} held-out episodes": per_step["psnr_mean"], "copy of the first frame": still_p.mean(0)}, args.out / "dynamics_psnr.png",
              bands={f"{len(held)} held-out episodes": per_step["psnr_std"]}, target=25.0)
    rollout_figure(ol, args.out / "dynamics_rollout.png")

    # training time
    run = args.run or (ckpt.parent.parent if ckpt.parent.name == "checkpoints" else None)
    if run is not None and (run / "metrics.jsonl").exists():
        rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
        step = int(json.loads((ckpt / "training_state" / "state.json").read_text())["step"]) \
            if (ckpt / "training_state").exists() else rows[-1]["step"]
        at = [r for r in rows if r["step"] <= step]
        result["training"] = {"run": str(run), "step": step, "minutes": at[-1]["elapsed_s"] / 60,
                              "evals": [{k: v for k, v in r.items()} for r in at if "eval/psnr" in r]}

    # speed
    frame = store.episode(held[0])["img"][0]
    result["speed"] = speed(wm, frame)

    # stability
    st = stability(wm, args.stability_steps, seed=100000)
    train_frames = store.array("img").oindex[np.linspace(0, store.n_frames - 1, 2000).astype(int)]
    g = train_frames.astype(np.float32) / 255
    real = {"mean": np.percentile(g.mean((1, 2, 3)), [5, 95]), "std": np.percentile(g.std((1, 2, 3)), [5, 95]),
            "block": np.percentile(block_fraction(train_frames).sum((1, 2)), [5, 95])}
    plot_stability(st, real, args.out / "dynamics_stability.png")
    rows = st.pop("rows")
    result["stability"] = {**st, "steps": args.stability_steps,
                           "wm_frame_mean": float(rows["wm_mean"].mean()),
                           "true_frame_mean": float(rows["true_mean"].mean()),
                           "wm_block_pixels": float(rows["wm_block"].mean()),
                           "true_block_pixels": float(rows["true_block"].mean()),
                           "last_1000_block_detected": float((rows["found"][-1000:] & (rows["fit_iou"][-1000:] >= 0.8)).mean())}
    (args.out / "dynamics.json").write_text(json.dumps(result, indent=2) + "\n")
    write_markdown(result, args.out / "dynamics.md")
    print((args.out / "dynamics.md").read_text())


def write_markdown(r: dict, path: Path) -> None:
    ol, sp, st = r["open_loop"], r["speed"], r["stability"]
    tr = r.get("training")
    mark = lambda ok: "met" if ok else "**missed**"  # noqa: E731
    lines = [
        "# Stage 2 benchmark (`bench/bench_dynamics.py`)",
        "",
        f"Checkpoint `{r['checkpoint']}` ({r['machine']}).",
        "",
        "## Open-loop accuracy",
        "",
        f"{ol['episodes']} held-out play episodes x {ol['steps']} steps, context = the first frame, the recorded "
        "actions; PSNR/SSIM on [0, 1] images against the recorded frames.",
        "",
        "| metric | value | target |",
        "|---|---|---|",
        f"| mean PSNR over all steps | {ol['psnr']:.2f} dB | >= 25 dB ({mark(ol['psnr'] >= 25)}) |",
        f"| mean SSIM over all steps | {ol['ssim']:.3f} | >= 0.85 ({mark(ol['ssim'] >= 0.85)}) |",
        f"| PSNR at step {ol['steps']} | {ol['psnr_last']:.2f} dB | |",
        f"| SSIM at step {ol['steps']} | {ol['ssim_last']:.3f} | |",
        f"| mean pixel-IoU error | {ol['iou_abs_err']:.4f} | |",
        "",
        f"For scale, repeating the first frame scores PSNR {ol['copy_first_frame']['psnr']:.2f} dB, SSIM "
        f"{ol['copy_first_frame']['ssim']:.3f} ({ol['copy_first_frame']['psnr_last']:.2f} dB at the last step).",
        "",
        "![psnr](dynamics_psnr.png)",
        "",
        "Truth (upper row) and prediction (lower row) at steps 1, 48, 96, 144 and 192 for three episodes:",
        "",
        "![rollout](dynamics_rollout.png)",
        "",
    ]
    if tr:
        lines += [f"Training: {tr['minutes']:.1f} min to step {tr['step']} (target: within 90 min, "
                  f"{mark(tr['minutes'] <= 90)}).", ""]
    lines += [
        "## Speed",
        "",
        "| | ms | frames/s |",
        "|---|---|---|",
        f"| `step` (dynamics + 1-jump decode), batch 1 | {sp['step_ms_batch1']:.1f} | "
        f"**{sp['frames_per_s_batch1']:.1f}** (target >= 30, {mark(sp['frames_per_s_batch1'] >= 30)}) |",
        f"| `step`, batch 64 | {sp['step_ms_batch64']:.1f} | {sp['frames_per_s_batch64']:.0f} |",
        f"| streaming dynamics step alone, batch 1 | {sp['dynamics_step_ms_batch1']:.1f} | |",
        f"| 1-jump decode alone, batch 1 | {sp['decode_ms_batch1']:.1f} | |",
        f"| one uncached forward over a whole window, batch 1 | {sp['uncached_window_forward_ms_batch1']:.1f} | |",
        "",
        "## Stability",
        "",
        f"{st['steps']} steps under the play policy's actions (driven by MuJoCo, which renders the same actions), "
        f"{st['seconds'] / 60:.1f} min.",
        "",
        f"- block found by the pixel scorer in **{100 * st['block_found_fraction']:.2f}%** of frames (target >= 99%, "
        f"{mark(st['block_found_fraction'] >= 0.99)}); found with a T-shape fit IoU >= 0.8 in "
        f"{100 * st['block_detected_fraction']:.2f}% (last 1000 steps: {100 * st['last_1000_block_detected']:.2f}%);",
        f"- resident memory {st['memory_first_mib']:.0f} MiB at step 250, {st['memory_last_mib']:.0f} MiB at the end;",
        f"- mean frame intensity {st['wm_frame_mean']:.4f} (MuJoCo {st['true_frame_mean']:.4f}); mean block pixels "
        f"{st['wm_block_pixels']:.1f} (MuJoCo {st['true_block_pixels']:.1f}).",
        "",
        "![stability](dynamics_stability.png)",
        "",
    ]
    path.write_text("\n".join(lines))


if __name__ == "__main__":
    main()
