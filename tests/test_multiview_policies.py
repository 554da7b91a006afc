"""Policies of several camera views (issue 68 item 4): Diffusion Policy (an encoder per view)
and ACT (one backbone, every view's tokens) train on a store of two views and are evaluated
in MuJoCo rendering both cameras and in a world model of both views; one-view policies and
their shipped checkpoints are unchanged."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from iwsim.cli import main
from iwsim.core.errors import InputError
from iwsim.data.frames import read_frames
from iwsim.data.store import EpisodeStore
from iwsim.data.views import stack_views
from iwsim.envs import make_env
from iwsim.eval.policy import evaluate, policy_frames, rollout
from iwsim.policies.common import random_shift
from iwsim.policies.data import PolicyData, Source
from iwsim.policies.factory import load_policy
from tests.test_cameras import two_view_model  # noqa: F401

pytestmark = pytest.mark.usefixtures("one_thread")

VIEWS = ("top", "side")


@pytest.fixture(scope="module")
def views_store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """3 short T-push expert episodes recorded from the top and side cameras."""
    store = tmp_path_factory.mktemp("mv") / "expert.zarr"
    assert main(["collect", "--task", "pusht", "--policy", "expert", "--episodes", "3", "--steps", "12", "--workers",
                 "1", "--cameras", ",".join(VIEWS), "--out", str(store), "--no-progress"]) == 0
    return store


@pytest.fixture(scope="module")
def trained(views_store: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A tiny DP and a tiny ACT trained a few steps on the two-view store, as a user would."""
    root = tmp_path_factory.mktemp("mv_runs")
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for policy in ("dp", "act"):
            assert main(["train", "policy", "--policy", policy, "--preset", f"tiny-{policy}", "--data",
                         str(views_store), "--steps", "4", "--out", str(root / policy), "--no-progress"]) == 0
    finally:
        torch.set_num_threads(n)
    return {"dp": root / "dp", "act": root / "act"}


def two_view_obs(policy, seed: int = 0, b: int = 2) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"image": rng.integers(0, 256, (b, policy.obs_horizon, 64, 64, 3 * policy.views), dtype=np.uint8),
            "agent_pos": rng.uniform(-0.2, 0.2, (b, policy.obs_horizon, 4)).astype(np.float32)}


def test_the_policies_record_the_stores_views_and_build_a_network_for_them(trained):
    for kind, path in trained.items():
        config = json.loads((path / "config.json").read_text())
        assert config["model"]["cameras"] == list(VIEWS), kind
        policy = load_policy(path)
        assert policy.cameras == VIEWS and policy.views == 2
    names = set(load_policy(trained["dp"]).state_dict())
    # Diffusion Policy: an encoder per view, none shared (the paper's share_rgb_model=False)
    assert any(k.startswith("encoder.0.") for k in names) and any(k.startswith("encoder.1.") for k in names)
    assert not any(k.startswith("encoder.2.") for k in names)
    dp = load_policy(trained["dp"])
    a, b = dp.encoders
    assert a is not b and not torch.equal(a.net[0].weight, b.net[0].weight)
    # ACT: one backbone for every view, a learned embedding per view
    act = load_policy(trained["act"])
    assert act.view_pos.weight.shape == (2, act.cfg.dim)
    import dataclasses

    from iwsim.policies.act.model import ACTPolicy

    one = ACTPolicy(dataclasses.replace(act.cfg, cameras=("top",)), act.action_norm, act.state_norm)
    shapes = {k: v.shape for k, v in act.state_dict().items() if k != "view_pos.weight"}
    assert shapes == {k: v.shape for k, v in one.state_dict().items()}  # the same backbone, not one per view


