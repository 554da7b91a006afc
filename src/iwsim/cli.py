"""The ``iwsim`` command: subcommands parse their flags, then call library functions."""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, TypeVar

from iwsim.errors import EXIT_USER_ERROR, InputError, check_positive, check_seed, reporting_errors
from iwsim.resources import human_bytes, set_threads

if TYPE_CHECKING:
    from pathlib import Path

log = logging.getLogger("iwsim")
C = TypeVar("C")  # a preset's config class


def build_parser() -> argparse.ArgumentParser:
    from iwsim.envs import IMAGE_SIZES, POLICIES, TASKS
    from iwsim.policies import POLICIES as LEARNED_POLICIES
    from iwsim.policies import PRESETS as POLICY_PRESETS
    from iwsim.resources import available_cores
    from iwsim.tasks import DEFAULT_TASK as TASK
    from iwsim.tasks import REGISTRY as TASK_REGISTRY

    parser = argparse.ArgumentParser(prog="iwsim", description="Interactive world simulator for robot learning.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("collect", help="record episodes of a MuJoCo task (scripted or learned policy) into a store")
    p.add_argument("--task", help=f"task: {', '.join(TASKS)} (default: a learned policy's own, as its checkpoint "
                   f"records it, else {TASK.kind})")
    scripted = "; ".join(f"{', '.join(names)} ({task})" for task, names in POLICIES.items())
    p.add_argument("--policy", default="play", help=f"scripted policy: {scripted}; or a learned policy's "
                   "run or checkpoint directory (its episodes run batched in this process) (default: %(default)s)")
    p.add_argument("--episodes", type=int, required=True, help="total episodes the store should hold")
    p.add_argument("--steps", type=int, default=200, help="steps per episode (default: %(default)s)")
    p.add_argument(
        "--image-size",
        type=int,
        default=TASK.image_size,
        help=f"square image size: {', '.join(map(str, IMAGE_SIZES))} (default: %(default)s)",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=available_cores(),
        help="worker processes (default: the CPU cores this process may use, %(default)s)",
    )
    p.add_argument("--seed", type=int, default=0, help="episode i uses seed SEED + i (default: %(default)s)")
    p.add_argument("--out", help="store path (default: data/<task>_<policy>.zarr)")
    _wait_for_lock_flag(p)
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=_collect)

    p = sub.add_parser("demos", help="record a pixel expert's successful takes into a store, in MuJoCo or a world "
                                     "model; with --takeover from where a trained policy hands over (HG-DAgger)")
    p.add_argument("--task", metavar="NAME", help=f"task, the takes in its MuJoCo simulator: {', '.join(TASKS)} "
                                                  f"(default: {TASK.kind}; with --world-model, the model's)")
    p.add_argument("--world-model", metavar="CHECKPOINT",
                   help="world model to record inside instead of MuJoCo (from MuJoCo's initial frames); the task is "
                        "the model's")
    p.add_argument("--episodes", type=int, metavar="N", required=True,
                   help="accepted demonstrations the store should hold")
    p.add_argument("--steps", type=int, metavar="N", default=300, help="horizon of a take (default: %(default)s)")
    p.add_argument("--seed", type=int, metavar="N", default=0,
                   help="candidate i starts from seed SEED + i (default: %(default)s)")
    p.add_argument("--out", metavar="STORE", required=True,
                   help="episode store; rerunning the command resumes it, a store recorded otherwise is refused")
    p.add_argument("--accept-iou", "--accept-score", dest="accept_iou", type=float, metavar="X",
                   help="keep a take once its pixel score (T-push: IoU) reaches this (default: the task's success "
                        "score, 0.9)")
    p.add_argument("--tail", type=int, metavar="N", default=10,
                   help="a kept take ends this many steps after its first success; 0 keeps whole takes "
                        "(default: %(default)s)")
    p.add_argument("--batch", type=int, metavar="N", default=16,
                   help="candidates recorded in lockstep (default: %(default)s)")
    p.add_argument("--max-attempts", type=int, metavar="N", help="candidates tried at most (default: 4 x --episodes)")
    p.add_argument("--give-up-after", type=int, metavar="N",
                   help="stop once this many candidates were tried and none was kept (default: never)")
    experts = "; ".join(f"{', '.join(make().pixel_experts)} ({kind})" for kind, make in TASK_REGISTRY.items())
    p.add_argument("--demonstrator", default="expert", metavar="NAME",
                   help=f"the task's pixel expert: {experts} (default: %(default)s)")
    starts = "; ".join(f"{', '.join(make().starts)} ({kind})" for kind, make in TASK_REGISTRY.items())
    p.add_argument("--start", default="random", metavar="NAME",
                   help=f"MuJoCo's initial states: {starts} (default: %(default)s)")
    p.add_argument("--dart-noise", type=float, default=0.0, metavar="STD",
                   help="std (m) of noise added to the executed commands, the clean ones stored (DART) "
                        "(default: %(default)s)")
    p.add_argument("--takeover", metavar="POLICY", help="a trained policy (run or checkpoint) that drives each take "
                   "until the expert takes over; only the expert's part is stored")
    p.add_argument("--takeover-steps", metavar="LO,HI", help="with --takeover, the expert takes over at a step "
                   "drawn from the candidate's seed in LO..HI (default: 40,200)")
    p.add_argument("--image-size", type=int, metavar="N",
                   help=f"frame size in MuJoCo: {', '.join(map(str, IMAGE_SIZES))} (default: the task's, "
                        f"{TASK.image_size})")
    _wait_for_lock_flag(p)
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=_demos)

    p = sub.add_parser("data", help="inspect episode stores")
    data_sub = p.add_subparsers(dest="data_command", required=True, metavar="COMMAND")
    q = data_sub.add_parser("info", help="episodes, frames, arrays and attributes of a store")
    q.add_argument("path", help="episode store (a .zarr directory)")
    q.set_defaults(func=_data_info)
    from iwsim.data.formats import EXPORT_FORMATS, IMPORT_FORMATS

    q = data_sub.add_parser("export", help="write a store as LeRobot v3 / v2.1 or ALOHA HDF5")
    q.add_argument("--format", required=True, choices=EXPORT_FORMATS)
    q.add_argument("--in", dest="src", required=True, help="episode store")
    q.add_argument("--out", required=True, help="output directory (must not exist)")
    q.add_argument("--fps", type=int, help="frames per second (default: the store's)")
    q.add_argument("--task", help="task description (default: the store's task)")
    q.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    q.set_defaults(func=_data_export)
    q = data_sub.add_parser("import", help="read LeRobot, ALOHA/robomimic HDF5 or Diffusion Policy Zarr into a store")
    q.add_argument("--format", required=True, choices=IMPORT_FORMATS)
    q.add_argument("--in", dest="src", required=True, help="dataset directory or file")
    q.add_argument("--out", required=True, help="episode store to create (must not exist)")
    q.add_argument("--camera", help="camera to take frames from (default: the only or the usual one)")
    q.add_argument("--image-size", type=int, default=TASK.image_size,
                   help="frame size after a centred square crop; 0 keeps the source's (default: %(default)s)")
    q.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    q.set_defaults(func=_data_import)
    q = data_sub.add_parser("merge", help="episode stores of one task into a new store (e.g. play + expert data)")
    q.add_argument("sources", nargs="+", help="episode stores, in order")
    q.add_argument("--out", required=True, help="episode store to create (must not exist)")
    q.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    q.set_defaults(func=_data_merge)
    q = data_sub.add_parser("validate", help="check a store or an export against its format; list what is wrong")
    q.add_argument("path", help="episode store, LeRobot dataset directory or HDF5 file/directory")
    q.set_defaults(func=_data_validate)

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
                        "film-actions, no-points, no-unroll, no-delta, window-6, long-unroll; or state: the "
                        "dynamics also takes and predicts the robot's own state (the store's data/state; with "
                        "--init it is added to the model); several joined by '+' apply in turn, e.g. "
                        "long-unroll+deterministic (default: %(default)s)")
    q.add_argument("--context", type=int, help="latents in the window (default: the preset's, or the fine-tuned "
                                               "model's); with --init, a wider window starts with the older "
                                               "latents' weights at zero: the model unchanged")
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

    p = sub.add_parser("eval", help="evaluate a policy closed-loop in MuJoCo or inside the world model")
    eval_sub = p.add_subparsers(dest="eval_command", required=True, metavar="COMMAND")
    q = eval_sub.add_parser("policy", help="success and max score (T-push: IoU) over seeded episodes, with "
                            "intervals and videos")
    q.add_argument("--checkpoint", required=True, help="policy run (its last checkpoint) or checkpoint directory")
    q.add_argument("--task", help=f"task: {', '.join(TASKS)} (default: the one the policy was trained on, as its "
                                  f"checkpoint records it, else {TASK.kind})")
    q.add_argument("--env", default="mujoco", choices=("mujoco", *TASKS, "world-model"),
                   help="mujoco: the task's simulator (a task's name: that task's); world-model: inside --world-model "
                        "(default: %(default)s)")
    q.add_argument("--world-model", help=f"for --env world-model, a world model of the task (default: the task's "
                                         f"shipped one, {TASK.checkpoint} for {TASK.kind})")
    q.add_argument("--trust-model", help="a second world model of the task (trained differently): the policy runs "
                   "in it too, and each episode's score difference says how far the first can be trusted")
    q.add_argument("--paired", metavar="RESULTS", help="for --env world-model, the results.json of the same policy "
                   "in the task's simulator from some of these seeds (at least 2): adds the prediction-powered "
                   "estimate of the real score and success rate, with a 95%% interval")
    q.add_argument("--episodes", type=int, default=50, help="(default: %(default)s)")
    q.add_argument("--seed", type=int, default=100000, help="first MuJoCo seed (default: %(default)s)")
    q.add_argument("--steps", type=int, help=f"steps per episode (default: the task's horizon, {TASK.horizon} for "
                                             f"{TASK.kind})")
    q.add_argument("--videos", type=int, default=4, help="episodes recorded as videos (default: %(default)s)")
    q.add_argument("--action-steps", type=int,
                   help="actions executed per query, overriding the checkpoint's (Diffusion Policy's Ta)")
    q.add_argument("--out", required=True, help="output directory for results.json and videos")
    q.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N (default: %(default)s)")
    q.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    q.set_defaults(func=_eval_policy)

    p = sub.add_parser("export-model", help="write a standalone world-model checkpoint from a training run")
    p.add_argument("--run", "--dynamics", dest="run", required=True,
                   help="run directory of train dynamics or train decoder-finetune, or one of its checkpoints")
    p.add_argument("--out", required=True, help="checkpoint directory to write (e.g. checkpoints/NAME)")
    p.add_argument("--force", action="store_true", help="replace an existing --out")
    p.add_argument("--decoder", help="take the codec of this world model (a train decoder-finetune run or "
                   "checkpoint; its encoder must be --run's)")
    p.add_argument("--novelty-data", metavar="STORE", help="the model's training data: fit the trust signal "
                   "(how unlike this data a step's inputs are) into the checkpoint")
    p.add_argument("--rest-threshold", type=float, help="inference: a scene whose setpoint holds still and whose "
                   "newest latent changed by less than this stays at rest (0: off; default: the run's)")
    p.add_argument("--delta-deadband", type=float, help="inference: a predicted change of a latent cell under this "
                   "is no change (0: off; default: the run's)")
    p.add_argument("--bf16", dest="inference_bf16", action=argparse.BooleanOptionalAction,
                   help="inference under bf16 autocast where the CPU has AMX or AVX-512-BF16 (float32 elsewhere): "
                        "about twice the frames/s of large batches, frames within a few grey levels (default: the "
                        "run's, float32)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=_export_model)

    p = sub.add_parser("wip", help="save a training run's latest resumable state where a new machine finds it "
                                   "(checkpoints/wip/NAME), or restore it")
    wip_sub = p.add_subparsers(dest="wip_command", required=True, metavar="COMMAND")
    q = wip_sub.add_parser("save", help="copy a run's config, metrics and newest checkpoint to --out, replacing "
                                        "the state saved there before")
    q.add_argument("--run", required=True, help="training run directory")
    q.add_argument("--out", required=True, help="where the state goes, e.g. checkpoints/wip/NAME")
    q.set_defaults(func=_wip_save)
    q = wip_sub.add_parser("restore", help="lay a saved state out as a run directory; rerunning the run's command "
                                           "then resumes it exactly")
    q.add_argument("--wip", required=True, help="a state written by iwsim wip save")
    q.add_argument("--out", required=True, help="the run directory (absent, or holding the run at an older step)")
    q.set_defaults(func=_wip_restore)

    p = sub.add_parser("rollout", help="open-loop rollout of a recorded episode: truth | prediction video")
    p.add_argument("--checkpoint", required=True, help="world-model checkpoint directory")
    p.add_argument("--data", required=True, help="episode store")
    p.add_argument("--episode", type=int, default=0, help="episode index (default: %(default)s)")
    p.add_argument("--steps", type=int, default=192, help="predicted steps (default: %(default)s)")
    p.add_argument("--context", type=int, default=1, help="context frames (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="noise seed (default: %(default)s)")
    p.add_argument("--out", required=True, help="video path (.mp4); scores go to .json and _psnr.png beside it")
    p.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N (default: %(default)s)")
    p.set_defaults(func=_rollout)

    p = sub.add_parser("bench", help="world models side by side: video metrics, IoU error, speed, stability")
    p.add_argument("--checkpoint", required=True, help="our world model (checkpoint or run directory)")
    p.add_argument("--name", default="ours", help="its name in the report (default: %(default)s)")
    p.add_argument("--baselines", default="",
                   help="comma-separated NAME=CHECKPOINT pairs, e.g. deterministic=runs/bench/deterministic")
    p.add_argument("--data", help="episode store (default: the one the checkpoint was trained on)")
    p.add_argument("--out", required=True, help="results directory (e.g. bench/results/NAME)")
    p.add_argument("--episodes", type=int, default=20, help="held-out episodes (default: %(default)s)")
    p.add_argument("--steps", type=int, default=192, help="open-loop steps (default: %(default)s)")
    p.add_argument("--stability-steps", type=int, default=9000,
                   help="long-rollout steps per model, 0 to skip (default: %(default)s)")
    p.add_argument("--stability-every", type=int, default=1,
                   help="decode and score every N-th step of the long rollout (default: %(default)s)")
    p.add_argument("--speed-batch", type=int, default=64, help="batch of the batched speed test (default: %(default)s)")
    p.add_argument("--speed-calls", type=int, default=100, help="timed steps per speed test (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="rollout noise seed (default: %(default)s)")
    p.add_argument("--weights", help="LPIPS/FID/FVD weights directory (default: $IWSIM_WEIGHTS, else the cache)")
    p.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N (default: %(default)s)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    p.set_defaults(func=_bench)

    p = sub.add_parser("demo", help="the shipped world model next to MuJoCo under the scripted expert, as a video")
    p.add_argument("--task", default=TASK.kind, help=f"task: {', '.join(TASKS)} (default: %(default)s)")
    p.add_argument("--checkpoint", help=f"world model of the task (default: the task's shipped one, {TASK.checkpoint} "
                   f"for {TASK.kind})")
    p.add_argument("--seed", type=int, default=100000,
                   help="MuJoCo initial state; training data uses seeds below 100000 (default: %(default)s)")
    p.add_argument("--steps", type=int, default=192, help="steps (default: %(default)s)")
    p.add_argument("--policy", default="expert", help="scripted policy: expert or play (default: %(default)s)")
    p.add_argument("--out", default="outputs/demo", help="output directory (default: %(default)s)")
    p.set_defaults(func=_demo)

    p = sub.add_parser("play", help="drive a world model from the browser and record demonstrations")
    p.add_argument("--checkpoint", default=TASK.checkpoint, help="world model (default: %(default)s)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to bind; others need a token of your choice (default: %(default)s)")
    p.add_argument("--port", type=int, default=8000, help="port, 0 for any free one (default: %(default)s)")
    p.add_argument("--token-file", help="file whose first line is the secret sessions need (default: "
                                        "$IWSIM_PLAY_TOKEN, else a random one the page served here knows)")
    p.add_argument("--token", help="the secret on the command line (visible to other users in ps; "
                                   "prefer --token-file or $IWSIM_PLAY_TOKEN)")
    p.add_argument("--allow-origin", action="append", default=[], metavar="ORIGIN",
                   help="another web origin (http://host:port) whose pages may open sessions; repeatable")
    p.add_argument("--record-to", help="episode store that saved demonstrations are appended to")
    p.add_argument("--store", help="episode store to draw 'frame from store' starts from (for a task other than "
                                   "T-push also its starts; default: the store its checkpoint records)")
    p.add_argument("--bindings", help="JSON file of teleop bindings instead of the task's: {\"keys\": {\"w\": "
                                      "[dim, sign], ...}, \"axes\": [[axis, dim, sign], ...], \"speed\": "
                                      "[units/s per dim]}")
    p.add_argument("--hz", type=float, default=10.0, help="control rate, steps per second (default: %(default)s)")
    p.add_argument("--max-sessions", type=int, default=4, help="concurrent sessions (default: %(default)s)")
    p.add_argument("--device", default="auto", help="auto, cpu, cuda or cuda:N (default: %(default)s)")
    _wait_for_lock_flag(p)
    p.set_defaults(func=_play)
    p = sub.add_parser("experiment", help="the robot-learning studies: data generation, policy evaluation")
    exp_sub = p.add_subparsers(dest="experiment", required=True, metavar="EXPERIMENT")
    q = exp_sub.add_parser("datagen", help="policies trained on world-model demonstrations vs simulator ones")
    q.add_argument("--preset", default="default", choices=("default", "act", "tiny"),
                   help="default: Diffusion Policy, mixtures and sizes; act: ACT, mixtures (default: %(default)s)")
    _study_task_flags(q, TASK)
    q.add_argument("--policy", choices=tuple(LEARNED_POLICIES), help="policy type (default: the preset's)")
    q.add_argument("--episodes", type=int, help="MuJoCo evaluation episodes per policy (default: the preset's, 50)")
    q.add_argument("--steps", type=int, help=f"steps per evaluation episode (default: the preset's, the task's "
                                             f"horizon: {TASK.horizon} for {TASK.kind})")
    q.add_argument("--total", type=int, help="demonstrations per mixture run (default: the preset's, 100)")
    q.add_argument("--fractions", help="world-model shares of the mixture runs, comma-separated (default: the "
                                       "preset's, 0,0.25,0.5,0.75,1)")
    q.add_argument("--sizes", help="simulator dataset sizes, comma-separated (default: the preset's)")
    q.add_argument("--wm-sizes", help="world-model dataset sizes, comma-separated (default: the preset's)")
    q.add_argument("--train-steps", type=int, help="training steps per policy (default: the preset's)")
    q.add_argument("--accept-iou", "--accept-score", dest="accept_iou", type=float,
                   help="keep takes whose max pixel score (T-push: IoU) reaches this (default: the preset's, 0.9)")
    q.add_argument("--demo-steps", type=int, help="horizon of a demonstration take (default: the preset's)")
    _study_run_flags(q, "datagen, or datagen-act for --preset act")
    q.set_defaults(func=_experiment_datagen)
    q = exp_sub.add_parser("policy-eval", help="does the world model rank policies like MuJoCo? (r, rho, MMRV)")
    q.add_argument("--preset", default="default", choices=("default", "tiny"), help="scale (default: %(default)s)")
    _study_task_flags(q, TASK)
    q.add_argument("--episodes", type=int, help="episodes per policy and simulator (default: the preset's, 20)")
    q.add_argument("--steps", type=int, help=f"steps per episode (default: the preset's, the task's horizon: "
                                             f"{TASK.horizon} for {TASK.kind})")
    q.add_argument("--seed", type=int, help="episode i starts from MuJoCo seed SEED + i (default: 100000)")
    q.add_argument("--demos", help="demonstration store of the task the policies train on, e.g. from iwsim collect "
                                   "--policy expert (default: the simulator expert's, recorded under --work when "
                                   "missing)")
    q.add_argument("--demo-episodes", type=int, help="demonstrations of the full-data runs (default: 100)")
    q.add_argument("--small-demos", type=int, help="demonstrations of the small-data run (default: 25)")
    q.add_argument("--paired-episodes", help="N,N,...: paired estimates from each policy's first N first states in "
                   "both simulators (e.g. 2,5,10), judged against MuJoCo on --holdout-episodes other first states "
                   "(default: none)")
    q.add_argument("--holdout-episodes", type=int, help="MuJoCo episodes per policy that judge the paired "
                   "estimates (default: 50)")
    _study_run_flags(q, "policy_eval")
    q.set_defaults(func=_experiment_policy_eval)
    for q in _leaf_parsers(parser):
        q.add_argument("--threads", type=int,
                       help="torch threads (default: $OMP_NUM_THREADS, else the CPU cores this process may use)")
    return parser


def _study_task_flags(q: argparse.ArgumentParser, default: Any) -> None:
    """A study's --task, --world-model and --demonstrator (``default``: the default task)."""
    from iwsim.envs import TASKS
    from iwsim.tasks import ANY_EXPERTS

    q.add_argument("--task", default=default.kind, choices=tuple(TASKS),
                   help="the task, its MuJoCo simulator the ground truth and its pixel expert the demonstrator "
                        "(default: %(default)s)")
    q.add_argument("--world-model", help=f"a world-model checkpoint of the task (default: the task's shipped one, "
                                         f"{default.checkpoint} for {default.kind}; a task without one needs it)")
    q.add_argument("--demonstrator", choices=ANY_EXPERTS,
                   help="the task's pixel expert that records the demonstrations, e.g. T-push's expert-wide (wider "
                        "margins, easier to imitate); its takes get their own stores (default: expert)")


def _study_run_flags(q: argparse.ArgumentParser, report: str) -> None:
    """A study's --jobs, --out (``report``: its default under bench/results/experiments),
    --work and --no-progress."""
    from iwsim.resources import available_cores

    q.add_argument("--jobs", type=int, default=min(2, available_cores()),
                   help="trainings/evaluations at once, one thread each (default: %(default)s)")
    q.add_argument("--out", help=f"report directory (default: bench/results/experiments/{report}; another task's "
                                 "under bench/results/experiments/TASK)")
    q.add_argument("--work", default="runs/experiments", help="demos, runs, evaluations; another task's under "
                                                               "WORK/TASK (default: %(default)s)")
    q.add_argument("--no-progress", action="store_true", help="hide the progress bars")


def _study_config(args: argparse.Namespace, presets: dict[str, C], report: str, **overrides: Any) -> tuple[C, Path]:
    """A study's config: its preset on --task (:func:`iwsim.experiments.common.on_task`),
    the task's world model and the flags' ``overrides`` (None: not given); and its report
    directory (--out, else ``report`` under the task's ``bench/results/experiments``)."""
    import dataclasses
    from pathlib import Path

    from iwsim.experiments.common import on_task, study_dir
    from iwsim.tasks import get_task, shipped_world_model

    task = get_task(args.task)
    cfg: Any = on_task(presets[args.preset], task)  # a study's config dataclass
    overrides["world_model"] = args.world_model or shipped_world_model(task)
    cfg = dataclasses.replace(cfg, **{k: v for k, v in overrides.items() if v is not None})
    return cfg, Path(args.out) if args.out else study_dir("bench/results/experiments", task) / report


def _wait_for_lock_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument("--wait-for-lock", action="store_true",
                   help="when another process is writing the store, wait for it instead of stopping")


def _leaf_parsers(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    """The parsers of every (sub)command that runs something."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        return [parser]
    return [leaf for a in subs for p in dict.fromkeys(a.choices.values()) for leaf in _leaf_parsers(p)]


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``iwsim`` console script; returns the exit status."""
    args = build_parser().parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # what a report records of its command
    rank = int(os.environ.get("RANK", "0"))  # under torchrun only rank 0 logs
    logging.basicConfig(level=logging.INFO if rank == 0 else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    # PyOpenGL (under MuJoCo's renderer) says at import, at INFO, that its optional
    # accelerator is missing: noise, and a user error must stay one line.
    logging.getLogger("OpenGL").setLevel(logging.WARNING)
    def body() -> int:
        set_threads(args.threads)
        return args.func(args)

    return reporting_errors("iwsim", body)


def _collect(args: argparse.Namespace) -> int:
    from pathlib import Path

    from iwsim.data.collect import collect
    from iwsim.envs import POLICIES
    from iwsim.tasks import DEFAULT_TASK

    recorder, policy = None, args.policy
    if policy not in POLICIES.get(args.task or DEFAULT_TASK.kind, ()) and Path(policy).is_dir():  # a learned policy
        from iwsim.eval.policy import recorder as learned
        from iwsim.policies.factory import load_policy
        from iwsim.tasks import REGISTRY

        if args.out is None:
            raise InputError("collecting a learned policy's episodes needs --out STORE.")
        net = load_policy(policy)
        own = net.task.name if net.task is not None and net.task.kind in REGISTRY else None
        if args.task is not None and own is not None and own != args.task:
            raise InputError(f"{policy} was trained on episodes of task {own!r} (its checkpoint records it), not "
                             f"--task {args.task}; collect its episodes with --task {own} (or without --task).")
        args.task = args.task or own or DEFAULT_TASK.kind
        if net.image_size != args.image_size:
            raise InputError(f"{policy} was trained on {net.image_size}x{net.image_size} frames, not --image-size "
                             f"{args.image_size}.")
        recorder = learned(net, args.task, args.steps, image_size=args.image_size)
        policy = f"learned:{Path(policy).as_posix()}"
    args.task = args.task or DEFAULT_TASK.kind
    out = args.out or f"data/{args.task}_{args.policy}.zarr"
    collect(
        args.task,
        policy,
        args.episodes,
        out=out,
        steps=args.steps,
        image_size=args.image_size,
        workers=args.workers,
        seed=args.seed,
        progress=not args.no_progress,
        wait_for_lock=args.wait_for_lock,
        recorder=recorder,
    )
    return 0


def _demos(args: argparse.Namespace) -> int:
    from iwsim.eval.policy import WORLD_MODEL
    from iwsim.experiments.demos import record_demos
    from iwsim.tasks import DEFAULT_TASK, get_task

    handover: dict[str, Any] = {}  # --takeover-steps, else record_demos's default
    if args.takeover_steps is not None:
        if args.takeover is None:
            raise InputError("--takeover-steps applies to --takeover (when the expert takes over from the policy).")
        handover["takeover_steps"] = _numbers("--takeover-steps", args.takeover_steps, int, "LO,HI, two steps", 2)
    if args.world_model is not None and args.image_size is not None:
        raise InputError("--image-size applies to MuJoCo; a world model renders frames of its own size.")
    # a batch's candidates keep every step's frame until they are judged
    _check_frames_memory(f"--batch {args.batch} of --steps {args.steps}", args.batch * (args.steps + 1))
    task = None if args.task is None else get_task(args.task)
    env = (task or DEFAULT_TASK()).kind
    if args.world_model is not None:
        env = WORLD_MODEL
    stats = record_demos(env, args.out, args.episodes, args.steps, args.seed, world_model=args.world_model,
                         accept_iou=args.accept_iou, tail=None if args.tail == 0 else args.tail, batch=args.batch,
                         max_attempts=args.max_attempts, give_up_after=args.give_up_after,
                         dart_noise=args.dart_noise, start=args.start, demonstrator=args.demonstrator,
                         takeover=args.takeover, image_size=args.image_size, progress=not args.no_progress,
                         wait_for_lock=args.wait_for_lock, model_task=task, **handover)
    print(stats.summary())
    return 0


def _data_info(args: argparse.Namespace) -> int:
    from iwsim.data.store import EpisodeStore

    info = EpisodeStore.open(args.path, "r").info()
    attrs = info["attrs"]
    rows = [
        ("path", info["path"]),
        ("task", f"{info['task']} (policy {attrs['policy']})" if "policy" in attrs else info["task"]),
        ("episodes", info["episodes"]),
        ("frames", info["frames"]),
        ("fps", info["fps"]),
        ("image size", info["image_size"]),
        ("size on disk", human_bytes(info["bytes_on_disk"])),
    ]
    width = max(len(k) for k, _ in rows)
    lines = [f"{k:<{width}}  {v}" for k, v in rows]
    lines.append("arrays")
    kw = max((len(k) for k in info["arrays"]), default=0)
    for k, a in info["arrays"].items():
        lines.append(f"  {k:<{kw}}  {str(a['shape']):<20} {a['dtype']}")
    print("\n".join(lines))
    return 0


def _data_export(args: argparse.Namespace) -> int:
    from iwsim.data.formats import export

    check_positive(args, "fps")
    print(export(args.format, args.src, args.out, fps=args.fps, task=args.task, progress=not args.no_progress))
    return 0


def _data_import(args: argparse.Namespace) -> int:
    from iwsim.data.formats import import_

    if args.image_size < 0:
        raise InputError(f"--image-size must be a positive integer or 0, got {args.image_size}.")
    store = import_(args.format, args.src, args.out, camera=args.camera, image_size=args.image_size or None,
                    progress=not args.no_progress)
    print(f"{store.path}: {store.n_episodes} episodes, {store.n_frames} frames")
    return 0


def _data_merge(args: argparse.Namespace) -> int:
    from iwsim.data.formats import merge

    store = merge(args.sources, args.out, progress=not args.no_progress)
    print(f"{store.path}: {store.n_episodes} episodes, {store.n_frames} frames ({store.attrs['policy']})")
    return 0


def _data_validate(args: argparse.Namespace) -> int:
    from iwsim.data.formats import validate

    kind, problems = validate(args.path)
    if not problems:
        print(f"{args.path}: a valid {kind}")
        return 0
    print(f"{args.path}: {kind} with {len(problems)} problem(s):", file=sys.stderr)
    for p in problems:
        print(f"  {p}", file=sys.stderr)
    return EXIT_USER_ERROR


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


def _numbers(flag: str, text: str, kind: type, expected: str | None = None, count: int | None = None) -> tuple:
    """The comma-separated numbers of a flag's value (``count`` of them when given), or
    one line: "FLAG takes EXPECTED, got TEXT." (EXPECTED: comma-separated KINDs)."""
    try:
        values = tuple(kind(v) for v in text.split(",") if v.strip())
    except ValueError:
        values = None
    if values is None or (count is not None and len(values) != count):
        raise InputError(f"{flag} takes {expected or f'comma-separated {kind.__name__}s'}, got {text!r}.")
    return values


def _check_frames_memory(what: str, frames: int, copies: int = 1) -> None:
    """Refuse flags that keep more frames in memory than fit: a lower bound, counted as RGB
    frames of the smallest image size (the model's may be larger)."""
    from iwsim.envs import SMALLEST_FRAME_BYTES
    from iwsim.resources import require_memory

    require_memory(frames * copies * SMALLEST_FRAME_BYTES, f"{what} (at least {frames * copies} frames in memory)")


def _resolve_preset(args: argparse.Namespace, presets: dict[str, C],
                    trained: Callable[[C], Any] | None = None) -> C | None:
    """The preset named by --preset with --steps/--batch-size/--seed (and --variant) applied; prints it
    (``trained(preset)``, the config the run trains with, when given) and returns None under --dry-run."""
    import dataclasses
    import json

    from iwsim.config import to_dict

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
    training stores (:func:`iwsim.training.trainer.check_batch_memory`)."""
    from iwsim.data.store import EpisodeStore, StoreError
    from iwsim.tasks import DEFAULT_TASK
    from iwsim.training.trainer import check_batch_memory

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
    from iwsim.training.trainer import resolve_device
    from iwsim.world_model.train_codec import train_autoencoder

    _print_metrics(train_autoencoder(cfg, args.data, args.out, device=resolve_device(args.device),
                                     force=args.force, progress=not args.no_progress))
    return 0


def _train_dynamics(args: argparse.Namespace) -> int:
    from iwsim.world_model.presets import DYNAMICS_PRESETS

    if args.init is not None and args.variant not in ("ours", "state"):
        raise InputError("--variant applies to training from scratch (with --init, only 'state', which adds the "
                         "robot's state to the model); --init keeps the model's own objective and network.")
    check_positive(args, "context")
    from iwsim.world_model.train_dynamics import run_config, train_dynamics

    def trained(cfg: Any) -> Any:  # what --init and --context make of the preset
        from iwsim.world_model import WorldModel

        return run_config(cfg, None if args.init is None else WorldModel.load(args.init), args.context)

    cfg = _resolve_preset(args, DYNAMICS_PRESETS, trained)
    if cfg is None:
        return 0
    from iwsim.training.trainer import resolve_device

    _print_metrics(train_dynamics(cfg, args.data, args.ae, args.out, device=resolve_device(args.device),
                                  force=args.force, progress=not args.no_progress, latent_cache=args.latent_cache,
                                  init=args.init, context=args.context, compile=args.compile))
    return 0


def _train_policy(args: argparse.Namespace) -> int:
    from iwsim.policies import PRESETS

    args.preset = args.preset or args.policy
    cfg = _resolve_preset(args, PRESETS)
    if cfg is None:
        return 0
    if cfg.policy != args.policy:
        raise InputError(f"preset {args.preset!r} is a {cfg.policy!r} policy, not {args.policy!r}.")
    from iwsim.policies.data import parse_mixture
    from iwsim.training.policy import train_policy
    from iwsim.training.trainer import resolve_device

    _print_metrics(train_policy(cfg, parse_mixture(args.data), args.out, device=resolve_device(args.device),
                                force=args.force, progress=not args.no_progress))
    return 0


def _eval_policy(args: argparse.Namespace) -> int:
    from pathlib import Path

    import torch

    from iwsim.checkpoint import load_json
    from iwsim.eval.policy import WORLD_MODEL, check_args, check_model_task, check_paired, choose_task, evaluate
    from iwsim.eval.records import command_line
    from iwsim.experiments.common import fingerprint
    from iwsim.policies.factory import checkpoint_dir, load_policy, recorded_task
    from iwsim.tasks import DEFAULT_TASK, shipped_world_model
    from iwsim.training.trainer import resolve_device
    from iwsim.world_model_env import score_key

    env, task = choose_task(args.env, args.task, recorded_task(args.checkpoint))
    steps = args.steps if args.steps is not None else (task or DEFAULT_TASK()).horizon or DEFAULT_TASK.horizon
    check_args(args.episodes, args.seed, steps, args.videos, env)
    if args.trust_model is not None and env != WORLD_MODEL:
        raise InputError("--trust-model applies to --env world-model (MuJoCo is the ground truth).")
    if args.paired is not None and env != WORLD_MODEL:
        raise InputError("--paired applies to --env world-model (it corrects the model's score with real episodes).")
    world_model = None
    if env == WORLD_MODEL:
        world_model = args.world_model or shipped_world_model(task)
    device = resolve_device(args.device)
    torch.manual_seed(0)  # the policy's sampling noise, as the studies seed it: the same command, the same scores
    policy = load_policy(args.checkpoint, device, n_action_steps=args.action_steps)
    wm = partner = None
    if world_model is not None:
        from iwsim.world_model import WorldModel

        wm = WorldModel.load(world_model, device)
        task = check_model_task(wm, task, f"--world-model {world_model}")
        if args.trust_model is not None:
            partner = WorldModel.load(args.trust_model, device)
            check_model_task(partner, task, f"--trust-model {args.trust_model}")
            from iwsim.checkpoint import same_weights

            if same_weights(partner, wm):
                raise InputError(f"--trust-model {args.trust_model} holds the same weights as --world-model "
                                 f"{world_model}: the model would be checked against itself; give a second model "
                                 "trained differently (another seed or other data).")
    policy_sha256 = fingerprint(checkpoint_dir(args.checkpoint))
    real = None
    if args.paired is not None:
        assert task is not None  # the world model's
        real = load_json(Path(args.paired), "--paired results")
        check_paired(real, task, [args.seed + i for i in range(args.episodes)], steps, policy_sha256,
                     policy.cfg.n_action_steps, args.paired)
    result = evaluate(policy, env, episodes=args.episodes, seed=args.seed, steps=steps, world_model=wm,
                      image_size=policy.image_size, out=args.out, videos=args.videos, progress=not args.no_progress,
                      meta={"checkpoint": str(args.checkpoint), "policy_sha256": policy_sha256,
                            "n_action_steps": policy.cfg.n_action_steps, "world_model": world_model,
                            "trust_model": args.trust_model, "paired_results": args.paired},
                      partner=partner, command=command_line("iwsim", args.argv), paired=real)
    if result["scorer"] is None:
        print(f"{env}: no scorer (task {result['task']!r} has no pixel scorer): {args.episodes} episodes of "
              f"{steps} steps without a score; {result['env_steps_per_s']:.0f} env steps/s -> {args.out}")
        return 0
    post = result["success_beta_posterior"]
    lo, hi = result["success_clopper_pearson"]
    assert task is not None  # the simulator's, or the world model's
    mean = result[f"mean_max_{score_key(task)}"]
    print(f"{env}: mean max {result['scorer']} {mean:.3f}; success {result['success_rate']:.2f} "
          f"(Beta posterior mean {post['mean']:.2f}, 95% {post['low']:.2f}-{post['high']:.2f}; "
          f"Clopper-Pearson {lo:.2f}-{hi:.2f}); {result['env_steps_per_s']:.0f} env steps/s -> {args.out}")
    if "paired" in result:
        est, rate = result["paired"][f"mean_max_{score_key(task)}"], result["paired"]["success_rate"]
        print(f"paired with {est['n_paired']} real episodes ({args.paired}): real mean max {result['scorer']} "
              f"{est['estimate']:.3f} (95% {est['interval'][0]:.3f}-{est['interval'][1]:.3f}; the model's own "
              f"{est['model_mean']:.3f}, its bias on the pairs {est['bias_paired']:+.3f}); success "
              f"{rate['estimate']:.2f} (95% {rate['interval'][0]:.2f}-{rate['interval'][1]:.2f}); worth "
              f"{est['effective_n']:.1f} real episodes (prediction-powered, Student t)")
    if "disagreement" in result:
        dis = result["disagreement"]
        print(f"trust: the two world models' scores differ by {dis['mean']:.3f} on average; "
              f"{100 * dis['above_warn']:.0f}% of episodes differ by more than {dis['warn']:g}, where the score is "
              "least to be trusted")
    if "novelty" in result:
        nov = result["novelty"]
        print(f"novelty: {nov['mean']:.2f} on average (about 1 on the model's training data); "
              f"{100 * nov['above_warn']:.0f}% of episodes above {nov['warn']:g} stray from it")
    return 0


def _train_decoder_finetune(args: argparse.Namespace) -> int:
    from iwsim.training.trainer import resolve_device
    from iwsim.world_model.train_codec import finetune_decoder

    check_positive(args, "steps", "batch_size")
    if not args.lr > 0:
        raise InputError(f"--lr must be positive, got {args.lr}.")
    if args.batch_size is not None:
        _check_batch_memory("decoder-finetune", args.batch_size, args.data)
    noise: tuple[float, float] | None = None
    if args.latent_noise is not None:
        expected = "LO,HI with 0 <= LO <= HI"
        lo, hi = _numbers("--latent-noise", args.latent_noise, float, expected, 2)
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi):
            raise InputError(f"--latent-noise takes {expected}, got {args.latent_noise!r}.")
        noise = (lo, hi)
    _print_metrics(finetune_decoder(args.world_model, args.data, args.out, device=resolve_device(args.device),
                                    steps=args.steps, batch_size=args.batch_size, lr=args.lr, seed=args.seed,
                                    latent_noise=noise, symmetric_foreground=args.symmetric_foreground,
                                    force=args.force, progress=not args.no_progress))
    return 0


def _export_model(args: argparse.Namespace) -> int:
    from iwsim.checkpoint import resolve_checkpoint
    from iwsim.world_model import WorldModel, export_model
    from iwsim.world_model.model import INFERENCE_SETTINGS, check_inference

    inference = check_inference({k: v for k in INFERENCE_SETTINGS if (v := getattr(args, k)) is not None})
    novelty = None
    if args.novelty_data is not None:
        from iwsim.world_model.dynamics_data import fit_store_novelty

        novelty = fit_store_novelty(WorldModel.load(resolve_checkpoint(args.run)), args.novelty_data,
                                    progress=not args.no_progress)
    path = export_model(args.run, args.out, force=args.force, decoder=args.decoder, novelty=novelty,
                        inference=inference)
    print(path)
    return 0


def _wip_save(args: argparse.Namespace) -> int:
    from iwsim.eval.records import command_line
    from iwsim.training.wip import save_wip

    info = save_wip(args.run, args.out, command=command_line("iwsim", args.argv))
    print(f"{args.out}: {args.run} at step {info['step']} (restore it with iwsim wip restore --wip {args.out} "
          f"--out {args.run}, then rerun the run's command)")
    return 0


def _wip_restore(args: argparse.Namespace) -> int:
    from iwsim.training.wip import restore_wip

    info = restore_wip(args.wip, args.out)
    print(f"{args.out}: restored at step {info['step']}; rerun the run's command to resume it")
    return 0


def _rollout(args: argparse.Namespace) -> int:
    from iwsim.data.store import EpisodeStore
    from iwsim.eval.rollout import open_loop, write_side_by_side
    from iwsim.training.trainer import resolve_device
    from iwsim.world_model import WorldModel

    if not str(args.out).endswith(".mp4"):
        raise InputError(f"--out must be an .mp4 path, got {args.out!r}.")
    check_positive(args, "steps", "context")
    store = EpisodeStore.open(args.data, "r")
    if not 0 <= args.episode < store.n_episodes:  # (a negative index would silently count from the end)
        raise InputError(f"--episode must be in 0..{store.n_episodes - 1} ({args.data} holds {store.n_episodes} "
                         f"episodes), got {args.episode}.")
    wm = WorldModel.load(args.checkpoint, resolve_device(args.device))
    result = open_loop(wm, store, [args.episode], args.steps, args.context, args.seed, progress=True)
    path = write_side_by_side(result, args.out)
    s = result.summary()
    print(f"{path}: mean PSNR {s['psnr']:.2f} dB, SSIM {s['ssim']:.3f}, last-step PSNR {s['psnr_last']:.2f} dB, "
          + ("no scorer (the task has no pixel scorer)" if s["iou_abs_err"] is None else
             f"mean |IoU error| {s['iou_abs_err']:.3f}"))
    return 0


def _bench(args: argparse.Namespace) -> int:
    from pathlib import Path

    from iwsim.eval.benchmark import run_benchmark
    from iwsim.eval.records import command_line
    from iwsim.training.trainer import resolve_device

    models = {args.name: args.checkpoint}
    for item in filter(None, (x.strip() for x in args.baselines.split(","))):
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise InputError(f"--baselines entries must be NAME=CHECKPOINT, got {item!r}.")
        if name in models:
            raise InputError(f"model name {name!r} is given twice.")
        models[name] = path
    check_positive(args, "episodes", "steps", "stability_every", "speed_batch", "speed_calls")
    if args.stability_steps < 0:
        raise InputError(f"--stability-steps must be >= 0, got {args.stability_steps}.")
    # the recorded episodes and every model's rollout of them
    _check_frames_memory(f"--episodes {args.episodes} x --steps {args.steps}", args.episodes * (args.steps + 1),
                         len(models) + 1)
    run_benchmark(models, args.out, args.data, episodes=args.episodes, steps=args.steps,
                  stability_steps=args.stability_steps, stability_every=args.stability_every,
                  speed_batch=args.speed_batch, speed_calls=args.speed_calls, seed=args.seed,
                  weights=Path(args.weights) if args.weights else None, device=resolve_device(args.device),
                  progress=not args.no_progress, command=command_line("iwsim", args.argv))
    print(Path(args.out) / "results.md")
    return 0


def _play(args: argparse.Namespace) -> int:
    from iwsim.play.access import LOOPBACK, Access, bind, check_bind, resolve_token
    from iwsim.play.engine import check_sessions_memory

    # Before the model loads: a bad token, too many sessions for this machine's memory or a
    # taken port fails at once.
    token, source = resolve_token(args.token, args.token_file)
    bindings = None if args.bindings is None else _read_json(args.bindings, "--bindings")
    check_positive(args, "max_sessions")
    check_sessions_memory(args.max_sessions)
    check_bind(args.host, token)
    sock = bind(args.host, args.port)
    try:
        access = Access.create(token, args.host, sock.getsockname()[1], args.allow_origin)
        from pathlib import Path

        from iwsim.play.engine import Engine, PlayConfig
        from iwsim.play.server import serve
        from iwsim.training.trainer import resolve_device
        from iwsim.world_model import WorldModel

        port = access.port
        cfg = PlayConfig(hz=args.hz, max_sessions=args.max_sessions, checkpoint=args.checkpoint,
                         record_to=Path(args.record_to) if args.record_to else None,
                         store=Path(args.store) if args.store else None, wait_for_lock=args.wait_for_lock,
                         bindings=bindings)
        engine = Engine(WorldModel.load(args.checkpoint, resolve_device(args.device)), cfg)
        shown = "localhost" if args.host in ("0.0.0.0", "::") else args.host
        # The token is never logged: the page served here carries it, remote users know their own.
        how = "" if args.host in LOOPBACK else f"; from elsewhere open /?token=... with the token of {source}"
        log.info("serving %s at http://%s:%d/ (%s Hz, up to %d sessions%s%s); Ctrl-C stops", args.checkpoint,
                 shown, port, args.hz, args.max_sessions,
                 f", recording to {args.record_to}" if args.record_to else "", how)
        serve(engine, sock, access)
    finally:
        sock.close()
    return 0


def _read_json(path: str, flag: str) -> object:
    import json

    from iwsim.resources import read_capped

    try:
        return json.loads(read_capped(path, 16 << 20))
    except OSError as e:
        raise InputError(f"{flag} {path}: cannot read it ({e.strerror}).") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{flag} {path} is not valid JSON: {e}.") from None


def _experiment_datagen(args: argparse.Namespace) -> int:
    import dataclasses

    from iwsim.experiments.datagen import PRESETS, run_datagen

    def numbers(flag: str, text: str | None, kind: type) -> tuple | None:
        return None if text is None else _numbers(flag, text, kind)

    base = PRESETS[args.preset]
    recipe = {"accept_iou": args.accept_iou, "steps": args.demo_steps, "demonstrator": args.demonstrator}
    report = "datagen" + ("-act" if args.preset == "act" else "")
    cfg, out = _study_config(
        args, PRESETS, report, policy=args.policy, episodes=args.episodes, steps=args.steps, total=args.total,
        train_steps=args.train_steps, wm_fractions=numbers("--fractions", args.fractions, float),
        sim_sizes=numbers("--sizes", args.sizes, int), wm_sizes=numbers("--wm-sizes", args.wm_sizes, int),
        recipe=dataclasses.replace(base.recipe, **{k: v for k, v in recipe.items() if v is not None}))
    run_datagen(cfg, out=out, work=args.work, preset=args.preset, jobs=args.jobs, progress=not args.no_progress)
    print(f"{out}/results.md")
    return 0


def _experiment_policy_eval(args: argparse.Namespace) -> int:
    import dataclasses

    from iwsim.experiments.policy_eval import PRESETS, headline, run_policy_eval

    base = PRESETS[args.preset].recipe
    recipe = base if args.demonstrator is None else dataclasses.replace(base, demonstrator=args.demonstrator)
    cfg, out = _study_config(args, PRESETS, "policy_eval", episodes=args.episodes, steps=args.steps, seed=args.seed,
                             demos=args.demos, demo_episodes=args.demo_episodes, small_demos=args.small_demos,
                             recipe=recipe, paired=None if args.paired_episodes is None else
                             _numbers("--paired-episodes", args.paired_episodes, int, "counts N,N,..."),
                             holdout_episodes=args.holdout_episodes)
    report = run_policy_eval(cfg, out=out, work=args.work, preset=args.preset, jobs=args.jobs,
                             progress=not args.no_progress)
    print(f"{headline(report)} -> {out}/results.md")
    return 0


def _demo(args: argparse.Namespace) -> int:
    from iwsim import demo

    check_seed(args, "seed")
    _check_frames_memory(f"--steps {args.steps}", args.steps + 1, 2)  # MuJoCo's frames and the model's

    return demo.main(args)


if __name__ == "__main__":
    sys.exit(main())
