"""How often a scene at rest stays at rest in a store's data: the measurement behind
``stage2.rest_threshold`` (issue 41).

For every step t whose executed setpoint equals the previous step's and whose latent
changed by less than a threshold (a cell's largest channel, standardised by the model's
latent scale), the change of the next latent. Latents come from a stage-2 latent cache of
the store (``iwsim train dynamics --latent-cache``, the same frames in order).

    python bench/rest_stats.py --data data/broad.zarr --latents runs/latents_broad.safetensors \
        --model checkpoints/pusht-64
"""

from __future__ import annotations

import argparse

import numpy as np
import torch
from safetensors.torch import load_file

from iwsim.core.checkpoint import load_json
from iwsim.core.errors import reporting_errors
from iwsim.data.store import EpisodeStore


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, help="episode store")
    p.add_argument("--latents", required=True, help="its stage-2 latent cache")
    p.add_argument("--model", default="checkpoints/pusht-64", help="world model whose latent scale to use")
    p.add_argument("--thresholds", default="0.02,0.05,0.1,0.2")
    args = p.parse_args()
    store = EpisodeStore.open(args.data, "r")
    ends = store.episode_ends.astype(np.int64)
    target = np.asarray(store.array("target")[:])
    z = load_file(args.latents)["latents"].float() / load_json(f"{args.model}/config.json")["latent_norm"]["scale"]
    if len(z) != len(target):
        raise SystemExit(f"error: {args.latents} holds {len(z)} latents but {args.data} {len(target)} frames.")
    change = np.zeros(len(z), np.float32)  # the largest change into frame t
    change[1:] = (z[1:] - z[:-1]).abs().flatten(1).amax(1).numpy()
    inside = np.ones(len(z), bool)  # t - 1 and t + 1 in t's episode
    inside[np.r_[0, ends[:-1]]] = False
    inside[ends - 1] = False
    t = np.nonzero(inside)[0]
    still = np.abs(target[t] - target[t - 1]).max(1) == 0
    print(f"{len(t)} steps; the setpoint holds still in {still.mean():.1%}")
    print("| threshold | steps at rest | next change: median | p99 | share > 0.05 |")
    print("|---|---|---|---|---|")
    for thr in (float(x) for x in args.thresholds.split(",")):
        rest = still & (change[t] < thr)
        nxt = change[t[rest] + 1]
        if not len(nxt):
            print(f"| {thr:g} | 0 | - | - | - |")
            continue
        print(f"| {thr:g} | {rest.mean():.2%} | {np.median(nxt):.3f} | {np.quantile(nxt, 0.99):.3f} | "
              f"{(nxt > 0.05).mean():.1%} |")


if __name__ == "__main__":
    torch.set_num_threads(1)
    raise SystemExit(reporting_errors("rest_stats.py", main))
