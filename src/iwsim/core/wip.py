"""A training run's latest resumable state, kept where a new machine finds it.

``runs/`` survives only while a machine is handed on. A run that must outlive the machine
saves its state under ``checkpoints/wip/NAME/`` (committed; the previous one replaced, not
accumulated) and a new machine restores it into a run directory, where rerunning the run's
command resumes it exactly as if it had never stopped (``tests/test_wip.py``):

    iwsim wip save --run runs/pt_dyn_x4 --out checkpoints/wip/pt_dyn_x4
    iwsim wip restore --wip checkpoints/wip/pt_dyn_x4 --out runs/pt_dyn_x4

The state is the run's ``config.json``, ``metrics.jsonl`` and ``log.txt``, and its newest
checkpoint (weights, EMA, optimiser state and the step; the data order is drawn from the
seed and the step, so no RNG state is needed): not the latent cache, which the run
rebuilds from the data, nor the data. ``wip.json`` names the step and the command.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

from iwsim.core.checkpoint import last_checkpoint, load_json, write_json_atomic
from iwsim.core.errors import InputError
from iwsim.core.lock import temp_sibling

RUN_FILES = ("config.json", "metrics.jsonl", "log.txt")
MARKER = "wip.json"


def save_wip(run: str | os.PathLike, out: str | os.PathLike, command: str | None = None) -> dict[str, Any]:
    """Write ``run``'s latest resumable state to ``out`` (replacing a previous state there,
    atomically: a reader sees the old state or the new one). Returns ``wip.json``."""
    run, out = Path(run), Path(out)
    newest = last_checkpoint(run / "checkpoints") if (run / "checkpoints").is_dir() else None
    if not (run / "config.json").is_file() or newest is None:
        raise InputError(f"{run} is not a training run with a checkpoint (config.json + checkpoints/last).")
    if out.exists() and not (out / MARKER).is_file():
        raise InputError(f"{out} exists and is not a saved run state ({MARKER}); choose another --out.")
    info = {"run": str(run), "step": int(load_json(newest / "training_state" / "state.json")["step"]),
            "checkpoint": newest.name, "saved_by": command}
    tmp = temp_sibling(out)
    try:
        tmp.mkdir(parents=True)
        for name in RUN_FILES:
            if (run / name).is_file():
                shutil.copy2(run / name, tmp / name)
        shutil.copytree(newest, tmp / newest.name)
        write_json_atomic(tmp / MARKER, info)
        old = temp_sibling(out) if out.exists() else None
        if old is not None:
            os.rename(out, old)
        os.rename(tmp, out)
        if old is not None:
            shutil.rmtree(old)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return info


def restore_wip(wip: str | os.PathLike, out: str | os.PathLike) -> dict[str, Any]:
    """Lay the state saved in ``wip`` out as the run directory ``out`` (which must not hold
    a run at a later step: a state is never restored over newer work). Returns ``wip.json``."""
    wip, out = Path(wip), Path(out)
    if not (wip / MARKER).is_file():
        raise InputError(f"{wip} is not a saved run state (it has no {MARKER}).")
    info = load_json(wip / MARKER)
    here = last_checkpoint(out / "checkpoints") if (out / "checkpoints").is_dir() else None
    if here is not None:
        step = int(load_json(here / "training_state" / "state.json")["step"])
        if step >= info["step"]:
            raise InputError(f"{out} already holds the run at step {step} (the saved state is at step "
                             f"{info['step']}); nothing to restore.")
    if out.exists() and any(out.iterdir()) and not (out / "config.json").is_file():
        raise InputError(f"{out} is a directory that holds something other than a run; choose another --out.")
    out.mkdir(parents=True, exist_ok=True)
    ckpts = out / "checkpoints"
    ckpts.mkdir(exist_ok=True)
    for name in RUN_FILES:
        if (wip / name).is_file():
            shutil.copy2(wip / name, out / name)
    target = ckpts / info["checkpoint"]
    if not target.exists():
        tmp = temp_sibling(target)
        shutil.copytree(wip / info["checkpoint"], tmp)
        os.rename(tmp, target)
    link = ckpts / ".last.tmp"
    link.unlink(missing_ok=True)
    link.symlink_to(info["checkpoint"])
    os.replace(link, ckpts / "last")
    return info
