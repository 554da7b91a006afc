"""``iwsim bench``: world models side by side on the paper's protocol.

- Accuracy: open-loop rollouts of held-out episodes (context = the first frame, then the
  recorded actions) scored against the recorded frames with the seven video metrics (MSE,
  PSNR, SSIM, UIQI, LPIPS, FID, FVD) and the task fidelity |IoU_pred - IoU_true| of the
  pixel scorer; mean +- std over episodes, as the paper's table.
- Speed, measured in one process one model after another: single-stream steps/s
  (dynamics + decode at batch 1) and frames/s at a batch of 64.
- Stability: one long rollout per model under the scripted play policy's actions, driven
  by MuJoCo (which renders the same actions), with frame statistics and block
  detectability over time.
- A figure of predicted and true frames at steps 0, 48, 96, 144 and 192.

LPIPS, FID and FVD need pretrained networks (:mod:`iwsim.eval.features`); when their
weights are missing the report says so in their columns instead of giving a number.
"""

from __future__ import annotations

import logging
import os
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from iwsim.checkpoint import load_json, resolve_checkpoint, write_json_atomic
from iwsim.data.frames import split_episodes, to_model, to_uint8
from iwsim.data.store import EpisodeStore
from iwsim.envs.pixels import block_fraction, estimate_block_pose, pixel_iou
from iwsim.envs.scripted import run_scripted
from iwsim.errors import InputError
from iwsim.eval import features as feats
from iwsim.metrics import mse, psnr, ssim, uiqi
from iwsim.world_model import WorldModel

log = logging.getLogger(__name__)

FRAME_METRICS = ("mse", "psnr", "ssim", "uiqi", "lpips")  # one value per frame
SET_METRICS = ("fid", "fvd")  # one value per model (distances between sets)
METRICS = (*FRAME_METRICS, *SET_METRICS, "iou_err")
LOWER_IS_BETTER = {"mse", "lpips", "fid", "fvd", "iou_err"}
NEEDS = {"lpips": feats.LPIPS_FILE, "fid": feats.INCEPTION_FILE, "fvd": feats.I3D_FILE}
FVD_CLIP = 16  # frames per FVD clip (Unterthiner et al. 2018)
FIGURE_STEPS = (0, 48, 96, 144, 192)
COPY = "copy of the first frame"  # the reference row of the report


def latency_ms(fn: Callable[[], object], n: int = 200, warmup: int = 10) -> float:
    """Median wall-clock milliseconds of ``fn()`` over ``n`` calls after ``warmup``."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(n):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return 1000 * float(np.median(times))


def rss_mib() -> float:
    """This process's resident memory (MiB), from /proc (NaN elsewhere)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


# -- video metrics -------------------------------------------------------------------------------
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
    for k, v in sets.items():
        out[k] = {"mean": float(v)}
    return out


