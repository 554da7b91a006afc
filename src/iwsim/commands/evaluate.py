"""``iwsim eval policy``: a policy closed-loop in MuJoCo or inside a world model."""

from __future__ import annotations

import argparse

from iwsim.core.errors import InputError
from iwsim.envs import TASKS
from iwsim.envs.registry import DEFAULT_TASK as TASK


def register(sub: argparse._SubParsersAction) -> None:
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
    q.add_argument("--samples", type=int, default=1, help="for --env world-model, samples of the model per first "
                   "state (its noise drawn again): their score spread per episode is a trust signal; the score is "
                   "the first sample's (default: %(default)s)")
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


def _eval_policy(args: argparse.Namespace) -> int:
    from pathlib import Path

    import torch

    from iwsim.core.checkpoint import load_json
    from iwsim.core.trainer import resolve_device
    from iwsim.envs.registry import DEFAULT_TASK, shipped_world_model
    from iwsim.eval.policy import (
        WORLD_MODEL,
        check_args,
        check_model_task,
        check_paired,
        check_samples,
        choose_task,
        evaluate,
    )
    from iwsim.eval.records import command_line
    from iwsim.experiments.common import fingerprint
    from iwsim.policies.factory import checkpoint_dir, load_policy, recorded_task
    from iwsim.world_model.env import score_key

    env, task = choose_task(args.env, args.task, recorded_task(args.checkpoint))
    steps = args.steps if args.steps is not None else (task or DEFAULT_TASK()).horizon or DEFAULT_TASK.horizon
    check_args(args.episodes, args.seed, steps, args.videos, env)
    if args.trust_model is not None and env != WORLD_MODEL:
        raise InputError("--trust-model applies to --env world-model (MuJoCo is the ground truth).")
    check_samples(args.samples, env)  # before anything loads (the evaluation checks it again)
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
            from iwsim.core.checkpoint import same_weights

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
                      partner=partner, command=command_line("iwsim", args.argv), paired=real, samples=args.samples)
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
    if "implausibility" in result:
        imp = result["implausibility"]
        print(f"plausibility: the model's frames fit the task's objects {1 - imp['mean']:.3f} on average (the "
              f"simulator's ~0.95); {100 * imp['above_warn']:.0f}% of episodes below {1 - imp['warn']:g}, where "
              "the score is least to be trusted")
    if "sample_spread" in result:
        spread = result["sample_spread"]
        print(f"samples: {args.samples} samples of the model per first state differ by {spread['mean']:.3f} on "
              f"average; {100 * spread['above_warn']:.0f}% of episodes by more than {spread['warn']:g}")
    if "command_lead" in result:
        lead = result["command_lead"]
        print(f"command lead: the policy's commands run {lead['mean']:.3f} of the half view ahead of the robot it "
              f"saw (each episode's 90th percentile, averaged); {100 * lead['above_warn']:.0f}% of episodes beyond "
              f"{lead['warn']:g}, pressing where the model's training data rarely went")
    if "novelty" in result:
        nov = result["novelty"]
        print(f"novelty: {nov['mean']:.2f} on average (about 1 on the model's training data); "
              f"{100 * nov['above_warn']:.0f}% of episodes above {nov['warn']:g} stray from it")
    return 0
