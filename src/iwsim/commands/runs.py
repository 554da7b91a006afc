"""What is made of a training run: ``iwsim export-model`` (a standalone world-model checkpoint)
and ``iwsim wip`` (its resumable state, saved where a new machine finds it)."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
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


def _export_model(args: argparse.Namespace) -> int:
    from iwsim.core.checkpoint import resolve_checkpoint
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
    from iwsim.core.wip import save_wip
    from iwsim.eval.records import command_line

    info = save_wip(args.run, args.out, command=command_line("iwsim", args.argv))
    print(f"{args.out}: {args.run} at step {info['step']} (restore it with iwsim wip restore --wip {args.out} "
          f"--out {args.run}, then rerun the run's command)")
    return 0


def _wip_restore(args: argparse.Namespace) -> int:
    from iwsim.core.wip import restore_wip

    info = restore_wip(args.wip, args.out)
    print(f"{args.out}: restored at step {info['step']}; rerun the run's command to resume it")
    return 0
