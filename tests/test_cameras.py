"""Several cameras in the ground truth (issue 68 item 1): the tabletop tasks' side view, the
observation's per-view pixels, stores that record every view and their refusals."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

from iwsim.cli import main
from iwsim.core.errors import InputError
from iwsim.data.store import EpisodeStore
from iwsim.data.views import store_cameras, view_keys
from iwsim.envs import make_env
from iwsim.envs.collect import collect
from iwsim.envs.pusht.scripted import record_episode


@pytest.mark.parametrize("task", ["pusht", "pilesweep"])
def test_two_cameras_give_a_frame_per_view_and_the_top_view_unchanged(task):
    one, two = make_env(task, 64), make_env(task, 64, cameras=("top", "side"))
    try:
        o1, _ = one.reset(seed=5)
        o2, _ = two.reset(seed=5)
        assert isinstance(two.observation_space["pixels"], gym.spaces.Dict)
        assert two.observation_space.contains(o2)
        assert list(o2["pixels"]) == ["top", "side"]
        np.testing.assert_array_equal(o2["pixels"]["top"], o1["pixels"])  # the side view changes nothing
        side = o2["pixels"]["side"]
        assert side.shape == (64, 64, 3) and side.dtype == np.uint8
        assert not np.array_equal(side, o1["pixels"])  # another view of the same scene
        a = np.array([0.05, 0.05, -0.05, -0.05], np.float32)
        s1, s2 = one.step(a)[0], two.step(a)[0]
        np.testing.assert_array_equal(s2["pixels"]["top"], s1["pixels"])
    finally:
        one.close()
        two.close()


def test_the_side_view_sees_a_pusher_move():
    env = make_env("pusht", 64, cameras=("top", "side"))
    try:
        env.reset(seed=1, options={"reset_to_state": [-0.15, -0.15, 0.15, 0.15, 0.0, 0.0, 0.0]})
        before = env.step(np.array([-0.15, -0.15, 0.15, 0.15]))[0]["pixels"]["side"]
        for _ in range(10):
            after = env.step(np.array([-0.15, 0.05, 0.15, 0.15]))[0]["pixels"]["side"]
        changed = np.any(before != after, axis=-1)
        assert changed.any()
        rows = np.nonzero(changed.any(axis=1))[0]
        assert rows.min() < 64 and rows.max() >= 0
        # the left pusher moved along +y (away from the side camera): only the image's left half changed
        cols = np.nonzero(changed.any(axis=0))[0]
        assert cols.max() < 40
    finally:
        env.close()


@pytest.mark.parametrize("cameras, match", [
    (("side", "top"), "first camera must be 'top'"),
    (("top", "wrist"), "not a camera of this task"),
    (("top", "top"), "distinct"),
    ("top", "a tuple of camera names"),
    ((), "at least one"),
])
def test_bad_cameras_are_refused(cameras, match):
    with pytest.raises(InputError, match=match):
        make_env("pusht", 64, cameras=cameras)


def test_an_episode_records_every_view_and_the_first_is_unchanged():
    one = record_episode("pusht", "play", 7, 6, 64)
    two = record_episode("pusht", "play", 7, 6, 64, cameras=("top", "side"))
    assert set(two) == set(one) | {"img_side"}
    for k in one:
        np.testing.assert_array_equal(two[k], one[k], err_msg=k)
    assert two["img_side"].shape == one["img"].shape and two["img_side"].dtype == np.uint8


def test_collect_with_two_cameras_stores_them_and_appends_only_alike(tmp_path: Path):
    out = tmp_path / "two.zarr"
    assert main(["collect", "--task", "pilesweep", "--policy", "play", "--steps", "4", "--episodes", "1",
                 "--workers", "1", "--cameras", "top,side", "--out", str(out), "--no-progress"]) == 0
    s = EpisodeStore.open(out)
    assert store_cameras(s.attrs, s.keys) == ("top", "side")
    assert view_keys(store_cameras(s.attrs)) == {"top": "img", "side": "img_side"}
    assert s.episode(0)["img_side"].shape == (4, 64, 64, 3)
    with pytest.raises(InputError, match="cameras"):  # one more episode, but of the top view only
        collect("pilesweep", "play", 2, out=out, steps=4, image_size=64, progress=False)
    collect("pilesweep", "play", 2, out=out, steps=4, image_size=64, progress=False, cameras=("top", "side"))
    assert EpisodeStore.open(out).n_episodes == 2


def test_a_store_collected_before_cameras_existed_appends_with_the_top_view(tmp_path: Path):
    out = tmp_path / "old.zarr"
    collect("pusht", "play", 1, out=out, steps=3, image_size=64, progress=False)
    attrs = json.loads((out / ".zattrs").read_text())  # as a store written before the attribute existed
    del attrs["cameras"]
    (out / ".zattrs").write_text(json.dumps(attrs))
    assert "cameras" not in EpisodeStore.open(out).attrs
    collect("pusht", "play", 2, out=out, steps=3, image_size=64, progress=False)
    assert EpisodeStore.open(out).n_episodes == 2
    with pytest.raises(InputError, match="cameras"):
        collect("pusht", "play", 3, out=out, steps=3, image_size=64, progress=False, cameras=("top", "side"))


@pytest.mark.parametrize("flag, match", [("side,top", "first camera must be 'top'"),
                                         ("top,wrist", "no camera 'wrist'"), ("top,", "camera name ''")])
def test_collect_refuses_bad_cameras_before_writing(tmp_path: Path, flag, match, capsys):
    out = tmp_path / "x.zarr"
    assert main(["collect", "--task", "pusht", "--episodes", "1", "--steps", "2", "--cameras", flag,
                 "--out", str(out)]) == 1
    assert match in capsys.readouterr().err
    assert not out.exists()


# -- one world model over every view (item 3) ---------------------------------------------------------------


@pytest.fixture(scope="module")
def two_view_model(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A tiny T-push world model of the top and side views, made as a user would."""
    from conftest import train_tiny_world_model

    root = tmp_path_factory.mktemp("two_view")
    store = root / "two.zarr"
    wm = train_tiny_world_model(store, root, ["collect", "--task", "pusht", "--policy", "play", "--episodes", "3",
                                              "--steps", "12", "--workers", "1", "--cameras", "top,side", "--out",
                                              str(store), "--no-progress"])
    return {"store": store, "checkpoint": wm, "run": root / "dyn"}


