"""Success-rate statistics for policy evaluation: a Beta posterior under a uniform prior
and the Clopper-Pearson (exact binomial) interval."""

from __future__ import annotations

from scipy import stats

from iwsim.core.errors import InputError


def beta_posterior(successes: int, trials: int, level: float = 0.95) -> dict[str, float]:
    """Posterior Beta(1 + k, 1 + n - k) of a success rate after k successes in n trials
    (uniform prior): its mean and central ``level`` credible interval."""
    _check(successes, trials)
    a, b = 1 + successes, 1 + trials - successes
    lo, hi = stats.beta.ppf([(1 - level) / 2, (1 + level) / 2], a, b)
    return {"mean": a / (a + b), "low": float(lo), "high": float(hi)}


def clopper_pearson(successes: int, trials: int, level: float = 0.95) -> tuple[float, float]:
    """The exact binomial ``level`` confidence interval (Clopper & Pearson 1934)."""
    _check(successes, trials)
    alpha = 1 - level
    lo = 0.0 if successes == 0 else float(stats.beta.ppf(alpha / 2, successes, trials - successes + 1))
    hi = 1.0 if successes == trials else float(stats.beta.ppf(1 - alpha / 2, successes + 1, trials - successes))
    return lo, hi


def _check(successes: int, trials: int) -> None:
    if trials < 1 or not 0 <= successes <= trials:
        raise InputError(f"need 0 <= successes <= trials and trials >= 1, got {successes} of {trials}.")