def test_the_data_stacks_every_view_and_a_mixture_must_hold_the_same_views(views_store, play_store, tmp_path):
    data = PolicyData([Source(views_store, None)], 2, 8)
    store = EpisodeStore.open(views_store)
    assert data.cameras == VIEWS and data.img.shape[1:] == (64, 64, 6)
    np.testing.assert_array_equal(data.img.numpy(), read_frames(store, slice(0, data.n_frames)))
    top = PolicyData([Source(views_store, None)], 2, 8, cameras=("top",))  # a view of them, by name
    assert top.cameras == ("top",)
    np.testing.assert_array_equal(top.img.numpy(), data.img.numpy()[..., :3])
    side = PolicyData([Source(views_store, None)], 2, 8, cameras=("side", "top"))
    np.testing.assert_array_equal(side.img.numpy()[..., :3], data.img.numpy()[..., 3:])
    with pytest.raises(InputError, match=r"holds the camera views top; the policy sees top, side"):
        PolicyData([Source(views_store, None), Source(play_store, 1)], 2, 8)
    with pytest.raises(InputError, match=r"holds the camera views top, side; the policy sees top"):
        PolicyData([Source(play_store, 1), Source(views_store, None)], 2, 8)
    with pytest.raises(InputError, match="holds the camera views top, side; the policy sees wrist"):
        PolicyData([Source(views_store, None)], 2, 8, cameras=("wrist",))


def test_random_shift_moves_each_view_by_its_own_offsets():
    g = torch.Generator().manual_seed(0)
    image = torch.rand(3, 2, 6, 16, 16, generator=g)  # (B, To, 3V, H, W), V = 2
    offsets = torch.randint(0, 5, (2, 3 * 2), generator=g)  # window b's views at 2b, 2b + 1
    out = random_shift(image, 2, offsets, views=2)
    for v in range(2):
        one = random_shift(image[:, :, 3 * v:3 * v + 3], 2, offsets[:, v::2])
        torch.testing.assert_close(out[:, :, 3 * v:3 * v + 3], one, rtol=0, atol=0)
    same = torch.stack([offsets[:, ::2]] * 2, -1).flatten(1)  # equal offsets per view: one shift of all channels
    torch.testing.assert_close(random_shift(image, 2, same, views=2), random_shift(image, 2, offsets[:, ::2]))


def test_each_dp_encoder_sees_its_own_view_and_act_sees_both(trained):
    dp = load_policy(trained["dp"])
    obs = two_view_obs(dp)
    other = {**obs, "image": obs["image"].copy()}
    other["image"][..., 3:] = 255 - other["image"][..., 3:]  # only the side view changes
    f, s = dp.cfg.image_features, dp.state_dim
    with torch.no_grad():
        cond = [dp.condition(*_prepared(dp, o)).view(2, dp.obs_horizon, 2 * f + s) for o in (obs, other)]
    torch.testing.assert_close(cond[0][..., :f], cond[1][..., :f])  # the top view's features: unchanged
    assert (cond[0][..., f:2 * f] - cond[1][..., f:2 * f]).abs().max() > 1e-4  # the side view's: changed
    torch.testing.assert_close(cond[0][..., 2 * f:], cond[1][..., 2 * f:])  # agent_pos
    act = load_policy(trained["act"], temporal_ensemble=None)
    now = {k: v[:, -1:] for k, v in obs.items()}
    changed = {k: v[:, -1:] for k, v in other.items()}
    assert (act.predict_chunk(now) - act.predict_chunk(changed)).abs().max() > 1e-6
    top_changed = {**now, "image": now["image"].copy()}
    top_changed["image"][..., :3] = 255 - top_changed["image"][..., :3]
    assert (act.predict_chunk(now) - act.predict_chunk(top_changed)).abs().max() > 1e-6


def _prepared(policy, obs):
    from iwsim.policies.common import prepare_obs

    return prepare_obs(obs, policy.state_norm, policy.obs_horizon, policy.cameras)