def test_a_two_view_model_sees_both_views_in_one_latent(two_view_model):
    from iwsim.data.frames import read_frames, to_model
    from iwsim.data.views import unstack_views
    from iwsim.world_model import WorldModel

    wm = WorldModel.load(two_view_model["checkpoint"])
    assert wm.cameras == ("top", "side")
    c, h, w = wm.codec.latent_shape
    assert wm.latent_shape == (2 * c, h, w)  # the views' latents stacked along the channels
    frames = read_frames(EpisodeStore.open(two_view_model["store"]), slice(0, 2))
    assert frames.shape == (2, 64, 64, 6)
    z = wm.encode(frames)
    # each view is encoded alone by the one codec: the top view's channels are the top frame's latent
    top, side = unstack_views(frames, 2)
    with torch.inference_mode():
        torch.testing.assert_close(z[:, :c], wm.codec.encode(to_model(top)))
        torch.testing.assert_close(z[:, c:], wm.codec.encode(to_model(side)))
    assert wm.decode(z).shape == (2, 64, 64, 6)
    wm.reset(frames, seed=0)
    assert wm.step(np.zeros((2, 4), np.float32)).shape == (2, 64, 64, 6)
    with pytest.raises(InputError, match="2 views stacked"):
        wm.reset(top)


def test_the_world_model_env_gives_pixels_per_view_from_mujocos_start(two_view_model):
    from iwsim.world_model.env import WorldModelEnv, WorldModelVectorEnv

    env = WorldModelEnv(two_view_model["checkpoint"])
    obs, _ = env.reset(seed=11)
    assert env.observation_space.contains(obs) and list(obs["pixels"]) == ["top", "side"]
    sim = make_env("pusht", 64, cameras=("top", "side"))
    truth, _ = sim.reset(seed=11)
    sim.close()
    for view in ("top", "side"):  # the first frame is MuJoCo's, every view of it
        np.testing.assert_array_equal(obs["pixels"][view], truth["pixels"][view])
    obs, reward, _, _, info = env.step(np.zeros(4))
    assert env.observation_space.contains(obs) and 0.0 <= reward <= 1.0 and "target" in info
    assert env.render().shape == (128, 64, 3)  # the views one above the other
    obs, _ = env.reset(options={"frame": truth["pixels"]})
    np.testing.assert_array_equal(obs["pixels"]["side"], truth["pixels"]["side"])
    with pytest.raises(InputError, match="views"):
        env.reset(options={"frame": {"top": truth["pixels"]["top"]}})
    vec = WorldModelVectorEnv(2, two_view_model["checkpoint"], max_episode_steps=3)
    obs, _ = vec.reset(seed=0)
    assert vec.observation_space.contains(obs) and obs["pixels"]["side"].shape == (2, 64, 64, 3)
    obs, *_ = vec.step(np.zeros((2, 4)))
    assert vec.observation_space.contains(obs)


