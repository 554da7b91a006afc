"""``iwsim train``: the world model's stages (codec, dynamics, decoder fine-tune) and imitation
policies."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

from iwsim.commands.common import numbers
from iwsim.core.errors import InputError, check_positive
from iwsim.envs.registry import DEFAULT_TASK as TASK
from iwsim.policies import POLICIES as LEARNED_POLICIES
from iwsim.policies import PRESETS as POLICY_PRESETS

if TYPE_CHECKING:
    from pathlib import Path

C = TypeVar("C")  # a preset's config class


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train a stage of the world model")
    train_sub = p.add_subparsers(dest="train_command", required=True, metavar="STAGE")
    q = train_sub.add_parser("ae", help="stage 1: a codec (the preset says which: consistency-ae or conv-ae)")
    _train_flags(q, "tiny, pusht-64, pusht-128, tiny-conv, conv-x2-64, conv-x8-64, conv-x4-64, conv-x8c32-64, "
                    "conv-x16-64")
    q.set_defaults(func=_train_ae)
    q = train_sub.add_parser("dynamics", help="stage 2: latent consistency dynamics on a frozen stage 1")
    init = q.add_mutually_exclusive_group(required=True)
    init.add_argument("--ae", help="stage-1 run directory or checkpoint (e.g. runs/ae), or a world-model checkpoint "
                      "(its codec): train from scratch")
    init.add_argument("--init", help=f"world-model checkpoint to fine-tune (e.g. {TASK.checkpoint}): its "
                                     "autoencoder, normalisation and network are kept")
    q.add_argument("--variant", default="ours",
                   help="ours, or a benchmark baseline or ablation: deterministic, diffusion, no-context-noise, "
                        "film-actions, no-points, no-unroll, no-delta, window-6, long-unroll, unet (the middle "
                        "blocks at half resolution: a one-level U-Net); or state: the dynamics also takes and "
                        "predicts the robot's own state (the store's data/state; with --init it is added to the "
                        "model); or state-contact: state, its error weighted up where the "
                        "block holds a pusher back from its setpoint; or sampled (trained on jumps from every "
                        "level, sampled in 3 jumps), all-levels (the same training, one jump), detached-unroll "
                        "(fed-back predictions without gradient) or context-wide (context noise up to 0.6 stds "
                        "instead of 0.3), also with --init; "
                        "several joined by '+' apply in turn, e.g. "
                        "long-unroll+deterministic (default: %(default)s)")
    q.add_argument("--context", type=int, help="latents in the window (default: the preset's, or the fine-tuned "
                                               "model's); with --init, a wider window starts with the older "
                                               "latents' weights at zero: the model unchanged")
    q.add_argument("--unroll", type=int, metavar="N",
                   help="predictions unrolled per training sequence at the curriculum's longest (default: the "
                        "preset's or variant's, or the fine-tuned model's longest); from scratch the shorter stages "
                        "stay, with --init every sequence unrolls N")
    q.add_argument("--latent-cache", help="file for the encoded latents, shareable by runs with the same encoder; "
                                          "a store that extends the cached one (a merge of it and more) encodes "
                                          "only its new frames (default: in the run directory)")
    q.add_argument("--compile", action="store_true",
                   help="torch.compile the dynamics network: about a minute of compiling first, then ~1.1-1.2x faster "
                        "steps (bench/results/speed); a speed setting only: a run resumes with or without it")
    _train_flags(q, "tiny, pusht-64")
    q.set_defaults(func=_train_dynamics)
    q = train_sub.add_parser("policy", help="an imitation policy (Diffusion Policy or ACT) on a mixture of stores")
    q.add_argument("--policy", required=True, choices=tuple(LEARNED_POLICIES), help="policy type")
    _train_flags(q, f"{', '.join(POLICY_PRESETS)} (default: the policy's name)")
    q.set_defaults(func=_train_policy, preset=None)
    for action in q._actions:  # --data takes a mixture here
        if action.dest == "data":
            action.help = "STORE[:N][,STORE:N...]: exactly the first N episodes of each store (all without :N)"
    q = train_sub.add_parser("decoder-finetune", help="stage 3: fine-tune a world model's decoder on noisy latents")
    q.add_argument("--world-model", required=True, help="world-model run (e.g. runs/dyn) or checkpoint")
    q.add_argument("--data", required=True, help="episode store to train on")
    q.add_argument("--out", required=True, help="run directory; rerunning the same command resumes it")
    q.add_argument("--steps", type=int, default=500, help="training steps (default: %(default)s)")
    q.add_argument("--lr", type=float, default=1e-4, help="learning rate (default: %(default)s)")
    q.add_argument("--batch-size", type=int, help="global batch size (default: the autoencoder's)")
    q.add_argument("--seed", type=int, help="seed (default: the autoencoder's)")
    q.add_argument("--latent-noise", metavar="LO,HI",
                   help="std range of the noise on the latents the decoder learns to render, in the dynamics' "
                        "standardised units (default: the model's stage-2 context noise)")
    q.add_argument("--symmetric-foreground", action="store_true",
                   help="weight the foreground the decoder paints as the target's (a conv codec's loss weights "
                        "only the target's, so small things grow where the decoder is unsure)")
    q.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N (default: %(default)s)")
    q.add_argument("--force", action="store_true", help="train a run directory that holds a different config")
    q.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    q.set_defaults(func=_train_decoder_finetune)


def _train_flags(q: argparse.ArgumentParser, presets: str) -> None:
    q.add_argument("--data", required=True, help="episode store to train on")
    q.add_argument("--preset", default="pusht-64", help=f"config preset: {presets} (default: %(default)s)")
    q.add_argument("--out", required=True, help="run directory; rerunning the same command resumes it")
    q.add_argument("--steps", type=int, help="override the preset's training steps")
    q.add_argument("--batch-size", type=int, help="override the preset's global batch size")
    q.add_argument("--lr", type=float, help="override the preset's peak learning rate")
    q.add_argument("--seed", type=int, help="override the preset's seed")
    q.add_argument("--bf16", action="store_true", help="bf16 autocast on the CPU too (always on with CUDA); a CPU "
                                                       "without AMX or AVX-512-BF16 trains in float32, with a warning")
    q.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N (default: %(default)s)")
    q.add_argument("--force", action="store_true", help="train a run directory that holds a different config")
    q.add_argument("--dry-run", action="store_true", help="print the resolved config and exit")
    q.add_argument("--no-progress", action="store_true", help="hide the progress bar")


def _resolve_preset(args: argparse.Namespace, presets: dict[str, C],
                    trained: Callable[[C], Any] | None = None) -> C | None:
    """The preset named by --preset with --steps/--batch-size/--seed (and --variant) applied; prints it
    (``trained(preset)``, the config the run trains with, when given) and returns None under --dry-run."""
    import dataclasses
    import json

    from iwsim.core.config import to_dict

    if args.preset not in presets:
        raise InputError(f"unknown preset {args.preset!r}; expected one of {sorted(presets)}.")
    cfg: Any = presets[args.preset]  # a config dataclass with a train field
    overrides = {k: v for k, v in (("steps", args.steps), ("batch_size", args.batch_size), ("seed", args.seed),
                                   ("lr", args.lr)) if v is not None}
    if getattr(args, "bf16", False):
        overrides["cpu_bf16"] = True
    check_positive(args, "steps", "batch_size")
    if args.lr is not None and not (math.isfinite(args.lr) and args.lr > 0):
        raise InputError(f"--lr must be a positive number, got {args.lr}.")
    cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, **overrides))
    if getattr(args, "variant", None) is not None:
        from iwsim.world_model.presets import variant

        cfg = variant(cfg, args.variant)
    if args.dry_run:
        print(json.dumps({"preset": args.preset, **to_dict(cfg if trained is None else trained(cfg))}, indent=2))
        return None
    _check_batch_memory(args.train_command, cfg.train.batch_size, args.data)
    return cfg


def _check_batch_memory(stage: str, batch_size: int, data: str) -> None:
    """Refuse a global batch that cannot fit in memory at the largest frame size of the
    training stores (:func:`iwsim.core.trainer.check_batch_memory`)."""
    from iwsim.core.trainer import check_batch_memory
    from iwsim.data.store import EpisodeStore, StoreError
    from iwsim.envs.registry import DEFAULT_TASK

    if stage == "policy":
        from iwsim.policies.data import parse_mixture

        stores: list[str | Path] = [src.path for src in parse_mixture(data)]
    else:
        stores = [data]
    sizes = []
    for path in stores:
        try:  # the frames themselves: a store imported at its source's size records no image_size
            sizes.append(max(EpisodeStore.open(path).array("img").shape[1:3]))
        except (StoreError, KeyError, TypeError, ValueError):
            pass  # training reports a bad store itself
    check_batch_memory(stage, batch_size, max(sizes, default=DEFAULT_TASK.image_size))


def _print_metrics(metrics: dict[str, float]) -> None:
    if metrics:
        print(" ".join(f"{k}={v:.4f}" for k, v in metrics.items()))


def _train_ae(args: argparse.Namespace) -> int:
    from iwsim.world_model.presets import AE_PRESETS

    cfg = _resolve_preset(args, AE_PRESETS)
    if cfg is None:
        return 0
    from iwsim.core.trainer import resolve_device
    from iwsim.world_model.train_codec import train_autoencoder

    _print_metrics(train_autoencoder(cfg, args.data, args.out, device=resolve_device(args.device),
                                     force=args.force, progress=not args.no_progress))
    return 0


def _train_dynamics(args: argparse.Namespace) -> int:
    from iwsim.world_model.presets import DYNAMICS_PRESETS, FINE_TUNE_VARIANTS

    if args.init is not None and args.variant not in FINE_TUNE_VARIANTS:
        raise InputError("--variant applies to training from scratch (with --init, only "
                         f"{', '.join(FINE_TUNE_VARIANTS)}: state and state-contact add the robot's state to the "
                         "model, sampled, all-levels, detached-unroll and context-wide how it trains and "
                         "samples); --init keeps the model's own objective and network.")
    check_positive(args, "context", "unroll")
    from iwsim.world_model.train_dynamics import run_config, train_dynamics

    def trained(cfg: Any) -> Any:  # what --init, --context and --unroll make of the preset
        from iwsim.world_model import WorldModel

        return run_config(cfg, None if args.init is None else WorldModel.load(args.init), args.context, args.unroll)

    cfg = _resolve_preset(args, DYNAMICS_PRESETS, trained)
    if cfg is None:
        return 0
    from iwsim.core.trainer import resolve_device

    _print_metrics(train_dynamics(cfg, args.data, args.ae, args.out, device=resolve_device(args.device),
                                  force=args.force, progress=not args.no_progress, latent_cache=args.latent_cache,
                                  init=args.init, context=args.context, compile=args.compile, unroll=args.unroll))
    return 0


def _train_policy(args: argparse.Namespace) -> int:
    from iwsim.policies import PRESETS

    args.preset = args.preset or args.policy
    cfg = _resolve_preset(args, PRESETS)
    if cfg is None:
        return 0
    if cfg.policy != args.policy:
        raise InputError(f"preset {args.preset!r} is a {cfg.policy!r} policy, not {args.policy!r}.")
    from iwsim.core.trainer import resolve_device
    from iwsim.policies.data import parse_mixture
    from iwsim.policies.train import train_policy

    _print_metrics(train_policy(cfg, parse_mixture(args.data), args.out, device=resolve_device(args.device),
                                force=args.force, progress=not args.no_progress))
    return 0


def _train_decoder_finetune(args: argparse.Namespace) -> int:
    from iwsim.core.trainer import resolve_device
    from iwsim.world_model.train_codec import finetune_decoder

    check_positive(args, "steps", "batch_size")
    if not args.lr > 0:
        raise InputError(f"--lr must be positive, got {args.lr}.")
    if args.batch_size is not None:
        _check_batch_memory("decoder-finetune", args.batch_size, args.data)
    noise: tuple[float, float] | None = None
    if args.latent_noise is not None:
        expected = "LO,HI with 0 <= LO <= HI"
        lo, hi = numbers("--latent-noise", args.latent_noise, float, expected, 2)
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi):
            raise InputError(f"--latent-noise takes {expected}, got {args.latent_noise!r}.")
        noise = (lo, hi)
    _print_metrics(finetune_decoder(args.world_model, args.data, args.out, device=resolve_device(args.device),
                                    steps=args.steps, batch_size=args.batch_size, lr=args.lr, seed=args.seed,
                                    latent_noise=noise, symmetric_foreground=args.symmetric_foreground,
                                    force=args.force, progress=not args.no_progress))
    return 0
