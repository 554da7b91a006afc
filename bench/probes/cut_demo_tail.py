"""A demonstration store with every take cut at its first success frame (pixel IoU >= the
store's accept_iou): the steps the expert spends holding the block on the goal after it
are dropped. The same takes as recording with ``DemoRecipe(tail=1)``, without recording.

    python bench/probes/cut_demo_tail.py runs/experiments/demos/sim_expert.zarr runs/pol/demos/notail.zarr
"""

import argparse

import numpy as np

from iwsim.core.errors import reporting_errors
from iwsim.data.store import EpisodeStore


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("src")
    p.add_argument("out")
    args = p.parse_args()
    src = EpisodeStore.open(args.src, "r")
    accept = float(src.attrs["accept_iou"])
    attrs = {k: v for k, v in src.attrs.items() if k not in ("store_version", "keys", "seeds")}
    attrs.update(tail_steps=1, derived_from=f"{args.src}, each take cut at its first frame of pixel IoU >= {accept}")
    out = EpisodeStore.create(args.out, attrs)
    for i, seed in enumerate(src.seeds):
        ep = src.episode(i)
        first = int(np.argmax(ep["iou"] >= accept))
        if ep["iou"][first] < accept:
            raise SystemExit(f"take {i} of {args.src} never reaches IoU {accept}: not a store of kept takes.")
        out.append({k: v[:first + 1] for k, v in ep.items()}, seed=seed)
    print(f"{args.out}: {out.n_episodes} takes, {out.n_frames} frames (from {src.n_frames})")
    out.close()


if __name__ == "__main__":
    raise SystemExit(reporting_errors("cut_demo_tail.py", main))
