"""Per-episode trust signals of a world-model evaluation: numbers that should grow with the
episode's error |model score - real score|, known without the real episode.

- ``novelty``: how unlike the model's training data the episode's inputs are
  (:mod:`iwsim.world_model.novelty`; only models exported with its statistics).
- ``implausibility``: 1 - the mean :meth:`~iwsim.envs.task.Task.plausibility` of the
  episode's frames (every :data:`PLAUSIBILITY_EVERY`-th step): a world model whose rigid
  block bends or smears shows a scene the task cannot have, and its score there measures
  that scene. ``implausibility_worst``: the same at the episode's least plausible frame.
- ``sample_spread``: the range of the episode's max score over several samples of the
  model (the same policy from the same first state, the model's noise drawn again): where
  the data pins the outcome down the samples agree.
- ``command_lead``: how far the policy's commands run ahead of where the model shows the
  robot (:meth:`~iwsim.envs.task.Task.command_lead`, in units of the task's half view), the
  episode's 90th percentile over its steps: a policy pressing its setpoints far beyond a
  blocked pusher drives the model where its training data rarely went.
- ``disagreement`` (:func:`iwsim.eval.policy.disagreement`): the same against a second
  model trained differently.

:func:`error_ranking` says how well each ranks episodes by their error (Spearman rho);
:class:`ErrorPredictor` combines them (a ridge regression of the error on the
standardised signals and the model's own score, fitted on paired episodes of other
policies); :func:`calibration` and :func:`calibration_figure` show the error of the
episodes a signal flags against the share it flags.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import spearmanr

PLAUSIBILITY_EVERY = 10  # steps between the frames whose plausibility an evaluation measures
# Sample k's noise seeds: the episode's seed + k * SAMPLE_OFFSET modulo 2**32 (torch seeds its
# generators with 32 bits): an odd constant near 2**32 / golden ratio, so no other episode's seed
# among a few million consecutive ones.
SAMPLE_OFFSET = 0x9E3779B1
# Above these an episode's score is flagged as least to be trusted: a mean T fit below the
# yardstick's "crisp" 0.9 (iwsim.yardstick.families.CRISP), a spread as large as the
# ensemble's DISAGREE_WARN.
# command_lead: 0.1 of the half view is 26 mm on the tabletop tasks, the most the play and
# expert data lead their pushers by (bench/probes/setpoint_gap.py).
WARN = {"implausibility": 0.1, "implausibility_worst": 0.25, "sample_spread": 0.2, "command_lead": 0.1}
SIGNALS = ("novelty", "implausibility", "implausibility_worst", "sample_spread", "command_lead", "disagreement")
LEAD_QUANTILE = 90  # the percentile of an episode's per-step command lead that is its signal


def episode_signals(plausibility: np.ndarray | None, sample_max_scores: list[np.ndarray] | None,
                    command_lead: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The signals an evaluation measures itself, per episode (E,): from the plausibility
    of its frames (E, K) (``rollout``'s, None when the task cannot tell), the max scores
    (E,) of each of two or more samples of the model (None: one sample) and each step's
    command lead (E, T) (``rollout``'s, None when the task cannot tell)."""
    out: dict[str, np.ndarray] = {}
    if command_lead is not None and command_lead.shape[-1]:
        out["command_lead"] = np.percentile(np.asarray(command_lead, np.float64), LEAD_QUANTILE, axis=-1)
    if plausibility is not None:
        p = np.asarray(plausibility, np.float64)
        out["implausibility"] = 1.0 - p.mean(1)
        out["implausibility_worst"] = 1.0 - p.min(1)
    if sample_max_scores is not None and len(sample_max_scores) >= 2:
        out["sample_spread"] = np.ptp(np.stack(sample_max_scores), 0)
    return out


def summary(signals: dict[str, np.ndarray]) -> dict[str, Any]:
    """For a results.json: each signal's per-episode values, their mean and the share of
    episodes above its :data:`WARN` level."""
    return {name: {"per_episode": np.round(v, 4).tolist(), "mean": float(v.mean()),
                   "above_warn": float((v > WARN[name]).mean()), "warn": WARN[name]}
            for name, v in signals.items()}


