"""Speed and long-run stability of world models: latency, resident memory, steps per
second, and a long rollout under a scripted policy's actions beside MuJoCo."""

from __future__ import annotations

import time
from collections.abc import Callable, Collection
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
from tqdm import tqdm

from iwsim.core.errors import InputError
from iwsim.data.frames import to_uint8
from iwsim.envs.pusht.pixels import block_fraction, estimate_block_pose
from iwsim.envs.pusht.scripted import run_scripted
from iwsim.world_model import WorldModel


def latency_ms(fn: Callable[[], object], n: int = 200, warmup: int = 10) -> float:
    """Median wall-clock milliseconds of ``fn()`` over ``n`` calls after ``warmup`` (at most ``n``)."""
    for _ in range(min(warmup, n)):
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


def speed(wm: WorldModel, frame: np.ndarray, batch: int = 64, n: int = 100) -> dict[str, float]:
    """Single-stream and batched step costs of ``wm`` from one uint8 frame (H, W, 3)."""
    a = np.repeat(((wm.action_low + wm.action_high) / 2).cpu().numpy()[None], batch, 0)
    wm.reset(frame[None])
    step_ms = latency_ms(lambda: wm.step(a[:1]), n)
    a1 = wm.normalize_actions(a[:1])
    dyn_ms = latency_ms(lambda: wm.step(a1, latents=True), n)
    wm.reset(np.repeat(frame[None], batch, 0))
    batch_ms = latency_ms(lambda: wm.step(a), max(1, n // 10), warmup=2)
    return {"step_ms": step_ms, "steps_per_s": 1000 / step_ms, "dynamics_step_ms": dyn_ms,
            f"step_ms_batch{batch}": batch_ms, f"frames_per_s_batch{batch}": batch * 1000 / batch_ms}


RUN_STRIP_STEPS = (10, 20, 30, 50, 100, 200, 500, 1000, 2000)


def strip_steps(steps: int) -> list[int]:
    """The steps a strip of a ``steps``-step stability run shows."""
    return [t for t in RUN_STRIP_STEPS if t <= steps] or [steps]


def write_run_strip(path: str | Path, runs: dict[str, dict[str, np.ndarray]], names: list[str]) -> None:
    """``path``: the frames :func:`stability` kept, one row per name of ``runs`` (its models and
    "mujoco"), one column per kept step."""
    imageio.imwrite(path, np.concatenate([np.concatenate(list(runs[n]["frames"]), axis=1) for n in names], axis=0))


def stability(models: dict[str, WorldModel], steps: int, seed: int = 100000, every: int = 1,
              progress: bool = True, keep: Collection[int] = ()) -> dict[str, dict[str, np.ndarray]]:
    """All models and MuJoCo under the same play-policy actions for ``steps`` steps; every
    ``every`` steps, per model and for MuJoCo ("mujoco"): frame mean and std, block pixels,
    whether the block is detected (a T fits with IoU >= 0.8) and resident memory; with
    ``keep``, also the frames (N, H, W, 3) at those steps ("frames")."""
    if steps < 1 or every < 1:
        raise InputError(f"stability steps and interval must be >= 1, got {steps} and {every}.")
    if any(not 1 <= t <= steps for t in keep):
        raise InputError(f"the frames kept must be at steps 1..{steps}, got {sorted(keep)}.")
    size = next(iter(models.values())).image_size
    rows: dict[str, dict[str, list]] = {k: {"step": [], "mean": [], "std": [], "block": [], "detected": []}
                                        for k in (*models, "mujoco")}
    kept: dict[str, list[np.ndarray]] = {k: [] for k in rows}
    memory: list[float] = []
    run = run_scripted("play", seed, steps, "pusht", size)
    try:
        for t, tr in enumerate(tqdm(run, total=steps, desc="stability", disable=not progress), 1):
            if t == 1:
                for wm in models.values():
                    wm.reset(tr.obs["pixels"][None], seed=seed)
            obs, info = tr.next_obs, tr.next_info
            measured = t % every == 0 or t == steps
            frames = {}
            for name, wm in models.items():  # conditioned on the motion MuJoCo executed
                z = wm.step(wm.normalize_actions(info["target"][None]), latents=True)
                if measured or t in keep:
                    frames[name] = to_uint8(wm.decode_latents(z))[0]
            if not frames:
                continue
            frames["mujoco"] = obs["pixels"]
            for name, f in frames.items():
                if t in keep:
                    kept[name].append(f)
                if not measured:
                    continue
                g = f.astype(np.float32) / 255
                est = estimate_block_pose(f)
                r = rows[name]
                r["step"].append(t)
                r["mean"].append(float(g.mean()))
                r["std"].append(float(g.std()))
                r["block"].append(float(block_fraction(f).sum()))
                r["detected"].append(bool(est.found and est.fit_iou >= 0.8))
            if measured:
                memory.append(rss_mib())
    finally:
        run.close()
    out = {k: {kk: np.asarray(vv) for kk, vv in v.items()} for k, v in rows.items()}
    if keep:
        for k, f in kept.items():
            out[k]["frames"] = np.stack(f)
    out["mujoco"]["memory_mib"] = np.asarray(memory)
    return out