@pytest.mark.parametrize("kind", ["dp", "act"])
def test_a_two_view_policy_runs_in_mujoco_rendering_both_cameras(trained, kind, tmp_path):
    policy = load_policy(trained[kind])
    torch.manual_seed(0)
    run = rollout(policy, "pusht", [100000, 100001], 3, image_size=64, record=1, progress=False)
    assert run["frames"].shape == (1, 4, 64, 64, 6) and run["action"].shape == (2, 3, 4)
    sim = make_env("pusht", 64, cameras=VIEWS)
    truth, _ = sim.reset(seed=100000)
    sim.close()
    np.testing.assert_array_equal(run["frames"][0, 0], stack_views([truth["pixels"][c] for c in VIEWS]))
    result = evaluate(policy, "pusht", episodes=2, seed=100000, steps=3, image_size=64, out=tmp_path / "eval",
                      videos=1, progress=False)
    assert len(result["episodes"]) == 2 and 0.0 <= result["mean_max_iou"] <= 1.0
    assert (tmp_path / "eval" / "episode_100000.mp4").stat().st_size > 0  # the views one above the other


@pytest.mark.parametrize("kind", ["dp", "act"])
def test_a_two_view_policy_runs_in_a_world_model_of_both_views(trained, two_view_model, kind):  # noqa: F811
    from iwsim.world_model import WorldModel

    wm = WorldModel.load(two_view_model["checkpoint"])
    policy = load_policy(trained[kind])
    torch.manual_seed(0)
    result = evaluate(policy, "world-model", episodes=2, seed=100000, steps=3, world_model=wm, image_size=64,
                      videos=0, progress=False)
    assert len(result["episodes"]) == 2 and 0.0 <= result["mean_max_iou"] <= 1.0
    one_view = WorldModel.load("checkpoints/pusht-64")
    with pytest.raises(InputError, match="the policy sees the camera views top, side; the world model sees top"):
        rollout(policy, "world-model", [0], 2, world_model=one_view, image_size=64, progress=False)
    shipped = load_policy("checkpoints/dp-pusht-64")  # and a one-view policy in the two-view model
    with pytest.raises(InputError, match="the policy sees the camera views top; the world model sees top, side"):
        rollout(shipped, "world-model", [0], 2, world_model=wm, image_size=64, progress=False)


def test_iwsim_eval_policy_runs_a_two_view_policy_in_the_two_view_world_model(trained, two_view_model,  # noqa: F811
                                                                             tmp_path, capsys):
    out = tmp_path / "wm_eval"
    assert main(["eval", "policy", "--checkpoint", str(trained["dp"]), "--env", "world-model", "--world-model",
                 str(two_view_model["checkpoint"]), "--episodes", "2", "--steps", "3", "--videos", "1", "--out",
                 str(out), "--no-progress"]) == 0
    assert json.loads((out / "results.json").read_text())["env"] == "world-model"
    assert (out / "episode_100000.mp4").stat().st_size > 0
    capsys.readouterr()
    assert main(["eval", "policy", "--checkpoint", str(trained["dp"]), "--env", "world-model", "--world-model",
                 "checkpoints/pusht-64", "--episodes", "1", "--steps", "2", "--videos", "0", "--out",
                 str(tmp_path / "bad"), "--no-progress"]) == 1
    err = capsys.readouterr().err
    assert ("the policy sees the camera views top, side; the world model sees top: evaluate it in a world model of "
            "the policy's views.\n") in err
    assert not (tmp_path / "bad" / "results.json").exists()


