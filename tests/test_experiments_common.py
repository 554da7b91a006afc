"""What the two studies share: policy trainings side by side (resumed, never redone) and
closed-loop evaluations cached by what they evaluated."""

import dataclasses
import json
import shutil

import numpy as np
import pytest

from iwsim.core.errors import InputError
from iwsim.experiments.common import PolicyRun, checkpoints, evaluate_policies, train_runs
from iwsim.policies.scripted import ScriptedConfig

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.mark.slow
def test_runs_train_side_by_side_and_are_not_redone(play_store, tmp_path):
    runs = [PolicyRun("a", "dp", ((str(play_store), 2),), steps=4, preset="tiny-dp", checkpoint_every=2),
            PolicyRun("b", "act", ((str(play_store), None),), steps=2, preset="tiny-act")]
    dirs = train_runs(runs, tmp_path, jobs=2, progress=False)
    assert dirs == {"a": tmp_path / "a", "b": tmp_path / "b"}
    assert sorted(checkpoints(dirs["a"])) == [2, 4] and sorted(checkpoints(dirs["b"])) == [2]
    assert json.loads((dirs["a"] / "config.json").read_text())["episodes_used"] == {str(play_store): 2}
    stamp = (dirs["a"] / "metrics.jsonl").stat().st_mtime_ns
    train_runs(runs[:1], tmp_path, progress=False)  # finished: nothing is trained again
    assert (dirs["a"] / "metrics.jsonl").stat().st_mtime_ns == stamp
    # saving more or less often is the same training: finished, and a longer one resumes
    train_runs([dataclasses.replace(runs[0], checkpoint_every=1)], tmp_path, progress=False)
    assert (dirs["a"] / "metrics.jsonl").stat().st_mtime_ns == stamp
    train_runs([dataclasses.replace(runs[0], checkpoint_every=1, steps=5)], tmp_path, progress=False)
    assert sorted(checkpoints(dirs["a"])) == [2, 4, 5]
    # another training under the same name is not taken for the finished one
    other = dataclasses.replace(runs[0], seed=1)
    with pytest.raises(InputError, match="different config"):
        train_runs([other], tmp_path, progress=False)


def test_bad_runs_are_refused_before_training(tmp_path):
    with pytest.raises(InputError, match="unique"):
        train_runs([PolicyRun("a", data=(("x", 1),)), PolicyRun("a", data=(("x", 1),))], tmp_path)
    with pytest.raises(InputError, match="no data"):
        train_runs([PolicyRun("a")], tmp_path)
    with pytest.raises(InputError, match="is a 'dp' policy"):
        PolicyRun("a", "act", preset="tiny-dp").stage_config()


def test_evaluations_are_cached_by_what_they_evaluated(tmp_path):
    expert, noisy = ScriptedConfig("expert"), ScriptedConfig("expert", noise=0.01)
    first = evaluate_policies({"expert": expert}, "pusht", seeds=[5, 6], steps=3, world_model=None, out=tmp_path,
                              progress=False)["expert"]
    path = tmp_path / "pusht" / "expert.json"
    assert [e["seed"] for e in first["episodes"]] == [5, 6] and len(first["iou_per_step"][0]) == 4
    stamp = path.stat().st_mtime_ns
    again = evaluate_policies({"expert": expert}, "pusht", seeds=[5, 6], steps=3, world_model=None, out=tmp_path,
                              progress=False)
    assert path.stat().st_mtime_ns == stamp and again["expert"] == json.loads(path.read_text())
    # Another policy under the same name, or other seeds, is evaluated anew.
    changed = evaluate_policies({"expert": noisy}, "pusht", seeds=[5, 6], steps=3, world_model=None, out=tmp_path,
                                progress=False)["expert"]
    assert changed["key"]["policy"]["noise"] == 0.01 and path.stat().st_mtime_ns != stamp
    with pytest.raises(InputError, match="world-model checkpoint"):
        evaluate_policies({"expert": expert}, "world-model", seeds=[5], steps=3, world_model=None, out=tmp_path)