def test_a_store_of_other_views_is_refused_for_fine_tuning_and_starts(two_view_model, tmp_path: Path):
    from iwsim.world_model.env import WorldModelEnv

    one = tmp_path / "one.zarr"
    collect("pusht", "play", 2, out=one, steps=12, image_size=64, progress=False)
    with pytest.raises(InputError, match="views"):
        WorldModelEnv(two_view_model["checkpoint"], store=one, reset_source="store")
    assert main(["train", "dynamics", "--data", str(one), "--init", str(two_view_model["checkpoint"]),
                 "--preset", "tiny", "--out", str(tmp_path / "ft"), "--no-progress"]) == 1


def test_a_one_view_model_is_unchanged_by_views():
    from iwsim.world_model import WorldModel

    wm = WorldModel.load("checkpoints/pusht-64")
    assert wm.cameras == ("top",) and wm.latent_shape == wm.codec.latent_shape


# -- play on every view (item 4) ------------------------------------------------------------------------------


def test_play_shows_and_records_every_view_beside_mujocos(two_view_model, tmp_path: Path):
    from iwsim.play import protocol as proto
    from iwsim.play.engine import Engine, PlayConfig
    from iwsim.world_model import WorldModel

    store = tmp_path / "takes.zarr"
    eng = Engine(WorldModel.load(two_view_model["checkpoint"]), PlayConfig(record_to=store))
    s = eng.open()
    header, views = proto.unpack_frame(eng.frame_message(s))
    assert header["views"] == ["world_model", "world_model:side"] and len(views) == 2
    eng.handle(s, proto.SideBySide(True))
    header, views = proto.unpack_frame(eng.frame_message(s))
    assert header["views"] == ["world_model", "world_model:side", "mujoco", "mujoco:side"]
    sim = make_env("pusht", 64, cameras=("top", "side"))
    truth, _ = sim.reset(seed=s.seed)
    np.testing.assert_array_equal(views[1], truth["pixels"]["side"])  # the model starts from MuJoCo's views
    np.testing.assert_array_equal(views[3], truth["pixels"]["side"])
    eng.handle(s, proto.Command("record"))
    shown = []
    for t in range(3):
        eng.handle(s, proto.Action(t, (0.05, 0.05, -0.05, -0.05)))
        shown.append(s.frame.copy())
        eng.tick()
        truth, *_ = sim.step(np.array([0.05, 0.05, -0.05, -0.05], np.float32))
    sim.close()
    np.testing.assert_array_equal(s.twin_frame[..., 3:], truth["pixels"]["side"])  # the twin, every view
    eng.handle(s, proto.Command("save"))
    eng.recorder.close()
    back = EpisodeStore.open(store)
    assert store_cameras(back.attrs, back.keys) == ("top", "side")
    ep = back.episode(0)
    np.testing.assert_array_equal(ep["img"], np.stack(shown)[..., :3])
    np.testing.assert_array_equal(ep["img_side"], np.stack(shown)[..., 3:])
    eng.shutdown()
    one = tmp_path / "one.zarr"  # a store of one view takes no two-view takes
    collect("pusht", "play", 1, out=one, steps=3, image_size=64, progress=False)
    with pytest.raises(InputError, match="cameras"):
        Engine(WorldModel.load(two_view_model["checkpoint"]), PlayConfig(record_to=one))


