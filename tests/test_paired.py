"""The paired (prediction-powered) estimate of a policy's real score (issue 66): its closed
forms, its coverage on synthetic data, and its refusals."""

import json

import numpy as np
import pytest
from scipy import stats

from iwsim.core.errors import InputError
from iwsim.eval.paired import distrust, paired_estimate, paired_rate, power_tuned_lambda


def test_a_model_without_error_gives_its_own_mean_and_a_constant_bias_is_removed_exactly():
    rng = np.random.default_rng(0)
    f = rng.uniform(0.2, 0.9, 40)
    idx = [3, 7, 11, 20, 33]
    same = paired_estimate(f, f[idx], idx)
    assert same["lam"] == 1.0 and same["estimate"] == pytest.approx(f.mean(), abs=1e-12)
    shifted = paired_estimate(f, f[idx] - 0.25, idx)
    assert shifted["lam"] == 1.0 and shifted["estimate"] == pytest.approx(f.mean() - 0.25, abs=1e-12)
    assert shifted["bias_paired"] == pytest.approx(0.25) and shifted["std_error"] > 0
    # a model off by a constant adds no variance of its own: the interval is the model's spread only
    lo, hi = shifted["interval"]
    assert lo < f.mean() - 0.25 < hi


def test_the_closed_form_at_a_fixed_weight():
    f = np.array([0.5, 0.7, 0.2, 0.9, 0.4, 0.6])
    y = np.array([0.1, 0.6, 0.3])
    idx = np.array([1, 2, 4])
    out = paired_estimate(f, y, idx, lam=0.5)
    assert out["estimate"] == pytest.approx(y.mean() + 0.5 * (f.mean() - f[idx].mean()))
    w = 0.5 * (1 - 3 / 6)
    rest = np.delete(f, idx)
    a, b = np.var(y - w * f[idx], ddof=1) / 3, w ** 2 * np.var(rest, ddof=1) / 3
    assert out["std_error"] == pytest.approx(np.sqrt(a + b)) and out["df"] == 2  # the paired term's n - 1
    half = stats.t.ppf(0.975, 2) * np.sqrt(a + b)
    assert out["interval"] == pytest.approx([out["estimate"] - half, out["estimate"] + half])
    # lam 0 ignores the model: the paired real mean with its own t interval
    alone = paired_estimate(f, y, idx, lam=0.0)
    assert alone["estimate"] == pytest.approx(y.mean()) and alone["df"] == pytest.approx(2)


def test_power_tuning_is_the_regression_slope_clipped():
    f = np.array([0.1, 0.2, 0.3, 0.4])
    assert power_tuned_lambda(0.5 * f, f) == pytest.approx(0.5)
    assert power_tuned_lambda(-f, f) == 0.0 and power_tuned_lambda(3 * f, f) == 1.0
    assert power_tuned_lambda(np.array([0.3, 0.1, 0.5, 0.2]), np.full(4, 0.4)) == 1.0  # nothing to fit
    # fitted from 5 pairs on (one degree of freedom less), classic PPI below
    rng = np.random.default_rng(1)
    model = rng.uniform(0, 1, 30)
    few, many = paired_estimate(model, 0.5 * model[:4], range(4)), paired_estimate(model, 0.5 * model[:6], range(6))
    assert (few["lam"], few["df"]) == (1.0, 3) and (many["lam"], many["df"]) == (pytest.approx(0.5), 4)


@pytest.mark.parametrize("n", [2, 5, 10])
def test_the_interval_covers_the_real_mean_and_beats_real_episodes_alone(n):
    """Synthetic policies: the model over-credits by a bias that varies per state; over
    2000 seeded repetitions the 95% interval covers the true mean >= 93% of the time, and
    with a model that tracks the real score it is narrower than n real episodes' own t
    interval."""
    rng = np.random.default_rng(n)
    covered, widths, alone = 0, [], []
    reps, big_n, truth = 2000, 50, 0.55
    for _ in range(reps):
        real_all = np.clip(truth + rng.normal(0, 0.2, big_n), -1, 2)
        model = real_all + 0.3 + rng.normal(0, 0.05, big_n)  # biased, but it moves with the real score
        idx = rng.choice(big_n, n, replace=False)
        out = paired_estimate(model, real_all[idx], idx)
        lo, hi = out["interval"]
        covered += lo <= truth <= hi
        widths.append(hi - lo)
        y = real_all[idx]
        alone.append(2 * stats.t.ppf(0.975, n - 1) * y.std(ddof=1) / np.sqrt(n))
    assert covered / reps >= 0.95, covered / reps
    assert np.median(widths) < 0.75 * np.median(alone)


