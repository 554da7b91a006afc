"""Run by test_training.py under torchrun: train the tiny autoencoder on 2 CPU ranks and
save each rank's final weights to OUT/rank<r>.safetensors."""

import dataclasses
import sys
from pathlib import Path

import torch.distributed as dist
from safetensors.torch import save_file

from iwsim.core import trainer
from iwsim.core.config import to_dict
from iwsim.world_model.presets import AE_PRESETS
from iwsim.world_model.train_codec import AETask


def main(data: str, run_dir: str, out: str, steps: int) -> None:
    cfg = AE_PRESETS["tiny"]
    cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, steps=steps))
    task = AETask(cfg, data)
    trainer.train(task, cfg.train, Path(run_dir), {"model": to_dict(cfg)}, progress=False)
    save_file({k: v.contiguous() for k, v in task.module.state_dict().items()},
              Path(out) / f"rank{dist.get_rank()}.safetensors")
    dist.destroy_process_group()


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4]))
