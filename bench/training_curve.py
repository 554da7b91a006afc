"""The yardstick's measures against stage-2 training steps, one line per arm: the curve
that tells what more compute buys from what a design change buys (issue 64).

Reads a CSV of recorded yardstick rows (``bench/results/latent_curve/rows.csv``: one row
per arm, step count and machine, each naming the record it was copied from) and draws
three panels: a T kept over 192 held-out play steps, a T kept over the 2000-step run and
the pixel expert's takes kept of 32. Rows measured on different machines are drawn with
different markers: the same weights score a few points apart across CPUs, and the
2000-step run does not compare across them at all (``bench/results/ablations.md``).

    python bench/training_curve.py bench/results/latent_curve/rows.csv --out bench/results/latent_curve/curve.png
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

from iwsim.core.errors import InputError, reporting_errors
from iwsim.eval.figures import pyplot, save_figure

PANELS = {"t_kept_192": "T kept, 192 held-out play steps (%)", "t_kept_2000": "T kept, 2000-step run (%)",
          "expert_takes": "pixel expert's takes kept (of 32)"}
REQUIRED = ("arm", "steps", "machine", *PANELS)
MARKERS = ("o", "s", "^", "D")


def read_rows(path: Path) -> list[dict[str, str]]:
    """The CSV's rows; a missing column, a step count that is not a whole number or a
    measure that is neither a number nor empty is an error naming the row."""
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in REQUIRED if c not in (reader.fieldnames or [])]
        if missing:
            raise InputError(f"{path} lacks the column(s) {', '.join(missing)}; "
                             f"expected at least {', '.join(REQUIRED)}.")
        rows = list(reader)
    for i, row in enumerate(rows, start=2):
        if not row["steps"].isdigit():
            raise InputError(f"{path} line {i}: steps {row['steps']!r} is not a whole number.")
        for key in PANELS:
            try:
                float(row[key] or 0)
            except ValueError:
                raise InputError(f"{path} line {i}: {key} {row[key]!r} is neither a number nor empty.") from None
    return rows


def plot(rows: list[dict[str, str]], out: Path) -> None:
    """Three panels (``PANELS``) of each arm's measures against its steps; a line joins an
    arm's rows from one machine, the marker says which machine."""
    plt = pyplot()
    arms = list(dict.fromkeys(r["arm"] for r in rows))
    machines = list(dict.fromkeys(r["machine"] for r in rows))
    colours = {a: f"C{i}" for i, a in enumerate(arms)}
    fig, axes = plt.subplots(1, len(PANELS), figsize=(5.2 * len(PANELS), 4.6))
    for ax, (key, label) in zip(axes, PANELS.items(), strict=True):
        for arm in arms:
            for m, machine in enumerate(machines):
                pts = sorted((int(r["steps"]), float(r[key])) for r in rows
                             if r["arm"] == arm and r["machine"] == machine and r[key] != "")
                if pts:
                    xs, ys = zip(*pts, strict=True)
                    ax.plot(xs, ys, marker=MARKERS[m % len(MARKERS)], color=colours[arm], lw=1.2, ms=5)
        ax.set_xlabel("stage-2 training steps")
        ax.set_title(label, fontsize=10)
        ax.grid(alpha=0.3)
    for arm in arms:
        axes[0].plot([], [], color=colours[arm], lw=1.2, label=arm)
    for m, machine in enumerate(machines):
        axes[0].plot([], [], ls="", marker=MARKERS[m % len(MARKERS)], color="0.4", label=machine)
    fig.legend(loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.14, 1, 1))
    save_figure(fig, out)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("rows", type=Path, help="CSV of recorded yardstick rows")
    p.add_argument("--out", type=Path, required=True, help="the figure (.png)")
    args = p.parse_args()
    plot(read_rows(args.rows), args.out)
    print(args.out)


if __name__ == "__main__":
    raise SystemExit(reporting_errors("training_curve.py", main))