def test_a_success_rate_stays_in_its_range_and_bad_input_is_refused():
    model = [True] * 9 + [False]
    out = paired_rate(model, [True, True], [0, 1])
    assert 0.0 <= out["interval"][0] <= out["estimate"] <= out["interval"][1] <= 1.0
    # the paired states the model scores far below the real ones, the rest high: the
    # unbiased estimate (1 + 0.4) lies above the range; it and its interval are clipped into it
    above = paired_estimate([0.5, 0.5] + [1.0] * 8, [1.0, 1.0], [0, 1], bounds=(0.0, 1.0))
    assert above["estimate_unclipped"] == pytest.approx(1.4)
    assert above["estimate"] == above["interval"][1] == 1.0 and 0.0 <= above["interval"][0] <= 1.0
    for args, says in ((([0.5, 0.6], [0.5], [0]), "at least 2 paired episodes"),
                       (([0.5, 0.6], [0.5, 0.4], [0, 0]), "distinct states"),
                       (([0.5, 0.6], [0.5, 0.4], [0, 2]), "distinct states"),
                       (([0.5, np.nan], [0.5, 0.4], [0, 1]), "finite")):
        with pytest.raises(InputError, match=says):
            paired_estimate(*args)


def test_eval_policy_paired_with_real_episodes_and_its_refusals(tmp_path, capsys):
    """``iwsim eval policy --env world-model --paired RESULTS`` adds the estimate; results of
    another policy, task, steps or execution, or of seeds outside the model's, are refused."""
    import json
    import shutil
    from pathlib import Path

    from iwsim.cli import main

    root = Path(__file__).resolve().parents[1]
    dp, act = root / "checkpoints" / "dp-pusht-64", root / "checkpoints" / "act-pusht-64"
    base = ["eval", "policy", "--steps", "8", "--videos", "0", "--no-progress"]
    assert main([*base, "--checkpoint", str(dp), "--episodes", "3", "--seed", "100001",
                 "--out", str(tmp_path / "real")]) == 0
    real = tmp_path / "real" / "results.json"
    model = [*base, "--env", "world-model", "--episodes", "6", "--seed", "100000"]
    assert main([*model, "--checkpoint", str(dp), "--paired", str(real), "--out", str(tmp_path / "wm")]) == 0
    printed = capsys.readouterr().out
    assert "paired with 3 real episodes" in printed and "worth" in printed
    got = json.loads((tmp_path / "wm" / "results.json").read_text())
    est = got["paired"]["mean_max_iou"]
    assert got["paired"]["seeds"] == [100001, 100002, 100003] and est["n_paired"] == 3 and est["n_model"] == 6
    lo, hi = est["interval"]
    assert lo <= est["estimate"] <= hi and 0 <= got["paired"]["success_rate"]["interval"][0]
    # a copy of the same weights at another path pairs too: the policy is known by its hash
    copy = shutil.copytree(dp, tmp_path / "dp-copy")
    assert main([*model, "--checkpoint", str(copy), "--paired", str(real), "--out", str(tmp_path / "wm2")]) == 0
    capsys.readouterr()
    wrong = {"act": ([*model, "--checkpoint", str(act)], "evaluated another policy"),
             "steps": ([*model[:3], "9", *model[4:], "--checkpoint", str(dp)], "ran 8 steps per episode"),
             "seeds": ([*model[:-1], "100002", "--checkpoint", str(dp)], "outside this evaluation's"),
             "execution": ([*model, "--checkpoint", str(dp), "--action-steps", "2"], "evaluated another policy"),
             "model": ([*model, "--checkpoint", str(dp)], "is an evaluation in 'world-model'")}
    for name, (argv, says) in wrong.items():
        paired = tmp_path / "wm" / "results.json" if name == "model" else real
        assert main([*argv, "--paired", str(paired), "--out", str(tmp_path / name)]) == 1, name
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and says in err[0], (name, err)
        assert not (tmp_path / name).exists()
    assert main([*base, "--checkpoint", str(dp), "--episodes", "1", "--paired", str(real),
                 "--out", str(tmp_path / "mujoco")]) == 1
    assert "--paired applies to --env world-model" in capsys.readouterr().err


