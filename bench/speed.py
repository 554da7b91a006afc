"""Every hot network step of iwsim, timed and profiled against this machine's roofline.

    python bench/speed.py --threads 1 --out bench/results/speed          # everything (~15 minutes)
    python bench/speed.py --steps wm-step-1,dp-train --modes fp32,fast   # a subset
    python bench/speed.py --time dyn-train-preset-16 --mode fast -n 5    # one step, for farm-bench pairs
    python bench/speed.py --curves runs/curve_fp32 runs/curve_bf16 --out bench/results/speed  # loss curves

The roofline: a 3 x 3 convolution 64 -> 64 over 16 x 16 maps at batch 64 (forward, and
forward + backward) and a 1024^3 matrix product, in each precision and layout, measured
here on the machine the script runs on (its CPU model and bf16 flags recorded with it), the
fastest of 30 calls each.

The steps (shapes as the shipped models and presets run them):

- ``dyn-train-{preset,long}-{8,16}``: one stage-2 training step (forward, backward, AdamW)
  at batch 16: the ``pusht-64`` preset at its longest unroll (a 3-latent window, 12
  predictions) or the shipped model's long-unroll recipe (a 10-latent window, 24
  predictions, the gradient cut every 8), on 8 x 8 x 8 latents (the x8 codec) or 16 x 16 x 8
  (the x4 codec: the finer latents of issue 64);
- ``wm-step-1``, ``wm-step-64``: one step of the shipped world model (dynamics + decoder,
  a frame out) for one stream and for a batch of 64; ``wm-step-1-two-views``: one stream
  of its architecture over two camera views (issue 68; random dynamics weights);
- ``codec-encode-64``, ``codec-decode-64``: the shipped codec on 64 frames;
- ``dp-train``, ``act-train``: one training step of the shipped policies' networks at their
  training batch size; ``dp-predict``, ``act-predict``: one ``predict_action`` of one stream.

Modes: ``fp32`` (float32, the standard layout), ``bf16`` (bf16 autocast, the standard
layout: the trainer's ``--bf16`` before issue 63), ``bf16-cl`` (bf16 autocast with
channels-last activations) and ``fast``: what iwsim itself runs on this machine
(:mod:`iwsim.core.precision`; the trainer's path for a training step under ``--bf16``,
``WorldModel.bf16`` at inference; the policies run float32, where bf16 did not pay) and
``fast+compile`` (a training step with ``--compile``). Each row: the median time per step, its
FLOPs (``torch.utils.flop_counter``: convolutions, matrix products and attention, forward
and backward), the GFLOP/s they make, that as a share of the roofline's peak for the mode's
precision and layout, and the five operators that took the most time.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch
from torch import nn
from torch.profiler import ProfilerActivity, profile
from torch.utils.flop_counter import FlopCounterMode
from tqdm import tqdm

from iwsim.core.checkpoint import load_json, write_json_atomic, write_text_atomic
from iwsim.core.config import from_dict
from iwsim.eval.profiling import latency_ms
from iwsim.eval.records import command_line
from iwsim.policies.common import PolicyBatch
from iwsim.policies.factory import load_policy
from iwsim.world_model import WorldModel
from iwsim.world_model.dynamics import Dynamics
from iwsim.world_model.dynamics_data import DynBatch
from iwsim.world_model.presets import DYNAMICS_PRESETS, DynamicsStageConfig
from iwsim.world_model.train_dynamics import DynamicsTrainModule

MODES = ("fp32", "bf16", "bf16-cl", "fast", "fast+compile")
SHIPPED = Path(__file__).resolve().parents[1] / "checkpoints"
Step = Callable[[], object]


def mode_path(mode: str) -> tuple[bool, bool]:
    """(bf16, channels_last) of a mode other than ``fast``."""
    return {"fp32": (False, False), "bf16": (True, False), "bf16-cl": (True, True)}[mode]


def autocast(bf16: bool) -> contextlib.AbstractContextManager:
    return torch.autocast("cpu", dtype=torch.bfloat16) if bf16 else contextlib.nullcontext()


# ---------------------------------------------------------------- the roofline


def best_ms(fn: Step, repeat: int) -> float:
    """The fastest of ``repeat`` calls (ms), after one: a roofline is the best the machine
    does (a median moves with this shared machine's other tenants)."""
    fn()
    return min(latency_ms(fn, 1, warmup=0) for _ in range(repeat))


CONV_FLOPS = 2 * 64 * 64 * 9 * 16 * 16 * 64  # the roofline's convolution: 64 -> 64, 3 x 3, 16 x 16, batch 64


def roofline_row(bf16: bool, cl: bool, bf16_weights: bool, repeat: int) -> dict[str, float]:
    """GFLOP/s of the roofline's convolution (and, in the standard layout, a 1024^3 matrix
    product) under bf16 autocast or not, channels-last or not, or with bf16 weights."""
    conv = nn.Conv2d(64, 64, 3, padding=1)
    x = torch.randn(64, 64, 16, 16)
    if bf16_weights:
        conv, x = conv.to(torch.bfloat16), x.to(torch.bfloat16)
    if cl:
        conv, x = conv.to(memory_format=torch.channels_last), x.contiguous(memory_format=torch.channels_last)
    xg = x.clone().requires_grad_()

    def fwd() -> None:
        with torch.no_grad(), autocast(bf16):
            conv(x)

    def fwd_bwd() -> None:
        with autocast(bf16):
            y = conv(xg)
        y.backward(torch.ones_like(y))

    row = {"conv_fwd": CONV_FLOPS / best_ms(fwd, repeat) / 1e6,
           "conv_fwd_bwd": 3 * CONV_FLOPS / best_ms(fwd_bwd, repeat) / 1e6}
    if not cl:
        a = torch.randn(1024, 1024, dtype=torch.bfloat16 if bf16_weights else torch.float32)

        def mm() -> None:
            with autocast(bf16):
                a @ a
        row["matmul"] = 2 * 1024**3 / best_ms(mm, repeat) / 1e6
    return row


def roofline(repeat: int) -> dict[str, dict[str, float]]:
    """The roofline's rows per precision and layout (see the module docstring)."""
    return {name: roofline_row(bf16, cl, weights, repeat) for name, bf16, cl, weights in (
        ("fp32", False, False, False), ("fp32-cl", False, True, False), ("bf16", True, False, False),
        ("bf16-cl", True, True, False), ("bf16-weights-cl", False, True, True))}


def peak_for(roof: dict[str, dict[str, float]], bf16: bool, cl: bool | None, training: bool) -> float:
    """The roofline's convolution peak for a step of this precision and layout (``cl``
    None: the best of every layout of that precision, bf16 weights included)."""
    key = "conv_fwd_bwd" if training else "conv_fwd"
    prec = "bf16" if bf16 else "fp32"
    if cl is None:
        return max(row[key] for name, row in roof.items() if name.startswith(prec))
    return roof[prec + ("-cl" if cl else "")][key]


# ---------------------------------------------------------------- the steps


def dynamics_step(kind: str, size: int, bf16: bool, cl: bool, fast: bool) -> Step:
    """One stage-2 training step (see the module docstring), as the trainer runs it."""
    shipped = from_dict(DynamicsStageConfig, load_json(SHIPPED / "pusht-64" / "config.json")["stage2"])
    net = dataclasses.replace(shipped.dynamics, latent_size=size)
    if kind == "preset":
        preset = DYNAMICS_PRESETS["pusht-64"]
        cfg = dataclasses.replace(preset, dynamics=dataclasses.replace(net, context=preset.dynamics.context))
        n = preset.unroll_at(preset.train.steps)
    else:
        cfg = dataclasses.replace(shipped, dynamics=net)
        n = shipped.unroll_at(0)
    torch.manual_seed(0)
    module = DynamicsTrainModule(Dynamics(cfg.dynamics), cfg)
    b, k, shape = 16, cfg.dynamics.context, (cfg.dynamics.latent_channels, size, size)
    g = torch.Generator().manual_seed(0)
    batch = DynBatch(torch.randn(b, k + n, *shape, generator=g), torch.rand(b, n + 1, 4, generator=g) * 2 - 1,
                     torch.rand(b, n, generator=g) * 0.3, torch.randn(b, n, k, *shape, generator=g),
                     torch.full((b, n), 999), torch.zeros(b, n), torch.ones(b, n),
                     torch.randn(b, n, *shape, generator=g), torch.randn(b, n, *shape, generator=g))
    return train_step(module, batch, bf16, cl, fast)


COMPILE = False  # set by build() for the "fast+compile" mode


def train_step(module: nn.Module, batch: object, bf16: bool, cl: bool, fast: bool) -> Step:
    """forward, backward, gradient clipping and AdamW, as :mod:`iwsim.core.trainer` does."""
    ctx: Callable[[], contextlib.AbstractContextManager]
    if fast:
        from iwsim.core.precision import Precision, bf16_available
        from iwsim.core.trainer import compile_networks, training_precision

        precision = training_precision(torch.device("cpu"), bf16_available(torch.device("cpu")))
        ctx = lambda: precision.autocast(torch.device("cpu"))  # noqa: E731
        assert isinstance(precision, Precision)
        if COMPILE:
            compile_networks(module)
    else:
        if cl:
            module.to(memory_format=torch.channels_last)
        ctx = lambda: autocast(bf16)  # noqa: E731
    module.train()
    opt = torch.optim.AdamW(module.parameters(), lr=1e-4)

    def step() -> None:
        with ctx():
            loss, _ = module(batch)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(module.parameters(), 1.0)
        opt.step()
    return step


def world_model(bf16: bool, cl: bool, fast: bool) -> WorldModel:
    wm = WorldModel.load(SHIPPED / "pusht-64")
    if fast:
        wm.bf16 = True
    elif cl:
        wm.dynamics.to(memory_format=torch.channels_last)
    return wm


def two_view_model(wm: WorldModel) -> WorldModel:
    """The shipped model's architecture over two camera views (issue 68's layout: one codec,
    the views' latents stacked along the channels, so the dynamics takes and predicts
    twice the channels), its dynamics randomly initialised: a step costs what a trained
    one's does."""
    d = wm.cfg.dynamics
    cfg = dataclasses.replace(wm.cfg, cameras=("top", "side"),
                              dynamics=dataclasses.replace(d, latent_channels=2 * d.latent_channels))
    torch.manual_seed(0)
    two = WorldModel(wm.codec, Dynamics(cfg.dynamics), cfg, wm.action_low, wm.action_high).eval()
    two.bf16 = wm.bf16
    return two


def wm_step(batch: int, bf16: bool, cl: bool, fast: bool, views: int = 1) -> Step:
    wm = world_model(bf16, cl, fast)
    if views == 2:
        wm = two_view_model(wm)
    frame = torch.zeros(batch, 64, 64, 3 * views, dtype=torch.uint8).numpy()
    actions = ((wm.action_low + wm.action_high) / 2).repeat(batch, 1).numpy()
    wm.reset(frame)

    def step() -> None:
        with autocast(bf16 and not fast):
            wm.step(actions)
    return step


def codec_step(what: str, bf16: bool, cl: bool, fast: bool) -> Step:
    wm = world_model(bf16, cl, fast)
    frames = torch.zeros(64, 64, 64, 3, dtype=torch.uint8).numpy()
    z = wm.encode(frames)

    def step() -> None:
        with autocast(bf16 and not fast):
            wm.encode(frames) if what == "encode" else wm.decode(z)
    return step


def policy_batch(policy: nn.Module, batch: int) -> PolicyBatch:
    cfg = policy.cfg  # type: ignore[attr-defined]
    to = cfg.obs_horizon
    tp = getattr(cfg, "horizon", None) or cfg.chunk_size
    g = torch.Generator().manual_seed(0)
    return PolicyBatch(torch.rand(batch, to, 3, 64, 64, generator=g) * 2 - 1,
                       torch.rand(batch, to, 4, generator=g) * 2 - 1,
                       torch.rand(batch, tp, 4, generator=g) * 2 - 1, torch.zeros(batch, tp, dtype=torch.bool))


def policy_train_step(name: str, bf16: bool, cl: bool, fast: bool) -> Step:
    path = SHIPPED / f"{name}-pusht-64"
    policy = load_policy(path)
    batch = policy_batch(policy, load_json(path / "config.json")["train"]["batch_size"])
    torch.manual_seed(0)
    return train_step(policy, batch, bf16, cl, fast)


def policy_predict_step(name: str, bf16: bool, cl: bool, fast: bool) -> Step:
    policy = load_policy(SHIPPED / f"{name}-pusht-64").requires_grad_(False)  # fast: float32, as iwsim runs it
    if cl and not fast:
        policy.to(memory_format=torch.channels_last)
    to = policy.obs_horizon
    obs = {"image": torch.zeros(1, to, 64, 64, 3, dtype=torch.uint8).numpy(),
           "agent_pos": torch.zeros(1, to, 4).numpy()}

    def step() -> None:
        with autocast(bf16 and not fast):
            policy.predict_action(obs)
        policy.reset()
    return step


STEPS: dict[str, tuple[Callable[[bool, bool, bool], Step], bool]] = {  # name -> (builder, is a training step)
    **{f"dyn-train-{kind}-{size}": ((lambda b, c, f, kind=kind, size=size: dynamics_step(kind, size, b, c, f)), True)
       for kind in ("preset", "long") for size in (8, 16)},
    "wm-step-1": ((lambda b, c, f: wm_step(1, b, c, f)), False),
    "wm-step-64": ((lambda b, c, f: wm_step(64, b, c, f)), False),
    "wm-step-1-two-views": ((lambda b, c, f: wm_step(1, b, c, f, views=2)), False),
    "codec-encode-64": ((lambda b, c, f: codec_step("encode", b, c, f)), False),
    "codec-decode-64": ((lambda b, c, f: codec_step("decode", b, c, f)), False),
    "dp-train": ((lambda b, c, f: policy_train_step("dp", b, c, f)), True),
    "act-train": ((lambda b, c, f: policy_train_step("act", b, c, f)), True),
    "dp-predict": ((lambda b, c, f: policy_predict_step("dp", b, c, f)), False),
    "act-predict": ((lambda b, c, f: policy_predict_step("act", b, c, f)), False),
}


def build(name: str, mode: str) -> Step:
    global COMPILE
    builder, _ = STEPS[name]
    COMPILE = mode == "fast+compile"
    if mode.startswith("fast"):
        return builder(False, False, True)
    bf16, cl = mode_path(mode)
    return builder(bf16, cl, False)


def fast_path(name: str) -> tuple[bool, bool]:
    """(bf16, channels_last) of what iwsim runs for step ``name`` on this machine."""
    from iwsim.core.precision import bf16_available
    from iwsim.core.trainer import training_precision
    from iwsim.world_model.model import inference_precision

    cpu = torch.device("cpu")
    if name.endswith("-predict"):
        return False, False
    if STEPS[name][1]:
        p = training_precision(cpu, bf16_available(cpu))
    else:
        p = inference_precision(cpu)
    return p.bf16, False


def step_flops(name: str) -> int:
    """The FLOPs of one call of step ``name`` (counted in float32, eager: the same arithmetic)."""
    step = build(name, "fp32")
    with FlopCounterMode(display=False) as counter:
        step()
    return counter.get_total_flops()


def measure(name: str, mode: str, repeat: int, roof: dict[str, dict[str, float]], flops: int) -> dict[str, object]:
    step = build(name, mode)
    training = STEPS[name][1]
    t = time.perf_counter()
    step()  # warm-up: a first allocation of everything (and compiling, under fast+compile)
    first_s = time.perf_counter() - t
    ms = latency_ms(step, repeat, warmup=1)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        step()
    ops = sorted(prof.key_averages(), key=lambda e: e.self_cpu_time_total, reverse=True)
    total = sum(e.self_cpu_time_total for e in ops) or 1.0
    bf16, cl = fast_path(name) if mode.startswith("fast") else mode_path(mode)
    peak, best = peak_for(roof, bf16, cl, training), peak_for(roof, bf16, None, training)
    gflops = flops / ms / 1e6
    return {"step": name, "mode": mode, "bf16": bf16, "channels_last": cl, "ms": ms, "first_call_s": first_s,
            "gflop": flops / 1e9,
            "gflops": gflops, "peak_gflops": peak, "share_of_peak": gflops / peak,
            "best_peak_gflops": best, "share_of_best_peak": gflops / best,
            "top_ops": [[e.key, round(100 * e.self_cpu_time_total / total, 1)] for e in ops[:5]]}


def report(record: dict) -> str:
    cpu = record["machine"]
    lines = [f"# Every hot step against the roofline ({cpu['cpu']})", "", "```", record["command"], "```", "",
             f"CPU: {cpu['cpu']}; bf16 instructions: {cpu['cpu_bf16']}; {record['threads']} thread(s); "
             f"PyTorch {record['torch']}.", "", "## Roofline (GFLOP/s, measured here)", "",
             "| precision, layout | conv 3x3 fwd | conv fwd+bwd | matmul 1024^3 |", "|---|---|---|---|"]
    for name, row in record["roofline"].items():
        mm = f"{row['matmul']:.0f}" if "matmul" in row else "-"
        lines.append(f"| {name} | {row['conv_fwd']:.0f} | {row['conv_fwd_bwd']:.0f} | {mm} |")
    lines += ["", "## Steps", "", "Share of peak: of the roofline's convolution in the step's precision and layout "
              "(forward + backward for a training step, forward otherwise); of the best: of the fastest layout of that "
              "precision (for bf16: bf16 weights, channels-last).", "",
              "| step | mode (bf16, channels_last) | ms / step | first call s | GFLOP | GFLOP/s "
              "| share of peak (of the best) | top operators (% of time) |", "|---|---|---|---|---|---|---|---|"]
    for r in record["rows"]:
        ops = ", ".join(f"{k.replace('aten::', '')} {p}" for k, p in r["top_ops"])
        lines.append(f"| {r['step']} | {r['mode']} ({'bf16' if r['bf16'] else 'fp32'}"
                     f"{', cl' if r['channels_last'] else ''}) | {r['ms']:.1f} | {r['first_call_s']:.1f} | "
                     f"{r['gflop']:.2f} | {r['gflops']:.0f} | {100 * r['share_of_peak']:.0f}% "
                     f"({100 * r['share_of_best_peak']:.0f}%) | {ops} |")
    return "\n".join(lines) + "\n"


def curves(runs: list[Path], out: Path) -> None:
    """The training loss and held-out evaluations of runs of one command in other numeric
    paths (their metrics.jsonl), side by side: ``curves.md`` and ``curves.png``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    lines = ["# Training loss along the numeric paths", "", "```", command_line(__file__), "```", "",
             "| run | path | steps | loss, mean of the last 100 steps' rows | held-out evaluations (step: latent MSE, "
             "PSNR dB) | training s |", "|---|---|---|---|---|---|"]
    for run in runs:
        rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines() if line.strip()]
        train = [r for r in rows if "loss" in r]
        evals = [r for r in rows if "eval/psnr" in r]
        last = train[-1]["step"]
        tail = [r["loss"] for r in train if r["step"] > last - 100]
        ax.plot([r["step"] for r in train], [r["loss"] for r in train], label=f"{run.name} ({train[-1]['path']})")
        ev = ", ".join(f"{r['step']}: {r['eval/latent_mse']:.3f}, {r['eval/psnr']:.2f}" for r in evals)
        lines.append(f"| {run} | {train[-1]['path']} | {last} | {statistics.mean(tail):.4f} | {ev} | "
                     f"{train[-1]['elapsed_s']:.0f} |")
    ax.set(xlabel="training step", ylabel="loss", yscale="log", title="stage-2 training loss")
    ax.legend()
    out.mkdir(parents=True, exist_ok=True)
    fig.savefig(out / "curves.png", dpi=120, bbox_inches="tight")
    write_text_atomic(out / "curves.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--steps", default=",".join(STEPS), help="comma-separated steps (default: all)")
    p.add_argument("--modes", default=",".join(MODES), help="comma-separated modes (default: all)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("-n", "--repeat", type=int, default=5, help="timed calls per step and mode (median)")
    p.add_argument("--out", default="bench/results/speed")
    p.add_argument("--time", metavar="STEP", help="only time STEP in --mode (for farm-bench pairs)")
    p.add_argument("--mode", default="fast")
    p.add_argument("--append", action="store_true", help="add the rows measured to --out's record (same machine)")
    p.add_argument("--curves", nargs="+", type=Path, metavar="RUN", help="only compare the loss curves of these runs")
    args = p.parse_args()
    if args.curves:
        curves(args.curves, Path(args.out))
        return
    torch.set_num_threads(args.threads)
    if args.time:
        step = build(args.time, args.mode)
        step()
        print(f"{args.time} {args.mode}: {latency_ms(step, args.repeat, warmup=1):.1f} ms")
        return
    from iwsim.core.precision import cpu_info

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    record = {"command": command_line(__file__), "threads": args.threads, "torch": torch.__version__,
              "machine": {"cpu": cpu_info().model, "cpu_bf16": cpu_info().bf16,
                          "flags": sorted(f for f in cpu_info().flags if "avx512" in f or "amx" in f)},
              "roofline": {}, "rows": []}
    if args.append:  # the record's roofline and rows stay; rows of the same step and mode are measured again
        old = load_json(out / "results.json")
        if (old["machine"]["cpu"], old["threads"]) != (cpu_info().model, args.threads):
            raise SystemExit(f"{out / 'results.json'} was measured on {old['machine']['cpu']} with "
                             f"{old['threads']} thread(s); --append adds rows of the same machine and threads only.")
        record = {**old, "command": f"{old['command']} && {record['command']}"}
    else:
        record["roofline"] = roofline(30)
    modes = args.modes.split(",")
    # compiling pays only where a step runs for hours: the training steps
    pairs = [(s, m) for s in args.steps.split(",") for m in modes if m != "fast+compile" or STEPS[s][1]]
    flops: dict[str, int] = {}
    for name, mode in tqdm(pairs, desc="steps"):
        if name not in flops:
            flops[name] = step_flops(name)
        row = measure(name, mode, args.repeat, record["roofline"], flops[name])
        record["rows"] = [r for r in record["rows"] if (r["step"], r["mode"]) != (name, mode)] + [row]
        write_json_atomic(out / "results.json", record)  # what is measured so far
        write_text_atomic(out / "results.md", report(record))
    print(report(record))


if __name__ == "__main__":
    main()
