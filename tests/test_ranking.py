"""Agreement statistics between two evaluators (iwsim.eval.ranking): hand-computed
values, scipy's, and bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from iwsim.core.errors import InputError
from iwsim.eval.ranking import agreement, mmrv, pearson, rank_violations, spearman


def test_pearson_by_hand():
    # x = [1, 2, 3], y = [1, 3, 2]: deviations dx = [-1, 0, 1], dy = [-1, 1, 0];
    # sum dx*dy = 1, sum dx^2 = sum dy^2 = 2, so r = 1 / sqrt(2 * 2) = 0.5.
    assert pearson([1, 2, 3], [1, 3, 2]) == pytest.approx(0.5)
    assert pearson([1, 2, 3], [2, 4, 6]) == pytest.approx(1.0)
    assert pearson([1, 2, 3], [3, 2, 1]) == pytest.approx(-1.0)


def test_spearman_by_hand_with_ties():
    # x = [1, 2, 2, 3] ranks to [1, 2.5, 2.5, 4] (the tie shares ranks 2 and 3), y to [1, 2, 3, 4].
    # Around the mean rank 2.5: dx = [-1.5, 0, 0, 1.5], dy = [-1.5, -0.5, 0.5, 1.5];
    # sum dx*dy = 4.5, sum dx^2 = 4.5, sum dy^2 = 5, so rho = 4.5 / sqrt(22.5) = sqrt(0.9).
    assert spearman([1, 2, 2, 3], [1, 2, 3, 4]) == pytest.approx(math.sqrt(0.9))
    # Monotone but not linear: rho = 1 where r < 1.
    assert spearman([1, 2, 3, 4], [1, 10, 100, 1000]) == pytest.approx(1.0)
    assert pearson([1, 2, 3, 4], [1, 10, 100, 1000]) < 0.9


def test_mmrv_by_hand():
    # Real order 0 > 1 > 2 > 3; the proxy swaps policies 1 and 2 (0.2 < 0.5) and keeps the rest.
    # The only flipped pair is (1, 2), |R_1 - R_2| = 0.3, so the row maxima are [0, 0.3, 0.3, 0]
    # and MMRV = 0.6 / 4 = 0.15.
    real, sim = [0.9, 0.6, 0.3, 0.1], [0.8, 0.2, 0.5, 0.0]
    assert rank_violations(real, sim).max(axis=1) == pytest.approx([0, 0.3, 0.3, 0])
    assert mmrv(real, sim) == pytest.approx(0.15)
    # The same order: 0. Reversed order: rows max |R_i - R_j| over all j:
    # [|0.1 - 0.9|, |0.5 - 0.1|, |0.9 - 0.1|] = [0.8, 0.4, 0.8] -> 2.0 / 3.
    assert mmrv([0.1, 0.5, 0.9], [0.2, 0.3, 0.4]) == 0.0
    assert mmrv([0.1, 0.5, 0.9], [0.9, 0.5, 0.1]) == pytest.approx(2.0 / 3)


def test_mmrv_ties():
    # The proxy ties everything (e.g. every policy fails inside it) while the real scores are
    # [0.5, 0.2, 0.0]: each tied pair counts once, at its lower-scoring policy
    # (1[(S_i < S_j) != (R_i < R_j)] is 1 only for the one with R_i < R_j).
    # Row maxima: policy 0 -> 0; policy 1 -> |0.2 - 0.5| = 0.3; policy 2 -> max(0.5, 0.2) = 0.5.
    # MMRV = (0 + 0.3 + 0.5) / 3 = 0.8 / 3.
    assert mmrv([0.5, 0.2, 0.0], [0.0, 0.0, 0.0]) == pytest.approx(0.8 / 3)
    # Ties in the real scores cost nothing, however the proxy orders them.
    assert mmrv([0.5, 0.5, 0.0], [0.1, 0.9, 0.0]) == 0.0


def test_against_scipy_on_random_scores():
    rng = np.random.default_rng(0)
    for n in (3, 5, 12, 40):
        x = rng.random(n)
        y = 0.5 * x + rng.random(n)
        assert pearson(x, y) == pytest.approx(stats.pearsonr(x, y)[0], abs=1e-12)
        assert spearman(x, y) == pytest.approx(stats.spearmanr(x, y)[0], abs=1e-12)
        # success rates of 20 episodes tie often
        xs, ys = rng.integers(0, 21, n) / 20, rng.integers(0, 21, n) / 20
        if len(set(xs)) > 1 and len(set(ys)) > 1:
            assert spearman(xs, ys) == pytest.approx(stats.spearmanr(xs, ys)[0], abs=1e-12)


def test_mmrv_matches_the_definition_written_out():
    rng = np.random.default_rng(1)
    real, sim = rng.integers(0, 6, 9) / 5, rng.integers(0, 6, 9) / 5  # with ties
    n = len(real)
    expected = sum(max(abs(real[i] - real[j]) * ((sim[i] < sim[j]) != (real[i] < real[j])) for j in range(n))
                   for i in range(n)) / n
    assert mmrv(real, sim) == pytest.approx(expected)


@pytest.mark.parametrize(("fn", "args", "match"), [
    (pearson, ([1, 2], [1, 2]), "at least 3 policies"),
    (spearman, ([1, 2], [2, 1]), "at least 3 policies"),
    (mmrv, ([1], [1]), "at least 2 policies"),
    (pearson, ([1, 2, 3], [1, 2]), "3 and 2 scores"),
    (mmrv, ([1, 2, 3], [1, 2]), "3 and 2 scores"),
    (pearson, ([1, 2, float("nan")], [1, 2, 3]), "finite"),
    (mmrv, ([1, 2, 3], [1, float("inf"), 3]), "finite"),
    (pearson, ([1, 1, 1], [1, 2, 3]), "undefined when one list is constant"),
    (spearman, ([1, 2, 3], [0.5, 0.5, 0.5]), "undefined when one list is constant"),
    (pearson, ([[1, 2, 3]], [[1, 2, 3]]), "1-D"),
])
def test_bad_input_is_one_clear_line(fn, args, match):
    with pytest.raises(InputError, match=match) as e:
        fn(*args)
    assert "\n" not in str(e.value)


def test_agreement_marks_undefined_statistics():
    out = agreement([0.5, 0.2, 0.0], [0.0, 0.0, 0.0])
    assert out["pearson"] is None and out["spearman"] is None
    assert "constant" in out["undefined"]["pearson"]
    assert out["mmrv"] == pytest.approx(0.8 / 3)
    good = agreement([0.9, 0.6, 0.3, 0.1], [0.8, 0.2, 0.5, 0.0])
    assert good["undefined"] == {} and good["mmrv"] == pytest.approx(0.15)
    with pytest.raises(InputError, match="3 and 2"):
        agreement([1, 2, 3], [1, 2])
