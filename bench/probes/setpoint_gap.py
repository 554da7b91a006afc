"""How hard does a motion press? The distance from each executed setpoint to where the
pusher is one step later (issue 41): near zero in free space (MuJoCo's pushers track their
setpoints to ~1.3 mm), centimetres when a pusher presses against the block and stays
there. For episode stores (their ``target`` and ``state``) and for learned policies
driven in MuJoCo.

    MUJOCO_GL=egl python bench/probes/setpoint_gap.py --stores data/contact.zarr data/play_broad.zarr \
        --zoo RUN/checkpoints/00001500 --episodes 6
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from iwsim.core.errors import reporting_errors
from iwsim.data.store import EpisodeStore
from iwsim.eval.policy import rollout
from iwsim.policies.factory import load_policy
from iwsim.yardstick import families

QUANTILES = (0.5, 0.9, 0.99)


def gaps(setpoints: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Per pusher, the distance (m) between setpoints (..., 4) and the pushers (..., 4) one step later."""
    return np.linalg.norm((setpoints - after).reshape(-1, 2, 2), axis=-1).ravel()


def store_gaps(path: str) -> np.ndarray:
    store = EpisodeStore.open(path)
    target, state = np.asarray(store.array("target")), np.asarray(store.array("state"))
    ends = np.asarray(store.episode_ends)
    inside = np.ones(len(target) - 1, bool)  # step t's setpoint and frame t + 1 of the same episode
    inside[ends[:-1] - 1] = False
    return gaps(target[:-1][inside], state[1:][inside])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--stores", nargs="*", default=[])
    p.add_argument("--zoo", nargs="*", default=[], help="policy checkpoints or runs")
    p.add_argument("--episodes", type=int, default=6)
    p.add_argument("--steps", type=int, default=300)
    args = p.parse_args()
    torch.set_num_threads(1)
    print("| whose motion | setpoint to pusher one step later, p50 / p90 / p99 mm |\n|---|---|")
    rows = [(path, lambda path=path: store_gaps(path)) for path in args.stores]
    seeds = [families.SEED + i for i in range(args.episodes)]

    def policy_gaps(checkpoint: str) -> np.ndarray:
        torch.manual_seed(0)  # the policy's sampling noise, as the studies seed it
        r = rollout(load_policy(checkpoint), "pusht", seeds, args.steps, progress=False)
        return gaps(r["target"], r["agent_pos"][:, 1:])

    rows += [(f"{c} ({args.episodes} episodes)", lambda c=c: policy_gaps(c)) for c in families.zoo_sources(args.zoo)]
    for name, measure in rows:
        q = np.quantile(measure(), QUANTILES) * 1000
        print(f"| {name} | {' / '.join(f'{v:.0f}' for v in q)} |", flush=True)


if __name__ == "__main__":
    raise SystemExit(reporting_errors("setpoint_gap.py", main))
