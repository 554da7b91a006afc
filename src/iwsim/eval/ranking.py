"""Does one evaluator rank policies like another? Agreement statistics between the scores
of the same policies under a reference ("real", here MuJoCo) and a proxy ("sim", here
the world model): Pearson r, Spearman rho and MMRV, as in SIMPLER (Li et al. 2024,
"Evaluating Real-World Robot Manipulation Policies in Simulation", Sec. 4).

    agreement(real=[0.9, 0.5, 0.1], sim=[0.8, 0.6, 0.2])
    # -> {"pearson": 0.99..., "spearman": 1.0, "mmrv": 0.0, "undefined": {}}
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from scipy.stats import rankdata

from iwsim.core.errors import InputError

MIN_POLICIES_CORRELATION = 3  # with 2 points any two non-constant score lists correlate perfectly
MIN_POLICIES_MMRV = 2


def _scores(x: Sequence[float], y: Sequence[float], minimum: int, what: str) -> tuple[np.ndarray, np.ndarray]:
    """Two 1-D float64 arrays of the same length >= ``minimum``, all finite."""
    a, b = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if a.ndim != 1 or b.ndim != 1:
        raise InputError(f"{what} takes two 1-D lists of scores, got shapes {a.shape} and {b.shape}.")
    if len(a) != len(b):
        raise InputError(f"{what} needs one score per policy in both lists, got {len(a)} and {len(b)} scores.")
    if len(a) < minimum:
        raise InputError(f"{what} needs at least {minimum} policies, got {len(a)}.")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise InputError(f"{what} needs finite scores, got {a.tolist()} and {b.tolist()}.")
    return a, b


LABELS = ("first list", "second list")  # how an undefined statistic's message names its inputs


def _check_varies(what: str, a: np.ndarray, b: np.ndarray, labels: tuple[str, str]) -> None:
    for label, v in zip(labels, (a, b)):
        if np.all(v == v[0]):
            raise InputError(f"{what} is undefined when one list is constant ({label}: all {v[0]:g}).")


def pearson(x: Sequence[float], y: Sequence[float], labels: tuple[str, str] = LABELS) -> float:
    """Pearson's correlation coefficient of two score lists (N,), N >= 3.
    r = sum (x - mean x)(y - mean y) / sqrt(sum (x - mean x)^2 sum (y - mean y)^2)."""
    a, b = _scores(x, y, MIN_POLICIES_CORRELATION, "Pearson r")
    _check_varies("Pearson r", a, b, labels)
    da, db = a - a.mean(), b - b.mean()
    # Clipped: rounding can put |r| a hair above 1 for (anti-)proportional lists.
    return float(np.clip(np.sum(da * db) / np.sqrt(np.sum(da**2) * np.sum(db**2)), -1.0, 1.0))


def spearman(x: Sequence[float], y: Sequence[float], labels: tuple[str, str] = LABELS) -> float:
    """Spearman's rank correlation of two score lists (N,), N >= 3: Pearson's r of their
    ranks, tied scores sharing the average of the ranks they span."""
    a, b = _scores(x, y, MIN_POLICIES_CORRELATION, "Spearman rho")
    _check_varies("Spearman rho", a, b, labels)
    return pearson(rankdata(a, method="average"), rankdata(b, method="average"))


def rank_violations(real: Sequence[float], sim: Sequence[float]) -> np.ndarray:
    """(N, N) RankViolation(i, j) = |R_i - R_j| * 1[(S_i < S_j) != (R_i < R_j)] (SIMPLER,
    Eq. 1): how far apart in real score two policies are that the proxy orders differently.
    Two policies the proxy ties but the reference does not count once, at the one with the
    lower real score; a pair tied in the real scores costs nothing."""
    r, s = _scores(real, sim, MIN_POLICIES_MMRV, "MMRV")
    flipped = (s[:, None] < s[None, :]) != (r[:, None] < r[None, :])
    return np.abs(r[:, None] - r[None, :]) * flipped


def mmrv(real: Sequence[float], sim: Sequence[float]) -> float:
    """Mean maximum rank violation (SIMPLER, Eq. 2): MMRV = (1/N) sum_i max_j
    RankViolation(i, j), in the units of the real scores; 0 when the proxy orders every
    pair of policies as the reference does. (SIMPLER's public code compares with ``>``
    instead of the paper's ``<``; the two differ only in where a tie of the proxy is
    counted, so a value can differ when the proxy ties policies.)"""
    return float(rank_violations(real, sim).max(axis=1).mean())


def agreement(real: Sequence[float], sim: Sequence[float],
              labels: tuple[str, str] = ("reference scores", "proxy scores")) -> dict[str, Any]:
    """Pearson r, Spearman rho and MMRV of ``sim`` against ``real`` (each (N,)); a
    statistic that is undefined for these scores (e.g. every policy fails in one
    simulator, so its success rates are constant) is None, with the reason in
    ``undefined[name]`` (naming the inputs by ``labels``). Lists of different lengths or
    non-finite scores raise InputError."""
    out: dict[str, Any] = {"pearson": None, "spearman": None, "mmrv": None, "undefined": {}}
    _scores(real, sim, 0, "Comparing scores")  # malformed input is an error, not an undefined statistic
    stats: tuple[tuple[str, Callable[..., float]], ...] = (("pearson", pearson), ("spearman", spearman), ("mmrv", mmrv))
    for name, fn in stats:
        try:
            out[name] = fn(real, sim, labels) if fn is not mmrv else fn(real, sim)
        except InputError as e:
            out["undefined"][name] = str(e)
    return out
