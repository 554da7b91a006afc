"""Times N training steps of the `act` preset on the expert's 100 takes, fp32 or bf16
autocast, one thread, into a fresh OUT (issue 44's bf16 check, recorded with the preset's trunk of
then: four convs, the first at full resolution; pair two calls with farm-bench):

    farm-bench -n 4 --vs "python bench/probes/act_step_time.py fp32 40 /tmp/a" -- \
        python bench/probes/act_step_time.py bf16 40 /tmp/b
"""
import dataclasses
import shutil
import sys

import torch

from iwsim.policies import PRESETS
from iwsim.policies.data import parse_mixture
from iwsim.policies.train import train_policy


def main() -> None:
    torch.set_num_threads(1)
    bf16, steps, out = sys.argv[1] == "bf16", int(sys.argv[2]), sys.argv[3]
    shutil.rmtree(out, ignore_errors=True)
    base = PRESETS["act"]
    train = dataclasses.replace(base.train, steps=steps, cpu_bf16=bf16, eval_every=10**9, checkpoint_every=10**9)
    train_policy(dataclasses.replace(base, train=train), parse_mixture("runs/experiments/demos/sim_expert.zarr:100"),
                 out, device=torch.device("cpu"), progress=False)


if __name__ == "__main__":
    main()