def test_evaluations_in_a_model_retrained_at_the_same_path_are_redone(tmp_path, one_thread):
    from tests.test_dynamics import tiny_world_model

    expert = {"expert": ScriptedConfig("expert")}
    tiny_world_model(0).save(tmp_path / "wm")
    first = evaluate_policies(expert, "world-model", seeds=[5], steps=2, world_model=tmp_path / "wm",
                              out=tmp_path / "eval", progress=False)["expert"]
    shutil.rmtree(tmp_path / "wm")
    tiny_world_model(1).save(tmp_path / "wm")
    second = evaluate_policies(expert, "world-model", seeds=[5], steps=2, world_model=tmp_path / "wm",
                               out=tmp_path / "eval", progress=False)["expert"]
    assert first["key"]["world_model_sha256"] != second["key"]["world_model_sha256"]


def test_stores_policies_and_models_are_known_by_content_not_path(play_store, tmp_path):
    """Issue 65 row 12: the same store, policy or world model reached by another path (a
    copy, another working directory) was another one: evaluated again, trained again, or
    refused as "a different config". Their identity is now what they hold."""
    from iwsim.data.store import EpisodeStore
    from iwsim.experiments.policy_eval import _store_tag
    from tests.test_dynamics import tiny_world_model

    moved = shutil.copytree(play_store, tmp_path / "elsewhere" / play_store.name)
    store = EpisodeStore.open(play_store)
    assert _store_tag(moved, 2) == _store_tag(play_store, 2) != _store_tag(play_store, 1)
    assert store.content_hash(2) != store.content_hash() or store.n_episodes == 2
    # a finished policy run is not trained again from the moved store, and trains on from it
    run = PolicyRun("a", "dp", ((str(play_store), 2),), steps=2, preset="tiny-dp", checkpoint_every=2)
    root = tmp_path / "runs"
    train_runs([run], root, progress=False)
    stamp = (root / "a" / "metrics.jsonl").stat().st_mtime_ns
    train_runs([dataclasses.replace(run, data=((str(moved), 2),))], root, progress=False)
    assert (root / "a" / "metrics.jsonl").stat().st_mtime_ns == stamp
    train_runs([dataclasses.replace(run, data=((str(moved), 2),), steps=4)], root, progress=False)
    assert sorted(checkpoints(root / "a")) == [2, 4]
    # other episodes are other data
    with pytest.raises(InputError, match="different config"):
        train_runs([dataclasses.replace(run, data=((str(moved), 1),), steps=4)], root, progress=False)
    # an evaluation of the same weights in the same model at other paths is reused
    tiny_world_model().save(tmp_path / "wm")
    policy = shutil.copytree(root / "a" / "checkpoints" / "00000004", tmp_path / "policy-copy")
    wm_copy = shutil.copytree(tmp_path / "wm", tmp_path / "elsewhere" / "wm")
    first = evaluate_policies({"dp": root / "a"}, "world-model", seeds=[5], steps=2, world_model=tmp_path / "wm",
                              out=tmp_path / "eval", progress=False)
    path = tmp_path / "eval" / "world-model" / "dp.json"
    stamp = path.stat().st_mtime_ns
    again = evaluate_policies({"dp": policy}, "world-model", seeds=[5], steps=2, world_model=wm_copy,
                              out=tmp_path / "eval", progress=False)
    assert path.stat().st_mtime_ns == stamp and again == first