# -- speed and stability -------------------------------------------------------------------------
def speed(wm: WorldModel, frame: np.ndarray, batch: int = 64, n: int = 100) -> dict[str, float]:
    """Single-stream and batched step costs of ``wm`` from one uint8 frame (H, W, 3)."""
    a = np.repeat(((wm.action_low + wm.action_high) / 2).cpu().numpy()[None], batch, 0)
    wm.reset(frame[None])
    step_ms = latency_ms(lambda: wm.step(a[:1]), n)
    a1 = wm.normalize_actions(a[:1])
    dyn_ms = latency_ms(lambda: wm.step_latent(a1), n)
    wm.reset(np.repeat(frame[None], batch, 0))
    batch_ms = latency_ms(lambda: wm.step(a), max(5, n // 10), warmup=2)
    return {"step_ms": step_ms, "steps_per_s": 1000 / step_ms, "dynamics_step_ms": dyn_ms,
            f"step_ms_batch{batch}": batch_ms, f"frames_per_s_batch{batch}": batch * 1000 / batch_ms}


def stability(models: dict[str, WorldModel], steps: int, seed: int = 100000, every: int = 1,
              progress: bool = True) -> dict[str, dict[str, np.ndarray]]:
    """All models and MuJoCo under the same play-policy actions for ``steps`` steps; every
    ``every`` steps, per model and for MuJoCo ("mujoco"): frame mean and std, block pixels,
    whether the block is detected (a T fits with IoU >= 0.8) and resident memory."""
    if steps < 1 or every < 1:
        raise InputError(f"stability steps and interval must be >= 1, got {steps} and {every}.")
    size = next(iter(models.values())).image_size
    rows: dict[str, dict[str, list]] = {k: {"step": [], "mean": [], "std": [], "block": [], "detected": []}
                                        for k in (*models, "mujoco")}
    memory: list[float] = []
    run = run_scripted("play", seed, steps, "pusht", size)
    try:
        for t, tr in enumerate(tqdm(run, total=steps, desc="stability", disable=not progress), 1):
            if t == 1:
                for wm in models.values():
                    wm.reset(tr.obs["pixels"][None], seed=seed)
            obs, info = tr.next_obs, tr.next_info
            frames = {}
            for name, wm in models.items():  # conditioned on the motion MuJoCo executed
                z = wm.step_latent(wm.normalize_actions(info["target"][None]))
                if t % every == 0 or t == steps:
                    frames[name] = to_uint8(wm.decode_latents(z))[0]
            if not frames:
                continue
            frames["mujoco"] = obs["pixels"]
            for name, f in frames.items():
                g = f.astype(np.float32) / 255
                est = estimate_block_pose(f)
                r = rows[name]
                r["step"].append(t)
                r["mean"].append(float(g.mean()))
                r["std"].append(float(g.std()))
                r["block"].append(float(block_fraction(f).sum()))
                r["detected"].append(bool(est.found and est.fit_iou >= 0.8))
            memory.append(rss_mib())
    finally:
        run.close()
    out = {k: {kk: np.asarray(vv) for kk, vv in v.items()} for k, v in rows.items()}
    out["mujoco"]["memory_mib"] = np.asarray(memory)
    return out


# -- figures -------------------------------------------------------------------------------------
def _save_figure(fig, path: Path) -> None:  # noqa: ANN001  (a matplotlib Figure)
    import matplotlib.pyplot as plt

    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)


def _pyplot():  # noqa: ANN202
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def frames_figure(context: np.ndarray, truth: np.ndarray, preds: dict[str, np.ndarray], path: Path,
                  episodes: tuple[int, ...] = (0, 1)) -> None:
    """Rows truth, then each model, at FIGURE_STEPS (step 0 is the context frame), for
    the given episode indices. context (E, H, W, 3); truth and preds (E, S, H, W, 3)."""
    plt = _pyplot()
    steps = [s for s in FIGURE_STEPS if s <= truth.shape[1]]
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
    _save_figure(fig, path)


def curves_figure(per_step: dict[str, dict[str, np.ndarray]], path: Path) -> None:
    """PSNR, SSIM and IoU error against rollout step, one line per model (+- std band)."""
    plt = _pyplot()
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
    _save_figure(fig, path)


def stability_figure(rows: dict[str, dict[str, np.ndarray]], path: Path, window: int = 50) -> None:
    """Frame mean, frame std, block pixels and block detectability over a long rollout
    (moving averages over ``window`` recorded points), one line per model and MuJoCo."""
    plt = _pyplot()
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
    _save_figure(fig, path)


# -- the benchmark ---------------------------------------------------------------------------------
def training_info(path: Path) -> dict[str, float]:
    """Steps and wall-clock minutes of a run checkpoint (empty for exported models)."""
    state = path / "training_state" / "state.json"
    if not state.is_file():
        return {}
    s = load_json(state)
    return {"train_steps": int(s["step"]), "train_minutes": float(s["elapsed_s"]) / 60}


def _data_of(path: Path) -> str | None:
    config = load_json(path / "config.json")
    return config.get("data") or config.get("provenance", {}).get("data")


def run_benchmark(models: dict[str, str | Path], out: str | Path, data: str | Path | None = None, *,
                  episodes: int = 20, steps: int = 192, stability_steps: int = 9000, stability_every: int = 1,
                  speed_batch: int = 64, speed_calls: int = 100, seed: int = 0, weights: Path | None = None,
                  device: torch.device | str = "cpu", progress: bool = True) -> dict:
    """Benchmark ``models`` (name -> world-model checkpoint; the first is "ours") into
    ``out``: results.json, results.md, curves.png, frames.png, stability.png."""
    from iwsim.eval.rollout import open_loop

    if not models:
        raise InputError("no model to benchmark.")
    paths = {name: resolve_checkpoint(p) for name, p in models.items()}
    wms = {name: WorldModel.load(p, device) for name, p in paths.items()}
    first = next(iter(paths.values()))
    data = data or _data_of(first)
    if data is None:
        raise InputError(f"{first} does not say which store it was trained on; pass --data.")
    store = EpisodeStore.open(data, "r")
    sizes = {wm.image_size for wm in wms.values()}
    if sizes != {store.array("img").shape[1]}:
        raise InputError(f"the models' image sizes {sorted(sizes)} do not match the {store.array('img').shape[1]} "
                         f"px frames of {data}.")
    _, held = split_episodes(store.n_episodes, next(iter(wms.values())).cfg.holdout_every)
    long_enough = [e for e in held if len(store.episode(e)["action"]) >= steps + 1]
    if len(long_enough) < episodes:
        raise InputError(f"{data} has {len(long_enough)} held-out episodes of at least {steps + 1} frames; "
                         f"{episodes} were asked for (lower --episodes or --steps).")
    chosen = long_enough[:episodes]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    nets = FeatureNets.load(weights, device)
    for k, why in nets.missing.items():
        log.warning("%s: %s (set %s to a directory holding it)", k.upper(), why, feats.WEIGHTS_ENV)

    result: dict = {"machine": f"{platform.machine()}, {torch.get_num_threads()} threads", "data": str(data),
                    "episodes": chosen, "steps": steps, "seed": seed, "ours": next(iter(models)),
                    "unavailable": nets.missing, "models": {}}
    per_step: dict[str, dict[str, np.ndarray]] = {}
    preds: dict[str, np.ndarray] = {}
    truth = context = None
    truth_feats: dict[str, np.ndarray] = {}
    for name, wm in wms.items():
        t0 = time.perf_counter()
        ol = open_loop(wm, store, chosen, steps, seed=seed, progress=progress)
        if truth is None:
            truth, context = ol.truth, np.stack([store.episode(e)["img"][0] for e in chosen])
            truth_iou = ol.iou_true
            if nets.inception is not None:
                truth_feats["fid"] = inception_features(nets.inception, truth)
            if nets.i3d is not None:
                truth_feats["fvd"] = i3d_features(nets.i3d, truth)
        scores = frame_metrics(truth, ol.pred, nets, device=device)
        scores["iou_err"] = np.abs(ol.iou_pred - truth_iou)
        entry = {"checkpoint": str(paths[name]), "objective": wm.cfg.objective, **training_info(paths[name]),
                 "accuracy": summarize(scores, set_metrics(truth_feats, ol.pred, nets)),
                 "accuracy_seconds": time.perf_counter() - t0}
        result["models"][name] = entry
        per_step[name], preds[name] = scores, ol.pred
        log.info("%s: PSNR %.2f dB, SSIM %.3f", name, entry["accuracy"]["psnr"]["mean"],
                 entry["accuracy"]["ssim"]["mean"])
    # For scale: a "model" that repeats the context frame.
    still = np.repeat(context[:, None], steps, 1)
    scores = frame_metrics(truth, still, nets, device=device)
    scores["iou_err"] = np.abs(np.asarray(pixel_iou(context))[:, None] - truth_iou)
    result["reference"] = {COPY: {"accuracy": summarize(scores, set_metrics(truth_feats, still, nets))}}
    for name, wm in wms.items():
        result["models"][name]["speed"] = speed(wm, context[0], speed_batch, speed_calls)
    curves_figure(per_step, out / "curves.png")
    frames_figure(context, truth, preds, out / "frames.png")
    if stability_steps > 0:
        t0 = time.perf_counter()
        rows = stability(wms, stability_steps, every=stability_every, progress=progress)
        stability_figure(rows, out / "stability.png")
        for name, r in rows.items():
            s = {"frame_mean": float(r["mean"].mean()), "frame_std": float(r["std"].mean()),
                 "block_pixels": float(r["block"].mean()), "block_detected": float(r["detected"].mean()),
                 "block_detected_last_10pct": float(r["detected"][-max(1, len(r["detected"]) // 10):].mean())}
            (result.setdefault("mujoco", {}) if name == "mujoco" else result["models"][name])["stability"] = s
        mem = rows["mujoco"]["memory_mib"]
        result["stability"] = {"steps": stability_steps, "every": stability_every,
                               "minutes": (time.perf_counter() - t0) / 60,
                               "memory_mib_first": float(mem[min(len(mem) - 1, 1)]), "memory_mib_last": float(mem[-1])}
    write_json_atomic(out / "results.json", result, sort_keys=False)  # models in the order given
    tmp = out / ".results.md.tmp"
    tmp.write_text(markdown(result))
    os.replace(tmp, out / "results.md")
    return result


# -- the report ------------------------------------------------------------------------------------
def _cell(acc: dict, metric: str, unavailable: dict[str, str], key: str = "mean") -> str:
    if metric in unavailable:
        return unavailable[metric]
    if metric not in acc:
        return "-"
    v = acc[metric]
    digits = 2 if metric in ("psnr", "fid", "fvd") else 4
    if key == "last":
        return f"{v['last']:.{digits}f} +- {v['last_std']:.{digits}f}"
    return f"{v['mean']:.{digits}f}" + (f" +- {v['std']:.{digits}f}" if "std" in v else "")


def compare(result: dict) -> list[str]:
    """Where ours wins and loses against each other model, metric by metric."""
    ours = result["ours"]
    mine = result["models"][ours]["accuracy"]
    lines = []
    for name, entry in result["models"].items():
        if name == ours:
            continue
        wins, losses = [], []
        for m in METRICS:
            if m not in mine or m not in entry["accuracy"]:
                continue
            a, b = mine[m]["mean"], entry["accuracy"][m]["mean"]
            better = a <= b if m in LOWER_IS_BETTER else a >= b
            (wins if better else losses).append(f"{m.upper()} {a:.4g} vs {b:.4g}")
        for m in ("psnr", "ssim", "iou_err"):
            a, b = mine[m]["last"], entry["accuracy"][m]["last"]
            better = a <= b if m in LOWER_IS_BETTER else a >= b
            (wins if better else losses).append(f"{m.upper()} at step {result['steps']} {a:.4g} vs {b:.4g}")
        sp = result["models"][ours].get("speed"), entry.get("speed")
        ratio = f"; per frame at batch 1 ours is {sp[1]['step_ms'] / sp[0]['step_ms']:.2f}x as fast" if all(sp) else ""
        lines.append(f"- **vs {name}**: matches or beats on {', '.join(wins) or 'nothing'}; "
                     f"loses on {', '.join(losses) or 'nothing'}{ratio}.")
    return lines


def markdown(r: dict) -> str:
    """The Markdown report of a ``run_benchmark`` result."""
    un = r["unavailable"]
    names = list(r["models"])
    arrows = {m: "↓" if m in LOWER_IS_BETTER else "↑" for m in METRICS}
    lines = [
        "# World-model benchmark (`iwsim bench`)",
        "",
        f"{len(r['episodes'])} held-out episodes of `{r['data']}` x {r['steps']} steps, open loop: context = the first "
        f"frame, then the recorded actions; per-frame metrics on [0, 1] images; mean +- std over episodes of each "
        f"episode's mean. Machine: {r['machine']}.",
        "",
        "| model | " + " | ".join(f"{m.upper()} {arrows[m]}" for m in METRICS) + " |",
        "|---|" + "---|" * len(METRICS),
    ]
    rows = [(n, r["models"][n]["accuracy"]) for n in names]
    rows += [(f"*{n}*", e["accuracy"]) for n, e in r.get("reference", {}).items()]
    for n, acc in rows:
        lines.append(f"| {n} | " + " | ".join(_cell(acc, m, un) for m in METRICS) + " |")
    lines += ["", f"At step {r['steps']}:", "", "| model | PSNR ↑ | SSIM ↑ | IoU error ↓ |", "|---|---|---|---|"]
    for n, acc in rows:
        lines.append(f"| {n} | " + " | ".join(_cell(acc, m, un, "last") for m in ("psnr", "ssim", "iou_err")) + " |")
    lines += ["", "![curves](curves.png)", "", "![frames](frames.png)", "", "## Training and speed", "",
              "| model | objective | training | step at batch 1 (ms) | steps/s | dynamics step (ms) | "
              f"frames/s at batch {_batch(r)} |", "|---|---|---|---|---|---|---|"]
    for n in names:
        e = r["models"][n]
        tr = f"{e['train_steps']} steps, {e['train_minutes']:.1f} min" if "train_steps" in e else "-"
        sp = e.get("speed", {})
        b = _batch(r)
        lines.append(f"| {n} | {e['objective']} | {tr} | {sp.get('step_ms', float('nan')):.1f} | "
                     f"{sp.get('steps_per_s', float('nan')):.1f} | {sp.get('dynamics_step_ms', float('nan')):.1f} | "
                     f"{sp.get(f'frames_per_s_batch{b}', float('nan')):.0f} |")
    if "stability" in r:
        st = r["stability"]
        lines += ["", "## Stability", "",
                  f"{st['steps']} steps under the play policy's actions (MuJoCo renders the same actions), "
                  f"scored every {st['every']} step(s); {st['minutes']:.1f} min for all models. Resident memory "
                  f"{st['memory_mib_first']:.0f} MiB at the start, {st['memory_mib_last']:.0f} MiB at the end.", "",
                  "| | frame mean | frame std | block pixels | block detected | detected, last 10% |",
                  "|---|---|---|---|---|---|"]
        for n, s in [*((n, r["models"][n]["stability"]) for n in names), ("MuJoCo", r["mujoco"]["stability"])]:
            lines.append(f"| {n} | {s['frame_mean']:.4f} | {s['frame_std']:.4f} | {s['block_pixels']:.1f} | "
                         f"{100 * s['block_detected']:.1f}% | {100 * s['block_detected_last_10pct']:.1f}% |")
        lines += ["", "![stability](stability.png)"]
    lines += ["", f"## Ours ({r['ours']}) against each model", "", *compare(r), ""]
    return "\n".join(lines)


def _batch(r: dict) -> int:
    for e in r["models"].values():
        for k in e.get("speed", {}):
            if k.startswith("frames_per_s_batch"):
                return int(k.removeprefix("frames_per_s_batch"))
    return 64