def test_views_that_do_not_match_the_policy_are_one_line_errors(trained):
    dp = load_policy(trained["dp"])
    one = {"image": np.zeros((1, 2, 64, 64, 3), np.uint8), "agent_pos": np.zeros((1, 2, 4), np.float32)}
    with pytest.raises(InputError, match=r"sees 2 camera view\(s\) \(top, side\).*got \(1, 2, 64, 64, 3\): 1 view"):
        dp.predict_action(one)
    floats = {**one, "image": torch.zeros(1, 2, 3, 64, 64)}
    with pytest.raises(InputError, match=r"images \(B, To, 6, H, W\) float.*1 view"):
        dp.predict_action(floats)
    shipped = load_policy("checkpoints/dp-pusht-64")
    two = {**one, "image": np.zeros((1, 2, 64, 64, 6), np.uint8)}
    with pytest.raises(InputError, match=r"sees 1 camera view\(s\) \(top\).*got \(1, 2, 64, 64, 6\): 2 view"):
        shipped.predict_action(two)
    act = load_policy(trained["act"])
    with pytest.raises(InputError, match=r"sees 2 camera view\(s\) \(top, side\)"):
        act.predict_action({k: v[:, -1:] for k, v in one.items()})
    frame = np.zeros((1, 64, 64, 3), np.uint8)
    with pytest.raises(InputError, match="sees the camera views top, side; the environment gives one view"):
        policy_frames(frame, VIEWS)
    with pytest.raises(InputError, match="sees the camera view.s. top; the environment gives the views top, side"):
        policy_frames({"top": frame, "side": frame}, ("top",))
    with pytest.raises(InputError, match="top, wrist; the environment gives the views top, side"):
        policy_frames({"top": frame, "side": frame}, ("top", "wrist"))
    stacked = policy_frames({"side": frame + 1, "top": frame}, VIEWS)  # in the policy's order
    assert stacked.shape == (1, 64, 64, 6) and stacked[..., :3].max() == 0 and stacked[..., 3:].min() == 1
    assert policy_frames({"top": frame, "side": frame + 1}, None) is frame  # a scripted policy: the first view


# The shipped one-view checkpoints, as the code before views (git HEAD 028bc8a) loads
# and runs them: the sha256 of their parameters' names and shapes, and their first actions
# for a fixed observation (DP: DDIM from a seeded generator; ACT: the chunk, z = 0).
SHIPPED = {
    "dp-pusht-64": ("1c81b56135f1e344", 169, [[-0.007726, 0.135864, 0.006583, -0.015865],
                                              [-0.009604, 0.150371, -0.009713, -0.02563],
                                              [-0.011617, 0.15838, -0.020072, -0.036513]]),
    "act-pusht-64": ("f123eefb90fafb38", 119, [[0.039702, 0.034646, 0.104934, 0.087962],
                                               [0.041369, 0.040301, 0.101732, 0.083833],
                                               [0.043322, 0.04247, 0.096983, 0.0802]]),
}


@pytest.mark.parametrize("name", sorted(SHIPPED))
def test_a_shipped_one_view_checkpoint_loads_and_acts_as_before(name):
    signature, count, expected = SHIPPED[name]
    policy = load_policy(f"checkpoints/{name}")
    assert policy.cameras == ("top",) and policy.views == 1
    state = policy.state_dict()
    assert len(state) == count
    names = repr([(k, tuple(v.shape)) for k, v in state.items()]).encode()
    assert hashlib.sha256(names).hexdigest()[:16] == signature
    to = policy.obs_horizon
    obs = {"image": np.random.default_rng(68).integers(0, 256, (1, to, 64, 64, 3), dtype=np.uint8),
           "agent_pos": np.random.default_rng(69).uniform(-0.2, 0.2, (1, to, 4)).astype(np.float32)}
    if name.startswith("dp"):
        out = policy.predict_action(obs, torch.Generator().manual_seed(0))
    else:
        out = policy.predict_chunk(obs).numpy()
    np.testing.assert_allclose(out[0, :3], expected, atol=1e-5)


def test_collect_records_a_two_view_policys_episodes_from_the_first_view(trained, tmp_path):
    out = tmp_path / "rollouts.zarr"
    assert main(["collect", "--task", "pusht", "--policy", str(trained["dp"]), "--episodes", "1", "--steps", "3",
                 "--out", str(out), "--no-progress"]) == 0
    store = EpisodeStore.open(out)
    assert store.attrs["cameras"] == ["top"] and store.episode(0)["img"].shape == (3, 64, 64, 3)


