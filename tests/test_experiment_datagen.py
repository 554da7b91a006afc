"""``iwsim experiment datagen``: demonstrations recorded through the vector envs with the
acceptance filter (layout, first frames, resume), and a tiny end-to-end study."""

import dataclasses
import json
import logging
import re
from pathlib import Path

import numpy as np
import pytest
import torch
import zarr

from iwsim.cli import main
from iwsim.data.store import EpisodeStore
from iwsim.envs.collect import store_attrs
from iwsim.envs.pusht.geometry import wrap_angle
from iwsim.envs.pusht.pixels import estimate_block_pose
from iwsim.envs.pusht.sim import GOAL_POSE
from iwsim.envs.registry import get_task
from iwsim.eval.policy import rollout, seed_sampling
from iwsim.experiments.common import fingerprint
from iwsim.experiments.datagen import PRESETS, DatagenConfig, command, demo_paths, plan
from iwsim.experiments.demos import SIM_SEED, DemoRecipe, handover_step, record_demos, record_with, simulator_store
from iwsim.experiments.policy_eval import PolicyEvalConfig
from iwsim.experiments.policy_eval import command as policy_eval_command
from iwsim.play.engine import EPISODE_KEYS
from iwsim.policies.factory import checkpoint_dir, load_policy
from iwsim.policies.scripted import ScriptedBatch
from tests.test_dynamics import tiny_world_model

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def wm_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("wm") / "tiny-wm"
    tiny_world_model().save(path)
    return path