@pytest.mark.browser
def test_the_play_page_draws_a_canvas_per_view(two_view_model):
    from iwsim.play.engine import Engine, PlayConfig
    from iwsim.world_model import WorldModel
    from tests.test_play_browser import CHROMIUM, served_page, wait

    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing; `make test` installs Debian's chromium package.")
    from playwright.sync_api import sync_playwright

    from tests.test_play_browser import FLAGS

    eng = Engine(WorldModel.load(two_view_model["checkpoint"]), PlayConfig())
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=FLAGS, headless=True)
        try:
            with served_page(browser, eng) as page:
                side = 'canvas[data-view="world_model:side"]'
                wait(page, f"document.querySelector('{side}') !== null")
                before = page.eval_on_selector(side, "c => c.toDataURL()")
                assert before != page.eval_on_selector("#wm", "c => c.toDataURL()")  # another view
                page.keyboard.down("w")
                wait(page, f"document.querySelector('{side}').toDataURL() !== {before!r}")
                page.keyboard.up("w")
                page.keyboard.press("b")  # side by side: MuJoCo's side view appears too
                wait(page, "document.querySelector('canvas[data-view=\"mujoco:side\"]') !== null && "
                           "!document.querySelector('canvas[data-view=\"mujoco:side\"]').parentElement.hidden")
        finally:
            browser.close()
    eng.shutdown()


# -- the block's pose from each view (item 5) ------------------------------------------------------------------


def test_the_side_view_reads_the_blocks_pose_by_the_cameras_geometry():
    from iwsim.envs.pusht import geometry as geo
    from iwsim.envs.pusht.pixels import estimate_block_pose_side
    from iwsim.envs.tabletop.scene import side_project

    env = make_env("pusht", 64, cameras=("top", "side"))
    errors = []
    try:
        centre = side_project(np.zeros(3), 64)  # the camera aims at the table's centre
        np.testing.assert_allclose(centre, [31.5, 31.5], atol=1e-9)
        for seed in range(12):
            state = env.unwrapped.sample_state(np.random.default_rng(seed))
            state[:4] = [-0.2, -0.2, 0.2, -0.2]  # the pushers out of the block's way
            obs, info = env.reset(options={"reset_to_state": state})
            est = estimate_block_pose_side(obs["pixels"]["side"])
            assert est.found
            truth = info["block_pose"]
            errors.append((np.hypot(*(est.pose[:2] - truth[:2])), abs(geo.wrap_angle(est.pose[2] - truth[2]))))
    finally:
        env.close()
    err = np.median(np.array(errors), axis=0)
    assert err[0] < 0.002 and np.degrees(err[1]) < 1.0, err  # measured: ~1 mm, ~0.3 degrees


@pytest.mark.slow
def test_the_cross_view_bench_compares_one_model_of_both_views_with_two_of_one(two_view_model, tmp_path: Path):
    """``bench/cross_view.py`` on the tiny two-view model and a pair of single-view models
    (the shipped one for both views: the mechanics, no quality asserted); the readers on
    MuJoCo's own frames agree within a few mm."""
    import json
    import os
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    store, out = tmp_path / "eval.zarr", tmp_path / "out"
    collect("pusht", "play", 2, out=store, steps=8, image_size=64, seed=900, progress=False, cameras=("top", "side"))
    subprocess.run([sys.executable, str(root / "bench" / "cross_view.py"), "--models",
                    f"joint={two_view_model['checkpoint']}", "pair=checkpoints/pusht-64+checkpoints/pusht-64",
                    "--store", str(store), "--steps", "6", "--out", str(out)], check=True, capture_output=True,
                   env={**os.environ, "OMP_NUM_THREADS": "1"}, cwd=root)
    report = json.loads((out / "results.json").read_text())
    assert report["episodes"] == 2 and set(report["models"]) == {"joint", "pair"}
    assert report["models"]["joint"]["kind"] == "joint" and report["models"]["pair"]["kind"] == "pair"
    assert report["mujoco"]["disagreement_mm"]["median"] < 3.0 and report["mujoco"]["top"]["no_block"] == 0
    for row in report["models"].values():
        assert len(row["disagreement_curve_mm"]) == 6 and 0 < row["top"]["psnr_db"] < 100
    assert (out / "disagreement_per_step.png").stat().st_size > 0
    assert "cross_view.py" in (out / "results.md").read_text()
    one = tmp_path / "one.zarr"  # a store of one view is refused in one line
    collect("pusht", "play", 1, out=one, steps=8, image_size=64, progress=False)
    bad = subprocess.run([sys.executable, str(root / "bench" / "cross_view.py"), "--models",
                          "pair=checkpoints/pusht-64", "--store", str(one), "--out", str(out)],
                         capture_output=True, text=True, cwd=root)
    assert bad.returncode == 2 and "top,side" in bad.stderr