def spearman(signal: np.ndarray, error: np.ndarray) -> float | None:
    """Spearman rho of a signal against the errors; None where either is constant."""
    signal, error = np.asarray(signal, np.float64), np.asarray(error, np.float64)
    if len(signal) < 3 or np.ptp(signal) == 0 or np.ptp(error) == 0:
        return None
    return float(spearmanr(signal, error)[0])


def error_ranking(signals: dict[str, np.ndarray], error: np.ndarray) -> dict[str, float | None]:
    """Spearman rho of each signal against the episodes' errors (> 0: it ranks them)."""
    return {name: spearman(v, error) for name, v in signals.items()}


@dataclass
class ErrorPredictor:
    """A ridge regression of |model - real| on standardised features (the signals and the
    model's score), fitted on paired episodes of policies other than those it judges."""

    names: tuple[str, ...]
    mean: np.ndarray
    scale: np.ndarray
    coef: np.ndarray
    intercept: float

    @classmethod
    def fit(cls, features: dict[str, np.ndarray], error: np.ndarray, ridge: float = 1.0) -> ErrorPredictor:
        names = tuple(sorted(features))
        x = np.stack([np.asarray(features[n], np.float64) for n in names], 1)
        mean, scale = x.mean(0), x.std(0)
        scale = np.where(scale > 0, scale, 1.0)
        z = (x - mean) / scale
        y = np.asarray(error, np.float64)
        coef = np.linalg.solve(z.T @ z + ridge * np.eye(len(names)), z.T @ (y - y.mean()))
        return cls(names, mean, scale, coef, float(y.mean()))

    def predict(self, features: dict[str, np.ndarray]) -> np.ndarray:
        x = np.stack([np.asarray(features[n], np.float64) for n in self.names], 1)
        return self.intercept + ((x - self.mean) / self.scale) @ self.coef

    def weights(self) -> dict[str, float]:
        """Each feature's coefficient (in its standard deviations)."""
        return {n: round(float(c), 4) for n, c in zip(self.names, self.coef)}


SHARES = (0.1, 0.2, 0.3, 0.5, 0.7, 1.0)


def calibration(signal: np.ndarray, error: np.ndarray, shares: tuple[float, ...] = SHARES) -> list[dict[str, float]]:
    """For each share q: the mean error of the q most suspect episodes by ``signal`` (the
    highest values) and of the rest; a signal that ranks errors flags the large ones first."""
    order = np.argsort(-np.asarray(signal, np.float64), kind="stable")
    err = np.asarray(error, np.float64)[order]
    rows = []
    for q in shares:
        k = max(1, int(round(q * len(err))))
        rows.append({"share": q, "flagged_error": float(err[:k].mean()),
                     "rest_error": float(err[k:].mean()) if k < len(err) else float("nan")})
    return rows


def calibration_figure(path: Path, curves: dict[str, tuple[np.ndarray, np.ndarray]], title: str) -> None:
    """Mean error of the flagged episodes against the share flagged, one line per signal
    (``curves``: name -> (signal, error)), beside the best possible ranking (the errors'
    own) and none (the mean error)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shares = np.linspace(0.05, 1.0, 20)
    fig, ax = plt.subplots(figsize=(6, 4))
    error = None
    for name, (signal, err) in curves.items():
        rows = calibration(signal, err, tuple(shares))
        ax.plot(shares, [r["flagged_error"] for r in rows], marker="o", ms=3, label=name)
        error = err
    if error is not None:
        best = calibration(error, error, tuple(shares))
        ax.plot(shares, [r["flagged_error"] for r in best], "k--", lw=1, label="the errors themselves (best)")
        ax.axhline(float(np.mean(error)), color="grey", lw=1, label="no signal (mean error)")
    ax.set_xlabel("share of episodes flagged (most suspect first)")
    ax.set_ylabel("mean |model - MuJoCo| of the flagged")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