@pytest.fixture(scope="module")
def learned(play_store: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny Diffusion Policy run on 64 px frames (2 training steps) for the expert to take over from."""
    out = tmp_path_factory.mktemp("policy") / "dp"
    assert main(["train", "policy", "--policy", "dp", "--preset", "tiny-dp", "--data", f"{play_store}:2",
                 "--steps", "2", "--out", str(out), "--no-progress"]) == 0
    return out


def record(env: str, out: Path, wm_path: Path, episodes: int = 2, **kw):
    kw = {"steps": 6, "seed": 300000, "accept_iou": 0.0, "tail": None, "batch": 2, "progress": False, **kw}
    return record_demos(env, out, episodes, kw.pop("steps"), kw.pop("seed"), world_model=wm_path, **kw)


def test_rollout_returns_every_step_and_stops_when_asked(wm_path):
    from iwsim.world_model import WorldModel

    wm = WorldModel.load(wm_path)
    run = rollout(ScriptedBatch("expert"), "world-model", [5, 6], 4, world_model=wm, record=2, progress=False)
    assert run["frames"].shape == (2, 5, 64, 64, 3) and run["agent_pos"].shape == (2, 5, 4)
    assert run["action"].shape == run["target"].shape == (2, 4, 4) and run["iou"].shape == (2, 5)
    # the executed setpoints move towards the commands at the speed limit, from the pushers at reset
    assert np.abs(run["target"][:, 0] - run["agent_pos"][:, 0]).max() <= 0.0161
    calls = []
    short = rollout(ScriptedBatch("expert"), "world-model", [5, 6], 4, world_model=wm, progress=False,
                    stop=lambda obs: calls.append(obs) or len(calls) == 2)
    assert short["action"].shape == (2, 2, 4) and short["iou"].shape == (2, 3)
    np.testing.assert_allclose(short["iou"], run["iou"][:, :3], atol=0.02)


def test_acceptance_filter(wm_path, tmp_path, caplog):
    everything = record("world-model", tmp_path / "all.zarr", wm_path, episodes=4, batch=4)
    assert (everything.episodes, everything.candidates, everything.acceptance_rate) == (4, 4, 1.0)
    scores = EpisodeStore.open(tmp_path / "all.zarr").attrs["candidate_max_iou"]
    assert len(scores) == 4
    # a threshold between the candidates' scores keeps exactly those that reach it
    threshold = float(np.median(scores))
    some = record("world-model", tmp_path / "some.zarr", wm_path, episodes=4, batch=4, max_attempts=4,
                  accept_iou=threshold)
    kept = [300000 + i for i, m in enumerate(scores) if m >= threshold]
    store = EpisodeStore.open(tmp_path / "some.zarr")
    assert store.seeds == kept and some.acceptance_rate == len(kept) / 4
    assert all(store.episode(i)["iou"].max() >= threshold for i in range(len(store)))
    with caplog.at_level(logging.WARNING):
        none = record("world-model", tmp_path / "none.zarr", wm_path, episodes=2, max_attempts=3, accept_iou=1.0)
    assert (none.episodes, none.candidates, none.acceptance_rate, none.complete) == (0, 3, 0.0, False)
    assert "holds 0 of the 2 demonstrations asked for: 3 candidates tried" in caplog.text
    assert EpisodeStore.open(tmp_path / "none.zarr").n_episodes == 0
    # with nothing kept after give_up_after candidates, the teleoperator stops early
    with caplog.at_level(logging.WARNING):
        early = record("world-model", tmp_path / "early.zarr", wm_path, episodes=2, max_attempts=8, give_up_after=2,
                       accept_iou=1.0)
    assert (early.episodes, early.candidates) == (0, 2) and "none of 2 candidates" in caplog.text
    for bad in (float("nan"), 2.0, -0.1):  # a score above 1 keeps nothing, after the whole budget (issue 65)
        with pytest.raises(ValueError, match=r"accept_iou must be a score in \[0, 1\]"):
            record("pusht", tmp_path / "bad.zarr", wm_path, accept_iou=bad)
    with pytest.raises(ValueError, match="needs? a world-model checkpoint"):
        record_demos("world-model", tmp_path / "bad.zarr", 1, 4, 0)


def test_kept_takes_end_tail_steps_after_success(wm_path, tmp_path):
    """accept_iou 0: the first frame succeeds, so a take holds ``tail`` steps (and the
    batch stops there instead of running the whole horizon)."""
    stats = record("pusht", tmp_path / "cut.zarr", wm_path, steps=8, tail=3)
    store = EpisodeStore.open(tmp_path / "cut.zarr")
    assert np.diff(store.episode_ends, prepend=0).tolist() == [3, 3] and stats.mean_length == 3


def test_first_frames_identical_and_layout_matches_collect(wm_path, tmp_path, play_store):
    sim = record("pusht", tmp_path / "sim.zarr", wm_path, episodes=2, seed=7)
    wm = record("world-model", tmp_path / "wm.zarr", wm_path, episodes=2, seed=7)
    a, b = EpisodeStore.open(sim.path), EpisodeStore.open(wm.path)
    for i in range(2):
        x, y = a.episode(i), b.episode(i)
        np.testing.assert_array_equal(x["img"][0], y["img"][0])
        np.testing.assert_array_equal(x["state"][0], y["state"][0])
        assert x["iou"][0] == y["iou"][0]
        # step t's target is the speed-limited motion towards step t's command
        assert np.abs(x["target"][0] - x["state"][0]).max() <= 0.0161
    collected = EpisodeStore.open(play_store)
    for store in (a, b):
        assert store.keys == sorted(EPISODE_KEYS)
        info, ref = store.info()["arrays"], collected.info()["arrays"]
        for k in EPISODE_KEYS:
            assert (info[k]["dtype"], info[k]["shape"][1:]) == (ref[k]["dtype"], ref[k]["shape"][1:])
        assert set(store_attrs("pusht", "x", 1, 64)) <= set(store.attrs)
        assert set(collected.attrs) - {"seeds"} <= set(store.attrs)
    assert a.attrs["policy"] == "expert-pixels" and a.attrs["world_model"] is None
    assert b.attrs["policy"] == "world-model-teleop" and b.attrs["world_model"] == str(wm_path)
    out = tmp_path / "pol"
    assert main(["train", "policy", "--policy", "dp", "--preset", "tiny-dp", "--data", f"{wm.path}:1,{sim.path}:2",
                 "--out", str(out), "--steps", "2", "--no-progress"]) == 0
    assert (out / "checkpoints" / "last").exists()


def test_resume_appends_only_what_is_missing(wm_path, tmp_path):
    path = tmp_path / "r.zarr"
    first = record("world-model", path, wm_path, episodes=2)
    before = EpisodeStore.open(path).episode(1)["img"]
    more = record("world-model", path, wm_path, episodes=3)
    assert (first.added, more.added, more.tried, more.candidates) == (2, 1, 1, 3)
    store = EpisodeStore.open(path)
    assert store.seeds == [300000, 300001, 300002]
    np.testing.assert_array_equal(store.episode(1)["img"], before)
    again = record("world-model", path, wm_path, episodes=3)
    assert (again.added, again.tried, again.episodes) == (0, 0, 3)
    with pytest.raises(ValueError, match="accept_iou=0.0, not accept_iou=0.5"):
        record("world-model", path, wm_path, episodes=3, accept_iou=0.5)
    other = tmp_path / "wm"  # a retrained model at the same path does not extend the old one's demonstrations
    tiny_world_model().save(other)
    record("world-model", tmp_path / "o.zarr", other, episodes=1)
    tiny_world_model(seed=1).save(other, force=True)
    with pytest.raises(ValueError, match="world_model_sha256="):
        record("world-model", tmp_path / "o.zarr", other, episodes=2)


def test_one_recipe_for_both_studies():
    """The studies share the simulator store, so they share its recipe, whose defaults are
    those the recorded ``sim_expert.zarr`` holds (a store refuses another recipe)."""
    r = DemoRecipe()
    assert (r.steps, r.tail, r.accept_iou, r.attempts_per_demo, r.batch, r.demonstrator) == (
        300, 10, 0.9, 2.0, 16, "expert")
    assert DatagenConfig().recipe == PolicyEvalConfig().recipe == r and SIM_SEED == 0
    assert simulator_store(Path("w")) == Path("w/demos/sim_expert.zarr")
    DemoRecipe(tail=None)
    for kw, match in (({"steps": 0}, "demo_steps must be a positive integer"), ({"tail": 0}, "demo_tail must"),
                      ({"batch": 1.5}, "demo_batch must"), ({"accept_iou": float("nan")}, "accept_iou must be"),
                      ({"attempts_per_demo": 0.5}, "attempts_per_demo must be >= 1")):
        with pytest.raises(ValueError, match=match):
            DemoRecipe(**kw)
    tiny = PRESETS["tiny"]
    cfg = dataclasses.replace(tiny, total=3, recipe=dataclasses.replace(tiny.recipe, steps=9, accept_iou=0.5))
    assert command(cfg, "tiny", Path("o"), Path("w")) == (
        "iwsim experiment datagen --preset tiny --total 3 --accept-iou 0.5 --demo-steps 9 --out o --work w")
    # Another demonstrator's takes: their own stores, and the flag in the command that reproduces the study.
    wide = dataclasses.replace(tiny, recipe=dataclasses.replace(tiny.recipe, demonstrator="expert-wide"))
    assert simulator_store(Path("w"), "expert-wide") == Path("w/demos/sim_expert-wide.zarr")
    paths = demo_paths(wide, Path("w"), "abc")
    assert paths["sim"] == Path("w/demos/sim_expert-wide.zarr") and paths["wm"].name.endswith("_abc_expert-wide.zarr")
    assert demo_paths(tiny, Path("w"), "abc")["wm"].name.endswith("_abc.zarr")
    assert command(wide, "tiny", Path("o"), Path("w")) == (
        "iwsim experiment datagen --preset tiny --demonstrator expert-wide --out o --work w")
    policy_eval = dataclasses.replace(PolicyEvalConfig(), recipe=DemoRecipe(demonstrator="expert-wide"))
    assert policy_eval_command(policy_eval, "default", Path("o"), Path("w"), 2) == (
        "iwsim experiment policy-eval --preset default --demonstrator expert-wide --jobs 2 --out o --work w")


def test_recipe_flags_are_checked_before_any_work(tmp_path, capsys):
    assert main(["experiment", "datagen", "--preset", "tiny", "--demo-steps", "0", "--out", str(tmp_path / "o"),
                 "--work", str(tmp_path / "w"), "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert err == "iwsim: error: demo_steps must be a positive integer, got 0."
    assert not (tmp_path / "w").exists()


def test_plan_shares_runs_between_the_sweeps():
    cfg = DatagenConfig(total=50, wm_fractions=(0.0, 0.5, 1.0), sim_sizes=(25, 50, 100))
    runs = {(r.n_wm, r.n_sim): r.sweeps for r in plan(cfg)}
    assert runs == {(0, 50): ("mixture", "size"), (25, 25): ("mixture",), (50, 0): ("mixture",),
                    (0, 25): ("size",), (0, 100): ("size",)}
    with pytest.raises(ValueError, match="unknown policy"):
        DatagenConfig(policy="ppo")
    assert PRESETS["tiny"].preset == "tiny-dp"
    # The paper's protocol: mixtures of 100 at 0-100% world model, sizes 5-100 of both sources.
    for name, policy, n_runs in (("default", "dp", 9), ("act", "act", 5)):
        cfg = PRESETS[name]
        assert (cfg.policy, cfg.total, cfg.wm_fractions, cfg.steps, cfg.episodes) == (
            policy, 100, (0.0, 0.25, 0.5, 0.75, 1.0), 600, 50)
        assert len(plan(cfg)) == n_runs
    sizes = {(r.n_wm, r.n_sim): r.sweeps for r in plan(PRESETS["default"])}
    assert sizes[(100, 0)] == sizes[(0, 100)] == ("mixture", "size") and (5, 0) in sizes and (0, 5) in sizes
    cfg = dataclasses.replace(PRESETS["act"], wm_fractions=(0.0, 1.0), wm_sizes=(10,))
    assert command(cfg, "act", Path("o"), Path("w")) == (
        "iwsim experiment datagen --preset act --fractions 0.0,1.0 --wm-sizes 10 --out o --work w")


def test_sweep_flags_are_parsed(tmp_path, capsys):
    for flag, value, kind in (("--fractions", "0,half", "floats"), ("--wm-sizes", "5,x", "ints")):
        assert main(["experiment", "datagen", "--preset", "tiny", flag, value, "--out", str(tmp_path / "o"),
                     "--work", str(tmp_path / "w"), "--no-progress"]) == 1
        assert capsys.readouterr().err.strip() == f"iwsim: error: {flag} takes comma-separated {kind}, got {value!r}."
    assert not (tmp_path / "w").exists()


@pytest.mark.slow
def test_tiny_study_end_to_end(wm_path, tmp_path):
    out, work = tmp_path / "out", tmp_path / "work"
    args = ["experiment", "datagen", "--preset", "tiny", "--world-model", str(wm_path), "--out", str(out),
            "--work", str(work), "--jobs", "1", "--no-progress"]
    assert main(args) == 0
    r = json.loads((out / "results.json").read_text())
    assert (out / "datagen.png").stat().st_size > 0
    md = (out / "results.md").read_text()
    assert next(iter(r)) == "command" and r["command"] in md.split("\n")[:5] and "parity ratio" in md
    assert (work / "demos" / "sim_expert.zarr").is_dir()
    assert {k: d["episodes"] for k, d in r["demos"].items()} == {"sim": 2, "wm": 2}
    assert r["config"]["recipe"] == json.loads(json.dumps(dataclasses.asdict(PRESETS["tiny"].recipe)))  # tuples: lists
    assert "reaches 0.0 and ends 4 steps after that (horizon 8 steps)" in md
    assert (r["demos"]["sim"]["first_seed"], r["demos"]["wm"]["first_seed"]) == (SIM_SEED, 300000)
    names = [run["name"] for run in r["runs"]]
    tag = fingerprint(wm_path)[:8]  # runs on world-model demonstrations name the model
    assert names == ["tiny-dp-wm0-sim2", f"tiny-dp-wm1-sim1-{tag}", f"tiny-dp-wm2-sim0-{tag}", "tiny-dp-wm0-sim1"]
    assert (work / "demos" / f"wm_teleop_tiny-wm_{tag}.zarr").is_dir()
    for run in r["runs"]:
        assert sum(d["episodes"] for d in run["data"]) == run["n_wm"] + run["n_sim"]
        assert run["training"]["steps"] == 4 and len(run["episodes"]) == 2 and run["name"] in md
        lo, hi = run["success_clopper_pearson"]
        assert lo <= run["success_rate"] <= hi
    p = r["parity"]
    assert (p["world_model"], p["simulator"]) == (names[2], names[0])
    by_name = {run["name"]: run for run in r["runs"]}
    assert p["mean_max_iou"]["ratio"] == pytest.approx(
        by_name[names[2]]["mean_max_iou"] / by_name[names[0]]["mean_max_iou"])
    assert r["expert"]["episodes"][0]["seed"] == 100000
    # a rerun resumes: nothing is recorded, trained or evaluated again
    stamp = (work / "datagen" / "runs" / names[0] / "metrics.jsonl").stat().st_mtime_ns
    assert main(args) == 0
    r2 = json.loads((out / "results.json").read_text())
    assert r2["runs"] == r["runs"] and r2["demos"]["sim"]["added"] == 0
    assert (work / "datagen" / "runs" / names[0] / "metrics.jsonl").stat().st_mtime_ns == stamp
    # too few demonstrations: the runs that need them are reported, not trained
    assert main(["experiment", "datagen", "--preset", "tiny", "--world-model", str(wm_path), "--accept-iou", "1.0",
                 "--out", str(tmp_path / "out2"), "--work", str(tmp_path / "work2"), "--jobs", "1",
                 "--no-progress"]) == 0
    r3 = json.loads((tmp_path / "out2" / "results.json").read_text())
    assert all("only 0 were kept" in run["skipped"] for run in r3["runs"])
    assert "not trained" in r3["parity"]["note"]


@pytest.mark.parametrize("study", ["datagen", "policy-eval"])
def test_a_second_study_on_a_work_directory_in_use_is_refused(wm_path, tmp_path, capsys, study):
    """Issue 26: two studies on one --work trained the same run directories at once."""
    from iwsim.core.lock import DirLock

    work = tmp_path / "work"
    work.mkdir()
    with DirLock(work, what="running the datagen study"):
        args = ["experiment", study, "--preset", "tiny", "--world-model", str(wm_path),
                "--out", str(tmp_path / "out"), "--work", str(work), "--no-progress"]
        assert main(args) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is in use by another study" in err[0] and "running the datagen study" in err[0], err
    assert sorted(p.name for p in work.iterdir()) == [".iwsim.lock"] and not (tmp_path / "out").exists()


@pytest.mark.slow
def test_a_study_killed_at_any_point_and_rerun_ends_as_an_uninterrupted_one(wm_path, tmp_path):
    """Issue 26: a study killed and re-run must end with the results (scores and trained
    weights) of an uninterrupted run. One study is killed three times, each time as soon as
    a phase has begun (recording the demonstrations, training the policies, evaluating
    them), every kill in a run resumed from the last one, then run to its end."""
    import os
    import signal
    import subprocess
    import sys
    import time

    iwsim = Path(sys.executable).parent / "iwsim"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}

    def cmd(name: str) -> list[str]:
        return [str(iwsim), "experiment", "datagen", "--preset", "tiny", "--world-model", str(wm_path),
                "--out", str(tmp_path / name / "out"), "--work", str(tmp_path / name / "work"), "--jobs", "1",
                "--no-progress"]

    def outcome(name: str) -> dict:
        r = json.loads((tmp_path / name / "out" / "results.json").read_text())
        runs = tmp_path / name / "work" / "datagen" / "runs"
        return {run["name"]: (run["mean_max_iou"], run["success_rate"],
                              (runs / run["name"] / "checkpoints" / "last" / "model.safetensors").read_bytes())
                for run in r["runs"]}

    subprocess.run(cmd("whole"), env=env, check=True, capture_output=True)
    want = outcome("whole")
    work = tmp_path / "killed" / "work"
    for phase in ("demos/sim_expert.zarr", "datagen/runs/*/checkpoints", "datagen/eval/pusht/*.json"):
        proc = subprocess.Popen(cmd("killed"), env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 300
        while not any(work.glob(phase)):
            assert proc.poll() is None and time.monotonic() < deadline, f"the study never reached {phase}"
            time.sleep(0.005)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        assert not (tmp_path / "killed" / "out" / "results.json").exists(), f"killed at {phase} after its end"
    subprocess.run(cmd("killed"), env=env, check=True, capture_output=True)
    assert outcome("killed") == want


def test_dart_recording_executes_noisy_commands_and_stores_the_experts_clean_ones(wm_path, tmp_path):
    """Issue 25: with dart_noise the executed setpoints are perturbed, and the stored
    actions are what the expert commanded from the states the noise led to."""
    clean = record("pusht", tmp_path / "clean.zarr", wm_path, steps=12, episodes=1, batch=1)
    dart = record("pusht", tmp_path / "dart.zarr", wm_path, steps=12, episodes=1, batch=1, dart_noise=0.01)
    assert clean.episodes == dart.episodes == 1
    a, b = EpisodeStore.open(tmp_path / "clean.zarr"), EpisodeStore.open(tmp_path / "dart.zarr")
    assert a.attrs["dart_noise"] == 0.0 and b.attrs["dart_noise"] == 0.01
    ep = b.episode(0)
    assert not np.allclose(ep["state"], a.episode(0)["state"])  # the noise moved the pushers
    # replaying the expert on the recorded frames and positions gives exactly the stored actions
    expert = ScriptedBatch("expert")
    replayed = [expert.predict_action({"image": ep["img"][t][None, None], "agent_pos": ep["state"][t][None, None]})
                for t in range(len(ep["action"]))]
    np.testing.assert_array_equal(np.concatenate(replayed)[:, 0], ep["action"])
    with pytest.raises(ValueError, match="dart_noise=0.01, not dart_noise=0.02"):
        record("pusht", tmp_path / "dart.zarr", wm_path, steps=12, episodes=2, batch=1, dart_noise=0.02)
    with pytest.raises(ValueError, match="dart_noise must be a finite number"):
        DemoRecipe(dart_noise=-1.0)


def test_goal_turned_recording_starts_from_the_turned_block_and_keeps_to_its_store(wm_path, tmp_path):
    """Issue 25's recovery demonstrations: a store of takes from the block on the goal's
    position turned away from it, which only takes of the same start may extend."""
    stats = record("pusht", tmp_path / "turned.zarr", wm_path, episodes=2, start="goal-turned")
    store = EpisodeStore.open(tmp_path / "turned.zarr")
    assert stats.episodes == 2 and store.attrs["start"] == "goal-turned"
    for i in range(2):
        pose = estimate_block_pose(store.episode(i)["img"][0]).pose  # read from the first frame
        assert np.abs(pose[:2] - GOAL_POSE[:2]).max() < 0.025
        assert abs(wrap_angle(pose[2] - GOAL_POSE[2])) > np.pi / 4 - 0.1
    with pytest.raises(ValueError, match="start='goal-turned', not start='random'"):
        record("pusht", tmp_path / "turned.zarr", wm_path, episodes=3)
    with pytest.raises(ValueError, match="start must be one of"):
        DemoRecipe(start="turned")
    with pytest.raises(ValueError, match="the world model starts from random ones"):
        record("world-model", tmp_path / "wm.zarr", wm_path, start="goal-turned")



def test_a_store_holds_one_demonstrators_takes(wm_path, tmp_path):
    """Issue 44: takes of the forgiving expert-wide go to a store of their own, which the
    expert's takes may not extend; a store written before demonstrators were named resumes
    as the expert's."""
    path = tmp_path / "wide.zarr"
    recipe = DemoRecipe(steps=6, tail=None, accept_iou=0.0, batch=1, demonstrator="expert-wide")
    assert record_with("pusht", path, 1, 300000, recipe, progress=False).episodes == 1
    store = EpisodeStore.open(path)
    assert store.attrs["demonstrator"] == "expert-wide"
    ep = store.episode(0)
    wide = ScriptedBatch("expert-wide")  # the stored actions are expert-wide's
    replayed = [wide.predict_action({"image": ep["img"][t][None, None], "agent_pos": ep["state"][t][None, None]})
                for t in range(len(ep["action"]))]
    np.testing.assert_array_equal(np.concatenate(replayed)[:, 0], ep["action"])
    assert record("pusht", path, wm_path, episodes=2, batch=1, demonstrator="expert-wide").added == 1
    with pytest.raises(ValueError, match="demonstrator='expert-wide', not demonstrator='expert'"):
        record("pusht", path, wm_path, episodes=3, batch=1)
    old = tmp_path / "old.zarr"
    record("pusht", old, wm_path, episodes=1, batch=1)
    del zarr.open_group(old, mode="r+").attrs["demonstrator"]
    assert "demonstrator" not in EpisodeStore.open(old).attrs
    assert record("pusht", old, wm_path, episodes=2, batch=1).added == 1
    with pytest.raises(ValueError, match="demonstrator='expert', not demonstrator='expert-wide'"):
        record("pusht", old, wm_path, episodes=3, batch=1, demonstrator="expert-wide")
    with pytest.raises(ValueError, match="demonstrator must be one of expert, expert-wide, got 'human'"):
        DemoRecipe(demonstrator="human")
    with pytest.raises(ValueError, match="demonstrator must be one of"):
        record("pusht", tmp_path / "bad.zarr", wm_path, demonstrator="play")


def test_the_command_line_offers_each_studys_presets():
    """The parser spells the studies' preset names (importing a study would cost every
    ``iwsim`` command torch's import); they stay the studies' own."""
    import argparse

    from iwsim.cli import build_parser
    from iwsim.experiments import policy_eval

    def subcommand(parser: argparse.ArgumentParser, name: str) -> argparse.ArgumentParser:
        return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[name]

    experiment = subcommand(build_parser(), "experiment")
    for study, presets in (("datagen", PRESETS), ("policy-eval", policy_eval.PRESETS)):
        preset = next(a for a in subcommand(experiment, study)._actions if a.dest == "preset")
        assert tuple(preset.choices) == tuple(presets), study


def test_tiny_study_on_pile_sweeping(pile_model, tmp_path):
    """Issue 45: the study on pile sweeping: its expert records in its MuJoCo and in a world
    model of it, the policies are evaluated in its MuJoCo against its expert, the report
    names its score; its work and report sit apart from T-push's."""
    work = tmp_path / "work"
    assert main(["experiment", "datagen", "--preset", "tiny", "--task", "pilesweep", "--world-model",
                 str(pile_model["checkpoint"]), "--out", str(tmp_path / "out"), "--work", str(work), "--jobs", "1",
                 "--no-progress"]) == 0
    r = json.loads((tmp_path / "out" / "results.json").read_text())
    assert r["config"]["task"] == "pilesweep" and r["scale"]["eval_steps"] == 6  # the tiny preset's
    assert r["command"].startswith("iwsim experiment datagen --preset tiny --task pilesweep --world-model ")
    tag = fingerprint(pile_model["checkpoint"])[:8]
    stores = {"sim": work / "pilesweep" / "demos" / "sim_expert.zarr",
              "wm": work / "pilesweep" / "demos" / f"wm_teleop_wm_{tag}.zarr"}
    assert {k: d["path"] for k, d in r["demos"].items()} == {k: str(v) for k, v in stores.items()}
    for key, source in (("sim", "mujoco"), ("wm", "world_model")):
        store = EpisodeStore.open(stores[key])
        assert (store.attrs["task"], store.attrs["source"], store.n_episodes) == ("pilesweep", source, 2)
        assert store.keys == sorted(("img", "state", "action", "target", "score"))
    starts = get_task("pilesweep").initial_frames(64)  # the takes in the model start from MuJoCo's frames
    np.testing.assert_array_equal(EpisodeStore.open(stores["wm"]).episode(1)["img"][0], starts.draw(300001).frame)
    starts.close()
    assert not (work / "demos").exists() and not (work / "datagen").exists()  # T-push's places
    assert r["expert"]["episodes"][0]["seed"] == 100000 and "mean_max_score" in r["expert"]
    for run in r["runs"]:
        assert run["training"]["steps"] == 4 and len(run["episodes"]) == 2 and "max_score" in run["episodes"][0]
    p = r["parity"]
    by_name = {run["name"]: run for run in r["runs"]}
    if p["mean_max_score"]["ratio"] is not None:
        assert p["mean_max_score"]["ratio"] == pytest.approx(
            by_name[p["world_model"]]["mean_max_score"] / by_name[p["simulator"]]["mean_max_score"])
    md = (tmp_path / "out" / "results.md").read_text()
    assert "score = max share in tray within the horizon, success = share in tray >= 0.9" in md
    assert "on mean max share in tray" in md and "IoU" not in md
    assert (tmp_path / "out" / "datagen.png").stat().st_size > 0
    cached = json.loads((work / "pilesweep" / "datagen" / "eval" / "pilesweep" / "expert.json").read_text())
    assert cached["key"]["env"] == "pilesweep" and len(cached["score_per_step"][0]) == 7


def test_takeover_stores_the_experts_part_from_the_state_the_learned_policy_left(learned, wm_path, tmp_path):
    """HG-DAgger's takes: a learned policy drives each candidate to its handover step (drawn
    from its seed), the expert takes over from there; only the expert's part is stored, from
    an unsolved frame to ``tail`` steps after success, and the same command records the same store."""
    kw = {"steps": 70, "seed": 300002, "accept_iou": 0.9, "tail": 3, "takeover": learned, "takeover_steps": (3, 12)}
    stats = record("pusht", tmp_path / "take.zarr", wm_path, **kw)
    store = EpisodeStore.open(tmp_path / "take.zarr")
    seeds, handovers = [300002, 300003], store.attrs["handover_steps"]
    assert stats.episodes == 2 and store.seeds == seeds
    assert handovers == [handover_step(s, (3, 12)) for s in seeds] == [8, 3]  # 3 cuts the policy's first chunk of 4
    assert (store.attrs["takeover"], store.attrs["takeover_steps"], store.attrs["takeover_sha256"]) == (
        str(learned), [3, 12], fingerprint(checkpoint_dir(learned)))
    policy = load_policy(learned)
    seed_sampling(seeds)  # the learned policy alone, its noise seeded as the recording seeds it
    alone = rollout(policy, "pusht", seeds, max(handovers), record=2, progress=False)
    for i, h in enumerate(handovers):
        ep = store.episode(i)
        np.testing.assert_array_equal(ep["img"][0], alone["frames"][i, h])  # the state the policy left
        np.testing.assert_array_equal(ep["state"][0], alone["agent_pos"][i, h])
        assert not np.array_equal(ep["img"][0], alone["frames"][i, 0])
        success = np.flatnonzero(ep["iou"] >= 0.9)
        assert ep["iou"][0] < 0.9 and len(ep["iou"]) == success[0] + 3
        expert = ScriptedBatch("expert")  # the stored actions: the expert's, started afresh at the handover
        replayed = [expert.predict_action({"image": ep["img"][t][None, None], "agent_pos": ep["state"][t][None, None]})
                    for t in range(len(ep["action"]))]
        np.testing.assert_array_equal(np.concatenate(replayed)[:, 0], ep["action"])
    record("pusht", tmp_path / "again.zarr", wm_path, **kw)
    again = EpisodeStore.open(tmp_path / "again.zarr")
    assert again.attrs["handover_steps"] == handovers and again.episode_ends.tolist() == store.episode_ends.tolist()
    for i in range(2):
        for k in store.keys:
            np.testing.assert_array_equal(again.episode(i)[k], store.episode(i)[k])


def test_a_take_that_starts_solved_is_discarded_in_either_env(learned, wm_path, tmp_path):
    """accept_iou 0: every frame succeeds, so every take starts solved and shows nothing."""
    for env in ("pusht", "world-model"):
        stats = record(env, tmp_path / f"{env}.zarr", wm_path, episodes=1, max_attempts=2, takeover=learned,
                       takeover_steps=(1, 3))
        store = EpisodeStore.open(tmp_path / f"{env}.zarr")
        assert (stats.episodes, stats.candidates, store.attrs["handover_steps"]) == (0, 2, []), env


def test_takeover_refuses_bad_steps_another_frame_size_and_another_stores_recipe(learned, wm_path, tmp_path):
    bad = tmp_path / "bad.zarr"
    for steps in ((5, 3), (0, 6), (-1, 2), (1, 2, 3), (1.0, 2)):
        with pytest.raises(ValueError, match=r"^takeover_steps must be two steps lo, hi with 0 <= lo <= hi < steps "
                                             rf"\(6\), got {re.escape(repr(steps))}\.$"):
            record("pusht", bad, wm_path, takeover=learned, takeover_steps=steps)
    with pytest.raises(ValueError, match="takeover_steps must be"):
        DemoRecipe(steps=10, takeover="run", takeover_steps=(2, 10))
    DemoRecipe(steps=10)  # without takeover, takeover_steps is not used
    with pytest.raises(ValueError, match=r"^takeover does not combine with dart_noise; got dart_noise=0.01, "
                                         r"expected 0\.$"):
        record("pusht", bad, wm_path, takeover=learned, takeover_steps=(1, 2), dart_noise=0.01)
    with pytest.raises(ValueError, match="takeover does not combine with dart_noise"):
        DemoRecipe(takeover="run", dart_noise=0.01)
    with pytest.raises(ValueError, match=rf"^takeover policy {re.escape(str(learned))} was trained on 64x64 frames; "
                                         "the store holds 96x96 ones.$"):
        record("pusht", bad, wm_path, takeover=learned, takeover_steps=(1, 2), image_size=96)
    assert not bad.exists()
    # a store is extended only with its own recipe's takes
    taken = tmp_path / "taken.zarr"
    record("pusht", taken, wm_path, episodes=1, max_attempts=1, takeover=learned, takeover_steps=(1, 2))
    with pytest.raises(ValueError, match=r"takeover_steps=\[1, 2\], not takeover_steps=\[1, 3\]; choose"):
        record("pusht", taken, wm_path, takeover=learned, takeover_steps=(1, 3))
    with pytest.raises(ValueError, match=rf"takeover='{re.escape(str(learned))}', takeover_sha256='[0-9a-f]{{16}}', "
                                         r"takeover_steps=\[1, 2\], not takeover=None, takeover_sha256=None, "
                                         r"takeover_steps=None; choose another store.$"):
        record("pusht", taken, wm_path)
    plain = tmp_path / "plain.zarr"  # and a store without takeover, one written before takeovers too, likewise
    record("pusht", plain, wm_path, episodes=1, batch=1)
    with pytest.raises(ValueError, match="takeover=None, takeover_sha256=None, takeover_steps=None, not takeover="):
        record("pusht", plain, wm_path, takeover=learned, takeover_steps=(1, 2))
    attrs = zarr.open_group(plain, mode="r+").attrs
    for k in ("takeover", "takeover_sha256", "takeover_steps"):
        del attrs[k]
    assert record("pusht", plain, wm_path, episodes=2, batch=1).added == 1


def test_the_demos_command_records_what_record_demos_does(learned, tmp_path, capsys):
    """``iwsim demos`` is :func:`record_demos` on the command line: the same takeover takes
    (HG-DAgger, in MuJoCo) give the same store, and a rerun resumes it (adds nothing)."""
    kw = {"tail": 3, "batch": 2, "takeover": learned, "takeover_steps": (3, 12)}  # two kept, as above
    lib = record_demos("pusht", tmp_path / "lib.zarr", 2, 70, 300002, accept_iou=0.9, progress=False, **kw)
    cli = tmp_path / "cli.zarr"
    # the command at the library call's thread count (the policy's float32
    # sums differ in their last bit between thread counts on some CPUs)
    argv = ["demos", "--task", "pusht", "--episodes", "2", "--steps", "70", "--seed", "300002", "--tail", "3",
            "--batch", "2", "--takeover", str(learned), "--takeover-steps", "3,12", "--out", str(cli), "--no-progress",
            "--threads", str(torch.get_num_threads())]
    assert main(argv) == 0  # without --accept-iou: the task's success score, 0.9
    assert capsys.readouterr().out.strip().startswith(f"{cli}: 2/2 episodes kept of {lib.candidates} candidates")
    a, b = EpisodeStore.open(cli), EpisodeStore.open(lib.path)
    assert a.episode_ends.tolist() == b.episode_ends.tolist() and a.n_episodes == 2
    for i in range(2):
        for k in ("img", "action", "state", "target", "iou"):
            np.testing.assert_array_equal(a.episode(i)[k], b.episode(i)[k])
    for k in ("takeover", "takeover_sha256", "takeover_steps", "handover_steps", "accept_iou", "tail_steps", "seeds",
              "candidate_max_iou", "candidates_tried"):
        assert a.attrs[k] == b.attrs[k], k
    assert a.attrs["takeover_steps"] == [3, 12] and a.attrs["accept_iou"] == 0.9
    assert main(argv) == 0
    assert capsys.readouterr().out.strip().endswith("this run added 0 of 0 tried")


def test_the_demos_command_refuses_bad_input_in_one_line(learned, wm_path, tmp_path, capsys):
    """Bad flags are one line each and create no store; a store recorded otherwise (here
    another --accept-iou) is refused and left as it was."""
    out = tmp_path / "d.zarr"
    base = ["demos", "--episodes", "1", "--steps", "20", "--out", str(out), "--no-progress"]
    policy = ["--takeover", str(learned)]
    for flags, message in (
            ([*policy, "--takeover-steps", "5"], "--takeover-steps takes LO,HI, two steps, got '5'."),
            ([*policy, "--takeover-steps", "a,b"], "--takeover-steps takes LO,HI, two steps, got 'a,b'."),
            ([*policy, "--takeover-steps", "10,5"], "takeover_steps must be two steps lo, hi with 0 <= lo <= hi < "
                                                    "steps (20), got (10, 5)."),
            (["--takeover-steps", "1,5"], "--takeover-steps applies to --takeover"),
            (["--takeover", str(tmp_path / "no-run"), "--takeover-steps", "1,5"], "is not a policy checkpoint"),
            (["--world-model", str(wm_path), "--task", "pilesweep"],
             f"world model {wm_path} is a world model of task 'pusht', not 'pilesweep'"),
            (["--world-model", str(wm_path), "--image-size", "96"], "--image-size applies to MuJoCo"),
            (["--task", "cube"], "unknown task 'cube'"),
            (["--demonstrator", "human"], "demonstrator must be one of expert, expert-wide, got 'human'."),
            (["--start", "upside-down"], "start must be one of random, goal-turned, got 'upside-down'."),
            (["--give-up-after", "0"], "give_up_after must be a positive integer")):
        assert main(base + flags) == 1, flags
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("iwsim: error: ") and message in err[0], (flags, err)
    assert not out.exists()
    # --tail 0 keeps whole takes; the store then takes only its own recipe's
    assert main([*base[:4], "6", "--out", str(out), "--accept-iou", "0", "--tail", "0", "--batch", "1",
                 "--no-progress"]) == 0
    capsys.readouterr()
    assert EpisodeStore.open(out).episode_ends.tolist() == [6]

    def files() -> dict[str, bytes]:
        return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*"))
                if p.is_file() and p.name != ".iwsim.lock"}

    before = files()
    assert main([*base[:4], "6", "--out", str(out), "--accept-iou", "0.5", "--tail", "0", "--no-progress"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("iwsim: error: ") and "accept_iou=0.0, not accept_iou=0.5" in err[0]
    assert files() == before and EpisodeStore.open(out).n_episodes == 1


def test_a_demos_run_killed_between_a_take_and_its_record_resumes_with_every_candidate_scored(wm_path, tmp_path,
                                                                                              monkeypatch):
    """Issue 65's smaller list: killed after appending a take but before recording the
    candidates' scores, a rerun left ``candidates_tried`` one longer than
    ``candidate_max_iou``. It now scores those candidates again (deterministic) without
    appending their takes twice, and ends as an uninterrupted run."""
    want = record("pusht", tmp_path / "whole.zarr", wm_path, episodes=3, accept_iou=0.2)
    real = EpisodeStore.update_attrs

    def killed(self, attrs):
        if "candidates_tried" in attrs:
            raise KeyboardInterrupt
        return real(self, attrs)

    monkeypatch.setattr(EpisodeStore, "update_attrs", killed)
    with pytest.raises(KeyboardInterrupt):
        record("pusht", tmp_path / "cut.zarr", wm_path, episodes=3, accept_iou=0.2)
    monkeypatch.setattr(EpisodeStore, "update_attrs", real)
    assert EpisodeStore.open(tmp_path / "cut.zarr").n_episodes >= 1
    got = record("pusht", tmp_path / "cut.zarr", wm_path, episodes=3, accept_iou=0.2)
    a, b = EpisodeStore.open(tmp_path / "cut.zarr"), EpisodeStore.open(tmp_path / "whole.zarr")
    for k in ("candidates_tried", "candidate_max_iou", "seeds", "acceptance_rate"):
        assert a.attrs[k] == b.attrs[k], k
    assert len(a.attrs["candidate_max_iou"]) == a.attrs["candidates_tried"] == want.candidates == got.candidates
    assert a.episode_ends.tolist() == b.episode_ends.tolist()
    np.testing.assert_array_equal(a.array("img")[:], b.array("img")[:])
