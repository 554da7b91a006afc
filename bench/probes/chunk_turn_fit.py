"""Does ACT predict the turn where its demonstrations turn? (issue 44)

Open loop on a store's takes: at chosen frames of every take (default each take's first,
which in a takeover store is the state where the expert took over from the policy), the
policy's predicted chunk against the demonstrated one:
- a0: the distance of the first predicted action from the demonstrated one (mm, mean of
  the two pushers);
- turn: how far the chunk turns the line between the two pushers over its k actions
  (degrees), predicted against demonstrated, and how often its direction agrees where
  the demonstration turns by more than 5 degrees;
- travel: how far the chunk moves the pushers' midpoint (mm), predicted against demonstrated.
A policy that fits the turn it was shown gives a predicted turn near the demonstrated one.

    MUJOCO_GL=egl OMP_NUM_THREADS=1 python bench/probes/chunk_turn_fit.py \
        --checkpoint runs/pol/act-s2-to/checkpoints/00010000 --data runs/pol/demos/takeover_act.zarr:100
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from iwsim.core.errors import InputError, reporting_errors
from iwsim.policies.data import PolicyData, parse_mixture
from iwsim.policies.factory import load_policy


def pair_angle(a: np.ndarray) -> np.ndarray:
    """[lx, ly, rx, ry] (..., 4) -> the angle of the line from left to right pusher (rad)."""
    return np.arctan2(a[..., 3] - a[..., 1], a[..., 2] - a[..., 0])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--data", required=True, help="STORE[:N][,STORE:N...]")
    p.add_argument("--offsets", default="0", help="frames after each take's first to probe, e.g. 0,10,20")
    args = p.parse_args()
    torch.set_num_threads(1)
    policy = load_policy(args.checkpoint)
    if not hasattr(policy, "predict_chunk"):
        raise InputError(f"{args.checkpoint} is a {policy.kind} policy; the probe reads ACT's whole chunks.")
    k = policy.cfg.horizon
    data = PolicyData(parse_mixture(args.data), policy.cfg.obs_horizon, k)
    rows = []
    for off in (int(s) for s in args.offsets.split(",")):
        t = torch.minimum(data.starts + off, data.ends - k)  # windows that stay inside their take
        keep = t >= data.starts
        obs, act, _ = data.windows(t[keep])
        chunk = policy.predict_chunk({"image": data.img[obs].numpy(), "agent_pos": data.state[obs].numpy()})
        pred = chunk.cpu().numpy()
        true = data.action[act].numpy()
        a0 = (np.linalg.norm((pred[:, 0] - true[:, 0]).reshape(-1, 2, 2), axis=-1).mean(-1) * 1000)
        turn_p = np.degrees(np.angle(np.exp(1j * (pair_angle(pred[:, -1]) - pair_angle(pred[:, 0])))))
        turn_t = np.degrees(np.angle(np.exp(1j * (pair_angle(true[:, -1]) - pair_angle(true[:, 0])))))
        mid = lambda a: (a[..., :2] + a[..., 2:]) / 2  # noqa: E731
        travel_p = np.linalg.norm(mid(pred[:, -1]) - mid(pred[:, 0]), axis=-1) * 1000
        travel_t = np.linalg.norm(mid(true[:, -1]) - mid(true[:, 0]), axis=-1) * 1000
        turning = np.abs(turn_t) > 5
        agree = np.mean(np.sign(turn_p[turning]) == np.sign(turn_t[turning])) if turning.any() else float("nan")
        rows.append((off, int(keep.sum()), np.median(a0), np.mean(np.abs(turn_t)), np.mean(np.abs(turn_p)),
                     int(turning.sum()), agree, np.mean(np.abs(turn_p[turning])) if turning.any() else float("nan"),
                     np.mean(travel_t), np.mean(travel_p)))
    print(f"{args.checkpoint} on {args.data}, chunks of {k}")
    print("| frame | windows | a0 error, median mm | mean abs turn, shown / predicted (deg) | windows turning > 5 deg "
          "| direction agrees | their predicted abs turn (deg) | travel, shown / predicted (mm) |")
    print("|---|---|---|---|---|---|---|---|")
    for off, n, a0m, tt, tp, nt, ag, tpt, dt, dp in rows:
        print(f"| +{off} | {n} | {a0m:.1f} | {tt:.1f} / {tp:.1f} | {nt} | {ag:.0%} | {tpt:.1f} | {dt:.1f} / {dp:.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(reporting_errors("chunk_turn_fit.py", main))
