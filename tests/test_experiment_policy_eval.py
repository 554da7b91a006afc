"""``iwsim experiment policy-eval`` end to end at the tiny scale: a tiny world model,
tiny policies trained a few steps, 2 short episodes; the report, its reuse of cached
evaluations on a rerun, identical first frames, and one-line errors for bad flags."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest

from iwsim.cli import main
from iwsim.data.store import EpisodeStore
from iwsim.envs.collect import collect
from iwsim.envs.pilesweep.task import PileSweepTask
from iwsim.eval.policy import make_vector_env
from iwsim.eval.ranking import mmrv, pearson, spearman
from iwsim.experiments.policy_eval import PRESETS, PolicyEvalConfig, _demos, mean_interval
from tests.test_dynamics import tiny_world_model

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A tiny world model and a store of 2 short expert demonstrations."""
    root = tmp_path_factory.mktemp("policy_eval")
    tiny_world_model().save(root / "wm")
    collect("pusht", "expert", 2, out=root / "expert.zarr", steps=12, image_size=64, workers=1, seed=0,
            progress=False)
    return {"wm": root / "wm", "demos": root / "expert.zarr"}


def _argv(inputs: dict[str, Path], tmp_path: Path, *extra: str) -> list[str]:
    return ["experiment", "policy-eval", "--preset", "tiny", "--world-model", str(inputs["wm"]), "--demos",
            str(inputs["demos"]), "--out", str(tmp_path / "out"), "--work", str(tmp_path / "work"), "--no-progress",
            "--jobs", "1", *extra]  # in this process: a pool's spawned workers would cost more than these jobs