def test_demo_and_open_loop_roll_out_every_view(two_view_model, tmp_path: Path):
    from iwsim.eval.rollout import against_mujoco, frame_scores, open_loop
    from iwsim.world_model import WorldModel

    wm = WorldModel.load(two_view_model["checkpoint"])
    result = open_loop(wm, EpisodeStore.open(two_view_model["store"]), [0, 1], 4)
    assert result.truth.shape == (2, 4, 64, 64, 6) and result.pred.shape == result.truth.shape
    top, _ = frame_scores(result.truth[..., :3], result.pred[..., :3])
    side, _ = frame_scores(result.truth[..., 3:], result.pred[..., 3:])
    np.testing.assert_allclose(result.psnr, (top + side) / 2, rtol=1e-5)  # the views' mean
    mj = against_mujoco(wm, 100000, 3)
    assert mj.truth.shape == (1, 3, 64, 64, 6) and mj.iou_true is not None
    out = tmp_path / "demo"
    assert main(["demo", "--checkpoint", str(two_view_model["checkpoint"]), "--steps", "3", "--out", str(out)]) == 0
    assert (out / "world_model_vs_mujoco.mp4").stat().st_size > 0


def test_one_view_of_a_two_view_store_imports_under_its_name(tmp_path: Path):
    from iwsim.data.formats import import_

    two = tmp_path / "two.zarr"
    collect("pusht", "play", 1, out=two, steps=3, image_size=64, progress=False, cameras=("top", "side"))
    src = EpisodeStore.open(two)
    for view, key in (("top", "img"), ("side", "img_side")):
        one = import_("zarr", two, tmp_path / f"{view}.zarr", camera=view, image_size=None, progress=False)
        assert store_cameras(one.attrs, one.keys) == (view,) and one.attrs["task"] == "pusht"
        np.testing.assert_array_equal(one.episode(0)["img"], src.episode(0)[key])


def test_demonstrations_in_a_two_view_model_record_every_view_scored_on_the_top_one(two_view_model, tmp_path: Path):
    from iwsim.envs.pusht.pixels import pixel_iou

    out = tmp_path / "demos.zarr"
    argv = ["demos", "--world-model", str(two_view_model["checkpoint"]), "--episodes", "2", "--steps", "4",
            "--accept-iou", "0", "--tail", "0", "--batch", "2", "--out", str(out), "--no-progress"]
    assert main(argv) == 0
    s = EpisodeStore.open(out)
    assert s.n_episodes == 2 and store_cameras(s.attrs, s.keys) == ("top", "side")
    ep = s.episode(0)
    assert ep["img"].shape == ep["img_side"].shape == (4, 64, 64, 3)
    assert not np.array_equal(ep["img"], ep["img_side"])
    np.testing.assert_allclose(ep["iou"], pixel_iou(ep["img"]), atol=1e-6)  # scored on the top view
    assert main([*argv[:4], "3", *argv[5:]]) == 0  # resumes
    assert EpisodeStore.open(out).n_episodes == 3


def test_demonstrations_in_mujoco_record_every_camera_asked_for(tmp_path: Path, capsys):
    from iwsim.envs.pusht.pixels import pixel_iou

    out = tmp_path / "demos.zarr"
    argv = ["demos", "--task", "pusht", "--cameras", "top,side", "--episodes", "1", "--steps", "3",
            "--accept-iou", "0", "--tail", "0", "--batch", "1", "--out", str(out), "--no-progress"]
    assert main(argv) == 0
    s = EpisodeStore.open(out)
    assert s.n_episodes == 1 and store_cameras(s.attrs, s.keys) == ("top", "side")
    ep = s.episode(0)
    assert ep["img"].shape == ep["img_side"].shape == (3, 64, 64, 3) and not np.array_equal(ep["img"], ep["img_side"])
    np.testing.assert_allclose(ep["iou"], pixel_iou(ep["img"]), atol=1e-6)  # scored on the top view
    one = tmp_path / "one.zarr"  # the same take with the top camera alone: the same top frames
    assert main([*argv[:3], "--cameras", "top", *argv[5:-2], str(one), "--no-progress"]) == 0
    np.testing.assert_array_equal(EpisodeStore.open(one).episode(0)["img"], ep["img"])
    capsys.readouterr()
    assert main([*argv[:3], "--cameras", "top", *argv[5:]]) == 1  # the store records both views
    assert "cameras=['top', 'side'], not cameras=['top']" in capsys.readouterr().err
    assert main([*argv[:3], "--cameras", "side,top", *argv[5:]]) == 1
    assert "the first camera must be 'top'" in capsys.readouterr().err