def test_a_study_on_another_task_has_its_horizon_its_directories_and_its_policies(tmp_path):
    """Issue 45: the presets are written for T-push; on pile sweeping a study evaluates over
    its horizon, keeps apart from T-push's work, and its scripted policies are its own."""
    from iwsim.envs.registry import get_task
    from iwsim.experiments.common import STUDY, on_task, study_dir, study_task
    from iwsim.experiments.datagen import PRESETS as DATAGEN
    from iwsim.experiments.policy_eval import PRESETS as POLICY_EVAL
    from iwsim.policies.scripted import ScriptedBatch

    pile = get_task("pilesweep")
    for presets in (DATAGEN, POLICY_EVAL):
        assert on_task(presets["default"], pile).steps == pile.horizon == 200
        assert on_task(presets["tiny"], pile).steps == presets["tiny"].steps  # a short preset keeps its own
        assert on_task(presets["default"], STUDY) == presets["default"]
    assert study_dir(tmp_path, STUDY) == tmp_path and study_dir(tmp_path, pile) == tmp_path / "pilesweep"
    with pytest.raises(InputError, match="unknown task 'nowhere'"):
        study_task("nowhere")
    with pytest.raises(InputError, match="task 'pilesweep' has no scripted policy 'expert-wide'"):
        ScriptedBatch("expert-wide", "pilesweep")
    with pytest.raises(InputError, match="pile sweeping has many"):
        ScriptedBatch("expert", "pilesweep", miss=0.01).predict_action(
            {"image": np.zeros((1, 1, 64, 64, 3), np.uint8), "agent_pos": np.zeros((1, 1, 4), np.float32)})
    result = evaluate_policies({"expert": ScriptedConfig("expert")}, "pilesweep", seeds=[5, 6], steps=3,
                               world_model=None, out=tmp_path, progress=False)["expert"]
    assert [e["seed"] for e in result["episodes"]] == [5, 6] and len(result["score_per_step"][0]) == 4
    assert result["mean_max_score"] == pytest.approx(np.mean(np.max(result["score_per_step"], 1)), abs=1e-4)
    assert (tmp_path / "pilesweep" / "expert.json").is_file()


def test_jobs_run_on_one_thread_in_this_process_too():
    """A study's job gets one torch thread whether it runs in a pool or here (``jobs`` 1, or
    a lone job): its result must not depend on how many jobs ran beside it."""
    import torch

    from iwsim.experiments.common import _in_parallel

    torch.set_num_threads(2)  # the one_thread fixture restores the caller's count after the test
    assert _in_parallel(torch.get_num_threads, [(), ()], 1, "threads", False) == [1, 1]
    assert _in_parallel(torch.get_num_threads, [()], 2, "threads", False) == [1]
    assert torch.get_num_threads() == 2


def test_the_studies_find_the_shipped_model_from_any_directory(tmp_path, monkeypatch):
    """Issue 65 row 13: outside the checkout a study said "world model checkpoints/pusht-64
    is not a checkpoint directory", where demo, eval and play found it."""
    from iwsim.experiments.common import check_study_model, fingerprint

    here = fingerprint("checkpoints/pusht-64")
    monkeypatch.chdir(tmp_path)
    check_study_model("checkpoints/pusht-64")
    assert fingerprint("checkpoints/pusht-64") == here


def test_a_state_models_fingerprint_changes_with_its_observation_alone(tmp_path, monkeypatch):
    """The environment's agent_pos changed for the models that predict the robot's state
    only: their cached results go, the others' stay."""
    import shutil

    from iwsim.core.checkpoint import load_json, write_json_atomic
    from iwsim.experiments import common

    plain = tmp_path / "plain"
    shutil.copytree("checkpoints/pusht-64", plain)
    state = tmp_path / "state"
    shutil.copytree(plain, state)
    config = load_json(state / "config.json")
    config["stage2"]["dynamics"]["state_dim"] = 4
    write_json_atomic(state / "config.json", config)
    before = {p: common.fingerprint(p) for p in (plain, state)}
    monkeypatch.setattr(common, "STATE_OBSERVATION_VERSION", common.STATE_OBSERVATION_VERSION + 1)
    assert common.fingerprint(plain) == before[plain] and common.fingerprint(state) != before[state]