@pytest.mark.slow
def test_tiny_study_end_to_end_with_paired_estimates_and_resumed(inputs, tmp_path, capsys, caplog):
    caplog.set_level(logging.INFO)
    paired_flags = ("--paired-episodes", "2", "--holdout-episodes", "3")
    assert main(_argv(inputs, tmp_path, *paired_flags)) == 0
    assert "Pearson r" in capsys.readouterr().out
    out = tmp_path / "out"
    report = json.loads((out / "results.json").read_text())
    names = [p["name"] for p in report["policies"]]
    assert names == PRESETS["tiny"].policy_names() == [
        "dp-2demos-2steps", "dp-2demos-4steps", "dp-1demos-2steps", "act-2demos-2steps", "expert",
        "expert-noise0.01", "expert-latency2", "play"]
    assert report["scale"]["policies"] == 8 and report["scale"]["seeds"] == [100000, 100001]
    for p in report["policies"]:
        for env in ("pusht", "world-model"):
            r = p[env]
            assert len(r["max_iou"]) == 2 and r["mean_max_iou"] == pytest.approx(np.mean(r["max_iou"]), abs=1e-4)
            lo, hi = r["mean_max_iou_interval"]
            assert lo <= r["mean_max_iou"] + 1e-9 and r["mean_max_iou"] <= hi + 1e-9
            assert r["successes"] / 2 == r["success_rate"]
    learned = {p["name"]: p for p in report["policies"] if p["kind"] != "scripted"}
    assert learned["dp-2demos-4steps"]["train_steps"] == 4 and learned["dp-1demos-2steps"]["demos"] == 1
    assert int(Path(learned["act-2demos-2steps"]["source"]).name) == 2  # the checkpoint of that step
    # The agreement statistics are those of the per-policy scores in the report (in 6 steps
    # the block may not move, so every policy can score the same: then r and rho are undefined).
    for score in ("mean_max_iou", "success_rate"):
        real = [p["pusht"][score] for p in report["policies"]]
        proxy = [p["world-model"][score] for p in report["policies"]]
        a = report["agreement"][score]
        assert a["mmrv"] == pytest.approx(mmrv(real, proxy))
        for name, fn in (("pearson", pearson), ("spearman", spearman)):
            if len(set(real)) > 1 and len(set(proxy)) > 1:
                assert a[name] == pytest.approx(fn(real, proxy))
            else:
                assert a[name] is None and "constant" in a["undefined"][name]
        assert a["mean_offset"] == pytest.approx(np.mean(np.subtract(proxy, real)))
    # The same statistics within the 4 scripted and the 4 learned policies.
    assert report["scale"]["groups"] == {"scripted": 4, "learned": 4}
    for group, members in (("scripted", [p for p in report["policies"] if p["kind"] == "scripted"]),
                           ("learned", [p for p in report["policies"] if p["kind"] != "scripted"])):
        real = [p["pusht"]["mean_max_iou"] for p in members]
        proxy = [p["world-model"]["mean_max_iou"] for p in members]
        a = report["agreement_within"][group]["mean_max_iou"]
        assert a["mmrv"] == pytest.approx(mmrv(real, proxy))
        assert a["mean_offset"] == pytest.approx(np.mean(np.subtract(proxy, real)))
    # No policy places the T in 6 steps: constant success rates, so no correlation.
    assert report["agreement"]["success_rate"]["pearson"] is None
    md = (out / "results.md").read_text()
    assert report["command"] in md and "iwsim experiment policy-eval --preset tiny" in report["command"]
    assert next(iter(report)) == "command"
    assert all(f"| {n} |" in md for n in names) and "undefined" in md and "Within each group" in md
    # each policy's trust signals inside the model (iwsim.eval.trust), none in MuJoCo
    assert all(0 <= p["world-model"]["trust"]["implausibility"] <= 1 and not p["pusht"]["trust"]
               for p in report["policies"]) and "implausibility 0." in md
    assert (out / "scatter.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    _check_paired(report, md, out)

    # A rerun trains nothing and evaluates nothing: the cached evaluations are reused.
    cache = sorted((tmp_path / "work" / "policy_eval").glob("eval*/*/*.json"))
    assert len(cache) == 8 * 3  # MuJoCo, the model, MuJoCo's held-out first states
    stamps = [p.stat().st_mtime_ns for p in cache]
    caplog.clear()
    assert main(_argv(inputs, tmp_path, *paired_flags)) == 0
    assert [p.stat().st_mtime_ns for p in cache] == stamps
    assert not [r for r in caplog.records if r.getMessage().startswith(("evaluating", "training"))]
    again = json.loads((out / "results.json").read_text())
    assert again["agreement"] == report["agreement"] and again["policies"] == report["policies"]


def test_missing_demonstrations_are_recorded_in_the_shared_simulator_store(tmp_path):
    cfg = PRESETS["tiny"]
    path, info = _demos(cfg, tmp_path, progress=False)
    assert path == tmp_path / "demos" / "sim_expert.zarr"
    assert (info["episodes"], info["first_seed"], info["given"], info["policy"]) == (2, 0, False, "expert-pixels")
    attrs = EpisodeStore.open(path).attrs
    assert (attrs["steps"], attrs["tail_steps"], attrs["accept_iou"]) == (12, None, 0.0)
    assert _demos(cfg, tmp_path, progress=False)[1]["added_now"] == 0  # a rerun reuses it


def test_first_frames_are_identical_in_both_simulators():
    seeds = [100000, 100001, 100002]
    frames = {}
    for env in ("pusht", "world-model"):
        venv = make_vector_env(env, len(seeds), 5, world_model=tiny_world_model())
        try:
            obs, _ = venv.reset(seed=seeds)
            frames[env] = obs["pixels"]
        finally:
            venv.close()
    assert frames["pusht"].shape == (3, 64, 64, 3)
    np.testing.assert_array_equal(frames["pusht"], frames["world-model"])
    assert not np.array_equal(frames["pusht"][0], frames["pusht"][1])  # the seeds differ


def test_the_default_preset_is_the_study_asked_for():
    cfg = PRESETS["default"]
    names = cfg.policy_names()
    assert len(names) >= 14 and cfg.episodes >= 20 and cfg.seed == 100000 and cfg.steps == 600
    assert sum(n.startswith("dp-100demos") for n in names) >= 3 and sum(n.startswith("act-") for n in names) >= 2
    assert {"expert", "play"} <= set(names) and any("noise" in n for n in names) and any("latency" in n for n in names)
    for run, steps in cfg.runs("store.zarr"):  # every evaluated step is kept, and a run saves every 500 steps
        assert all(s % run.checkpoint_every == 0 for s in steps) and run.steps == max(steps)
        assert run.checkpoint_every <= 500


def test_mean_interval_brackets_the_mean():
    lo, hi = mean_interval(np.array([0.1, 0.9, 0.5, 0.7]))
    assert 0.1 <= lo < 0.55 < hi <= 0.9
    assert mean_interval(np.array([0.3, 0.3])) == pytest.approx((0.3, 0.3))


@pytest.mark.parametrize(("extra", "match"), [
    (["--episodes", "0"], "--episodes must be a positive integer"),
    (["--seed", "-1"], "--seed must be in"),
    (["--jobs", "0"], "--jobs must be a positive integer"),
    (["--world-model", "nowhere"], "not a checkpoint directory"),
    (["--demos", "nowhere.zarr"], "nowhere.zarr"),
    (["--demo-episodes", "5", "--small-demos", "1"], "holds 2 demonstrations"),
    (["--small-demos", "2"], "--small-demos"),
])
def test_bad_flags_are_one_line_errors(inputs, tmp_path, capsys, extra, match):
    assert main(_argv(inputs, tmp_path, *extra)) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("iwsim: error:") and match in err and "\n" not in err
    assert not (tmp_path / "out").exists()


def test_config_refuses_a_study_that_cannot_rank():
    with pytest.raises(ValueError, match="at least 3 policies"):
        PolicyEvalConfig(dp_steps=(), dp_small_steps=1, act_steps=(), noise=(), latency=(), play=False,
                         small_demos=1, demo_episodes=2)


@pytest.mark.slow
def test_tiny_study_on_pile_sweeping(pile_model, tmp_path, capsys):
    """Issue 45: the study on pile sweeping: its MuJoCo the reference, its expert the
    demonstrator (recorded here, in a work directory of the task's own), its scripted
    policies in the zoo, its score in the report."""
    out, work = tmp_path / "out", tmp_path / "work"
    assert main(["experiment", "policy-eval", "--preset", "tiny", "--task", "pilesweep", "--world-model",
                 str(pile_model["checkpoint"]), "--out", str(out), "--work", str(work), "--no-progress",
                 "--jobs", "1", "--paired-episodes", "2", "--holdout-episodes", "3"]) == 0
    assert "mean max share in tray: Pearson r" in capsys.readouterr().out
    report = json.loads((out / "results.json").read_text())
    assert report["config"]["task"] == "pilesweep" and report["scale"]["steps"] == 6  # the tiny preset's
    assert "--task pilesweep" in report["command"] and f"--world-model {pile_model['checkpoint']}" in report["command"]
    assert [p["name"] for p in report["policies"]] == PRESETS["tiny"].policy_names()
    for p in report["policies"]:
        for env in ("pilesweep", "world-model"):
            r = p[env]
            assert len(r["max_score"]) == 2 and r["mean_max_score"] == pytest.approx(np.mean(r["max_score"]), abs=1e-4)
        assert "pusht" not in p and "mean_max_iou" not in p["pilesweep"]
    assert set(report["agreement"]) == {"mean_max_score", "success_rate"}
    demos = work / "pilesweep" / "demos" / "sim_expert.zarr"
    assert report["scale"]["demos"]["path"] == str(demos) and not (work / "demos").exists()
    store = EpisodeStore.open(demos)
    assert (store.attrs["task"], store.attrs["policy"], store.n_episodes) == ("pilesweep", "expert-pixels", 2)
    assert store.attrs["teleoperator"] == "expert (pieces from pixels)" and "score" in store.keys
    cached = json.loads((work / "pilesweep" / "policy_eval" / "eval" / "pilesweep" / "expert.json").read_text())
    assert len(cached["score_per_step"][0]) == 7 and cached["key"]["env"] == "pilesweep"
    md = (out / "results.md").read_text()
    assert "maximum share in tray an episode reaches; success: share in tray >= 0.9" in md
    assert "MuJoCo max share in tray" in md and "IoU" not in md
    assert (out / "scatter.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # issue 66 on this task too: each policy's paired estimate of its mean max share in tray
    paired = report["paired"]
    assert paired["holdout_episodes"] == 3
    assert set(paired["by_n"]["2"]["policies"]) == set(PRESETS["tiny"].policy_names())
    held = json.loads((work / "pilesweep" / "policy_eval" / "eval_holdout" / "pilesweep" / "expert.json").read_text())
    lo, hi = paired["holdout_seeds"]
    assert held["key"]["seeds"] == list(range(lo, hi + 1)) and held["key"]["env"] == "pilesweep"
    assert "## Paired estimates" in md and "mean max share in tray" in md


@pytest.mark.parametrize(("extra", "match"), [
    ([], "task 'pilesweep' has no shipped world model; pass --world-model"),
    (["--world-model", "WM"], "is a world model of task 'pusht'; the study compares with MuJoCo's 'pilesweep'"),
    (["--world-model", "PILE", "--demos", "DEMOS"], "holds episodes of task 'pusht'; the study runs on 'pilesweep'"),
])
def test_a_study_on_pile_sweeping_refuses_another_tasks_inputs(inputs, pile_model, tmp_path, capsys, extra, match,
                                                                monkeypatch):
    monkeypatch.setattr(PileSweepTask, "checkpoint", None)  # a task without a shipped model needs --world-model
    paths = {"WM": str(inputs["wm"]), "PILE": str(pile_model["checkpoint"]), "DEMOS": str(inputs["demos"])}
    assert main(["experiment", "policy-eval", "--preset", "tiny", "--task", "pilesweep", "--out", str(tmp_path / "out"),
                 "--work", str(tmp_path / "work"), "--no-progress", *(paths.get(x, x) for x in extra)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("iwsim: error:") and match in err and "\n" not in err
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_a_study_with_two_jobs_ends_without_leaked_semaphores(inputs, tmp_path):
    """Issue 65's smaller list: a clean ``--jobs 2`` study printed "leaked semaphore
    objects" at exit (its pool's workers were killed holding tqdm's multiprocessing lock)."""
    import os
    import subprocess
    import sys

    iwsim = Path(sys.executable).parent / "iwsim"
    run = subprocess.run([str(iwsim), *_argv(inputs, tmp_path, "--jobs", "2")], capture_output=True, text=True,
                         env={**os.environ, "MUJOCO_GL": "egl"}, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "leaked" not in run.stderr and "resource_tracker" not in run.stderr, run.stderr[-2000:]


def _check_paired(report: dict, md: str, out: Path) -> None:
    """Issue 66 item 2: --paired-episodes N reports every policy's paired estimate judged
    against MuJoCo on held-out first states, with coverage, widths and the ranking."""
    paired = report["paired"]
    assert paired["holdout_episodes"] == 3 and paired["holdout_seeds"] == [110000, 110002]
    rows = paired["by_n"]["2"]["policies"]
    assert set(rows) == {p["name"] for p in report["policies"]}
    for r in rows.values():
        lo, hi = r["interval"]
        assert lo <= r["estimate"] <= hi and r["covered"] == (lo <= r["truth"] <= hi)
        assert r["lam"] == 1.0  # two pairs: the classic PPI weight
    assert 0 <= paired["by_n"]["2"]["coverage"] <= 1 and "pearson" in paired["by_n"]["2"]["agreement"]
    assert "## Paired estimates" in md and "| 2 |" in md
    assert "--paired-episodes 2" in report["command"]
    assert (out / "paired.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    weighted = paired["trust_weighted"]["command_lead"]  # the model distrusted where its commands press ahead
    assert set(weighted["by_n"]["2"]["policies"]) == set(rows) and 0 <= weighted["by_n"]["2"]["coverage"] <= 1
    assert "Distrusted where `command_lead`" in md and "Per policy (95% intervals" in md


@pytest.mark.parametrize(("bad", "says"), [("1", "--paired-episodes must be counts in 2..2"),
                                           ("a,b", "takes counts N,N")])
def test_bad_paired_episodes_are_one_line_errors(inputs, tmp_path, capsys, bad, says):
    assert main(_argv(inputs, tmp_path, "--paired-episodes", bad)) == 1
    err = capsys.readouterr().err.strip()
    assert says in err and "\n" not in err and not (tmp_path / "out").exists()