def test_distrusted_states_keep_the_models_level_not_its_variation():
    f = np.array([0.2, 0.4, 0.9, 0.5, 0.7])
    u = np.array([0.0, 0.3, 0.05, 0.5, 0.1])
    np.testing.assert_allclose(distrust(f, u, 0.2), [0.2, 0.45, 0.9, 0.45, 0.7])  # the warned two: their mean
    np.testing.assert_array_equal(distrust(f, u, 1.0), f)  # none warned: the model as it is
    flat = distrust(f, u, -1.0)  # all warned: the model says nothing per state, the pairs alone decide
    y = np.array([0.1, 0.3])
    out = paired_estimate(flat, y, [0, 3])
    assert out["estimate"] == pytest.approx(y.mean())
    with pytest.raises(InputError, match="one per model episode"):
        distrust(f, u[:3], 0.2)


def test_distrusting_where_the_model_errs_narrows_the_interval_and_keeps_it_valid():
    """Synthetic policy: the model tracks the real score on half the states and is noise on
    the others, which a signal flags; distrusting them keeps coverage and narrows."""
    rng = np.random.default_rng(5)
    reps, big_n, n, truth = 2000, 20, 5, 0.5
    covered, plain, weighted = 0, [], []
    for _ in range(reps):
        y_all = np.clip(truth + rng.normal(0, 0.25, big_n), -1, 2)
        bad = np.arange(big_n) % 2 == 1
        f = np.where(bad, rng.uniform(0, 1, big_n), y_all + 0.1)
        idx = rng.choice(big_n, n, replace=False)
        a = paired_estimate(f, y_all[idx], idx)
        b = paired_estimate(distrust(f, bad.astype(float), 0.5), y_all[idx], idx)
        covered += b["interval"][0] <= truth <= b["interval"][1]
        plain.append(a["std_error"])
        weighted.append(b["std_error"])
    assert covered / reps >= 0.93, covered / reps
    assert np.median(weighted) < np.median(plain)


def _evaluation(path, scores, successes, seed=100000, steps=600):
    from iwsim.core.checkpoint import write_json_atomic

    path.mkdir(parents=True)
    episodes = [{"seed": seed + i, "max_iou": s, "success": ok} for i, (s, ok) in enumerate(zip(scores, successes))]
    write_json_atomic(path / "results.json", {"command": f"iwsim eval policy --out {path}", "env": "pusht",
                                              "steps": steps, "scorer": "IoU", "world_model": None,
                                              "episodes": episodes})
    return path


def test_two_policies_on_the_same_first_states_are_compared_episode_by_episode(tmp_path, capsys):
    """bench/compare_policies.py: the paired difference's interval is the Student t one of
    the per-state differences; evaluations of other first states or steps are refused."""
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location("compare_policies",
                                                  Path(__file__).parents[1] / "bench" / "compare_policies.py")
    cp = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cp)
    a = _evaluation(tmp_path / "a", [0.9, 0.5, 0.4, 0.95], [True, False, False, True])
    b = _evaluation(tmp_path / "b", [0.7, 0.5, 0.3, 0.60], [False, False, False, False])
    assert cp.main([f"two={a}", f"top={b}", "--out", str(tmp_path / "out")]) == 0
    c = cp.compare(cp.load(f"two={a}"), cp.load(f"top={b}"))
    d = np.array([0.2, 0.0, 0.1, 0.35])
    half = stats.t.ppf(0.975, 3) * d.std(ddof=1) / 2
    assert c["difference"] == pytest.approx(d.mean())
    assert c["interval"] == pytest.approx([d.mean() - half, d.mean() + half])
    assert c["better"] == {"two": 3, "top": 0, "tie": 1} and c["success_only"] == {"two": 2, "top": 0}
    assert "+0.163" in (tmp_path / "out" / "results.md").read_text() and (tmp_path / "out" / "scatter.png").is_file()
    written = json.loads((tmp_path / "out" / "results.json").read_text())
    assert next(iter(written)) == "command" and written["command"].startswith("python bench/compare_policies.py two=")
    other = _evaluation(tmp_path / "c", [0.7, 0.5, 0.3, 0.6], [False] * 4, seed=200000)
    longer = _evaluation(tmp_path / "d", [0.7, 0.5, 0.3, 0.6], [False] * 4, steps=300)
    capsys.readouterr()
    for bad, match in ((other, "other first states"), (longer, "other steps"), (tmp_path / "none", "no results")):
        assert cp.main([f"two={a}", f"x={bad}"]) == 2
        assert match in capsys.readouterr().err