# -- the studies on a two-view world model (item 4) ---------------------------------------------------------


@pytest.mark.slow
def test_the_policy_eval_study_on_a_two_view_model_trains_and_scores_two_view_policies(two_view_model,  # noqa: F811
                                                                                         tmp_path, capsys):
    """The study takes its views from the world model: the simulator expert's takes are
    recorded by both cameras (a store beside the one-view one), every learned policy sees
    both views, and each is scored in MuJoCo rendering them and in the model."""
    out, work = tmp_path / "out", tmp_path / "work"
    assert main(["experiment", "policy-eval", "--preset", "tiny", "--world-model", str(two_view_model["checkpoint"]),
                 "--out", str(out), "--work", str(work), "--no-progress", "--jobs", "1"]) == 0
    assert "Pearson r" in capsys.readouterr().out
    report = json.loads((out / "results.json").read_text())
    demos = work / "demos" / "sim_expert_top_side.zarr"
    assert report["scale"]["demos"]["path"] == str(demos) and report["scale"]["demos"]["cameras"] == list(VIEWS)
    assert not (work / "demos" / "sim_expert.zarr").exists()
    store = EpisodeStore.open(demos)
    assert list(store.attrs["cameras"]) == list(VIEWS) and {"img", "img_side"} <= set(store.keys)
    learned = [p for p in report["policies"] if p["kind"] != "scripted"]
    assert len(learned) == 4 and all(load_policy(p["source"]).cameras == VIEWS for p in learned)
    for p in report["policies"]:
        assert len(p["pusht"]["max_iou"]) == len(p["world-model"]["max_iou"]) == 2
    assert "seeing the camera views top, side" in (out / "results.md").read_text()


def test_a_study_refuses_demonstrations_of_other_views_than_its_model(two_view_model, tmp_path,  # noqa: F811
                                                                       capsys):
    one_view = tmp_path / "top.zarr"
    assert main(["collect", "--task", "pusht", "--policy", "expert", "--episodes", "2", "--steps", "6", "--workers",
                 "1", "--out", str(one_view), "--no-progress"]) == 0
    assert main(["experiment", "policy-eval", "--preset", "tiny", "--world-model", str(two_view_model["checkpoint"]),
                 "--demos", str(one_view), "--out", str(tmp_path / "out"), "--work", str(tmp_path / "work"),
                 "--no-progress"]) == 1
    err = capsys.readouterr().err.strip()
    assert "holds the camera view(s) top; the world model sees top,side" in err and "\n" not in err
    assert "--cameras top,side" in err and not (tmp_path / "out").exists()


def test_the_datagen_study_on_a_two_view_model_mixes_takes_of_both_views(two_view_model, tmp_path):  # noqa: F811
    """Demonstrations recorded in a two-view model and in MuJoCo by both cameras mix into one
    policy's data; the policies are scored in MuJoCo rendering both cameras."""
    out, work = tmp_path / "out", tmp_path / "work"
    assert main(["experiment", "datagen", "--preset", "tiny", "--world-model", str(two_view_model["checkpoint"]),
                 "--out", str(out), "--work", str(work), "--jobs", "1", "--no-progress"]) == 0
    r = json.loads((out / "results.json").read_text())
    assert r["scale"]["cameras"] == list(VIEWS)
    assert "seeing the camera views top, side" in (out / "results.md").read_text()
    for run in r["runs"]:
        stores = [EpisodeStore.open(d["store"]) for d in run["data"]]
        assert all(list(s.attrs["cameras"]) == list(VIEWS) for s in stores)
        assert load_policy(run["run"]).cameras == VIEWS and len(run["episodes"]) == 2
    assert any(run["n_wm"] and run["n_sim"] for run in r["runs"])  # a mixture of both sources
