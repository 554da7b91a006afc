"""ALOHA/ACT HDF5, robomimic HDF5 and Diffusion Policy Zarr: round trips, hand-written fixtures
laid out as those projects write them, bad input, corrupted files (hypothesis) and validation."""

from __future__ import annotations

import io
import json
import shutil
import uuid
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest
import zarr
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numcodecs import Blosc
from PIL import Image

from iwsim.data.formats import FormatError, export, import_, validate
from iwsim.data.formats.common import resize_frames
from iwsim.data.formats.hdf5 import ALOHA_ACTION_NAMES
from iwsim.data.store import EpisodeStore

# Deterministic (derandomize) and without an example database, so runs leave no files behind.
FUZZ = settings(max_examples=20, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])


# --- data --------------------------------------------------------------------------------------
def frames(t: int, size: int, seed: int) -> np.ndarray:
    """(t, size, size, 3) uint8 smooth gradients (JPEG keeps them well) with a pure red square."""
    y, x = np.mgrid[0:size, 0:size] / size
    phase = np.random.default_rng(seed).uniform(0, 1, 3)
    out = np.empty((t, size, size, 3), np.uint8)
    for k in range(t):
        for c in range(3):
            out[k, ..., c] = 40 + 150 * (0.5 + 0.5 * np.sin(2 * np.pi * (x + y + phase[c] + 0.1 * k)))
    q = size // 4
    out[:, q:2 * q, q:2 * q] = (255, 0, 0)
    return out


def episode(j: int, t: int, size: int = 32, s: int = 4, a: int = 4) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(100 + j)
    return {"img": frames(t, size, j), "state": rng.standard_normal((t, s)).astype(np.float32),
            "action": rng.standard_normal((t, a)).astype(np.float32)}


@pytest.fixture
def store_path(tmp_path: Path) -> Path:
    """3 episodes of 5, 6 and 7 steps at 32x32, seeds 10, 11, 12."""
    store = EpisodeStore.create(tmp_path / "s.zarr", {"fps": 10, "task": "pusht", "image_size": 32})
    for j in range(3):
        store.append(episode(j, 5 + j), seed=10 + j)
    return store.path


def jpeg_like_act(rgb: np.ndarray, quality: int = 50) -> bytes:
    """The bytes of ``cv2.imencode('.jpg', rgb)``: OpenCV takes the array for BGR, so the
    JPEG's true red is the array's last channel."""
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb[..., ::-1])).save(buf, format="JPEG", quality=quality)
    return buf.getvalue()


def write_act(path: Path, cams: dict[str, np.ndarray], qpos: np.ndarray, action: np.ndarray,
              compress: bool = False) -> None:
    """An episode file as act-plus-plus writes one: datasets created with h5py's default dtype
    (float32), one frame per chunk, then filled; JPEG rows padded to the longest plus
    /compress_len (cameras, T) when compressed (record_episodes.py / compress_data.py)."""
    t = len(action)
    with h5py.File(path, "w") as root:
        root.attrs["sim"] = True
        if compress:
            root.attrs["compress"] = True
        obs = root.create_group("observations")
        image = obs.create_group("images")
        lens = []
        for name, video in cams.items():
            if compress:
                jpegs = [np.frombuffer(jpeg_like_act(f), np.uint8) for f in video]
                lens.append([len(j) for j in jpegs])
                padded = np.zeros((t, max(lens[-1])), np.uint8)
                for k, j in enumerate(jpegs):
                    padded[k, :len(j)] = j
                image.create_dataset(name, padded.shape, dtype="uint8", chunks=(1, padded.shape[1]))
                image[name][...] = padded
            else:
                image.create_dataset(name, video.shape, dtype="uint8", chunks=(1, *video.shape[1:]))
                image[name][...] = video
        obs.create_dataset("qpos", qpos.shape, dtype="f4")  # h5py's default, which ACT relies on
        obs.create_dataset("qvel", qpos.shape, dtype="f4")
        root.create_dataset("action", action.shape, dtype="f4")
        root["observations/qpos"][...] = qpos
        root["action"][...] = action
        if compress:
            root.create_dataset("compress_len", (len(cams), t), dtype="f4")
            root["/compress_len"][...] = np.array(lens)


def act_dir(root: Path, compress: bool = False, numbers: tuple[int, ...] = (0, 2, 10)) -> tuple[Path, list[dict]]:
    """ALOHA files episode_<n>.hdf5 with two 32x32 cameras, 14-D qpos and action."""
    root.mkdir()
    eps = []
    for j, n in enumerate(numbers):
        ep = episode(j, 4 + j, s=14, a=14)
        cams = {"top": ep["img"], "left_wrist": frames(len(ep["img"]), 32, 50 + j)}
        write_act(root / f"episode_{n}.hdf5", cams, ep["state"], ep["action"], compress)
        eps.append({**ep, "left_wrist": cams["left_wrist"]})
    return root, eps


def write_h5(path: Path, arrays: dict[str, np.ndarray], attrs: dict[str, dict]) -> None:
    with h5py.File(path, "w") as f:
        for key, value in arrays.items():
            f.create_dataset(key, data=value)
        for key, values in attrs.items():
            f.require_group(key).attrs.update(values)


ROBOMIMIC_LOWDIM = {"robot0_eef_pos": 3, "robot0_eef_quat": 4, "robot0_gripper_qpos": 2, "object": 10}


def robomimic_arrays(demos: tuple[int, ...] = (0, 2, 10)) -> tuple[dict[str, np.ndarray], dict[str, dict], list[dict]]:
    """A robomimic file's datasets: data/demo_<i>/{actions (T, 7), obs/{agentview_image,
    robot0_eye_in_hand_image, low-dim keys}, states, rewards, dones} and data attrs."""
    arrays, attrs, eps = {}, {}, []
    env_args = {"env_name": "Lift", "env_type": 1, "env_kwargs": {"control_freq": 20, "camera_heights": 32}}
    attrs["data"] = {"env_args": json.dumps(env_args), "total": 0}
    for j, n in enumerate(demos):
        t = 4 + j
        rng = np.random.default_rng(j)
        base = f"data/demo_{n}"
        low = {k: rng.standard_normal((t, d)) for k, d in ROBOMIMIC_LOWDIM.items()}
        arrays[f"{base}/actions"] = rng.uniform(-1, 1, (t, 7))
        arrays[f"{base}/obs/agentview_image"] = frames(t, 32, j)
        arrays[f"{base}/obs/robot0_eye_in_hand_image"] = frames(t, 32, 70 + j)
        arrays.update({f"{base}/obs/{k}": v for k, v in low.items()})
        arrays[f"{base}/states"] = rng.standard_normal((t, 32))
        arrays[f"{base}/rewards"] = np.zeros(t)
        arrays[f"{base}/dones"] = np.zeros(t, np.int64)
        attrs[base] = {"num_samples": t}
        attrs["data"]["total"] += t
        state = np.concatenate([low[k] for k in sorted(low)], axis=1).astype(np.float32)
        eps.append({"img": arrays[f"{base}/obs/agentview_image"], "state": state,
                    "action": arrays[f"{base}/actions"].astype(np.float32)})
    return arrays, attrs, eps


def dp_arrays(lengths: tuple[int, ...] = (5, 6, 7)) -> dict[str, np.ndarray]:
    """Diffusion Policy's Push-T ReplayBuffer: img float32 in [0, 255], state (N, 5), action (N, 2)."""
    n = sum(lengths)
    rng = np.random.default_rng(0)
    return {
        "data/img": np.concatenate([frames(t, 16, j) for j, t in enumerate(lengths)]).astype(np.float32),
        "data/state": rng.uniform(0, 512, (n, 5)).astype(np.float32),
        "data/action": rng.uniform(0, 512, (n, 2)).astype(np.float32),
        "data/keypoint": rng.uniform(0, 512, (n, 9, 2)).astype(np.float32),
        "data/n_contacts": rng.integers(0, 3, (n, 1)).astype(np.float32),
        "meta/episode_ends": np.cumsum(lengths).astype(np.int64),
    }


def write_zarr(path: Path, arrays: dict[str, np.ndarray], attrs: dict | None = None) -> None:
    """Zarr format 2 with DP's default compressor (Blosc lz4) and ~4-frame chunks."""
    root = zarr.open_group(path, mode="w", zarr_format=2)
    for key, value in arrays.items():
        chunks = (max(1, min(4, len(value))), *value.shape[1:]) if value.ndim else ()
        compressor = None if key.startswith("meta") else Blosc(cname="lz4", clevel=5, shuffle=Blosc.NOSHUFFLE)
        arr = root.create_array(key, shape=value.shape, dtype=value.dtype, chunks=chunks or None,
                                compressors=compressor, fill_value=0)
        arr[...] = value
    root.attrs.update(attrs or {})


def assert_episodes(store: EpisodeStore, want: list[dict], keys: tuple[str, ...] = ("img", "state", "action")) -> None:
    assert store.n_episodes == len(want)
    for j, w in enumerate(want):
        got = store.episode(j)
        for k in keys:
            np.testing.assert_array_equal(got[k], w[k], err_msg=f"episode {j} key {k}")


def assert_clean_failure(err: BaseException, out: Path) -> None:
    """One line, and nothing left at or next to ``out``."""
    assert "\n" not in str(err), str(err)
    assert not out.exists()
    assert not [p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.")]


# --- round trips -------------------------------------------------------------------------------
def test_aloha_round_trip_is_exact(store_path: Path, tmp_path: Path) -> None:
    out = export("hdf5-aloha", store_path, tmp_path / "aloha", progress=False)
    assert sorted(p.name for p in out.iterdir()) == [f"episode_{i}.hdf5" for i in range(3)]
    with h5py.File(out / "episode_1.hdf5") as f:
        assert (bool(f.attrs["sim"]), bool(f.attrs["compress"]), int(f.attrs["fps"]), f.attrs["task"]) == \
            (True, False, 10, "pusht")
        assert f["observations/images/top"].shape == (6, 32, 32, 3) and f["observations/images/top"].dtype == np.uint8
        assert f["observations/qpos"].dtype == f["action"].dtype == np.float32
        assert f["observations/qvel"].shape == (6, 4)
    src = EpisodeStore.open(store_path)
    back = import_("hdf5-aloha", out, tmp_path / "back.zarr", image_size=None, progress=False)
    assert_episodes(back, [src.episode(j) for j in range(3)])
    assert back.seeds == [10, 11, 12]
    a = back.attrs
    assert (a["fps"], a["task"], a["image_size"], a["camera"]) == (10, "pusht", 32, "top")
    assert validate(out) == ("hdf5-aloha", [])
    assert validate(back.path) == ("episode store", [])


def test_aloha_round_trip_resized(store_path: Path, tmp_path: Path) -> None:
    out = export("hdf5-aloha", store_path, tmp_path / "aloha", progress=False)
    back = import_("hdf5-aloha", out, tmp_path / "back.zarr", image_size=16, progress=False)
    src = EpisodeStore.open(store_path)
    want = [{**src.episode(j), "img": resize_frames(src.episode(j)["img"], 16)} for j in range(3)]
    assert_episodes(back, want)
    assert back.attrs["image_size"] == 16


# --- fixtures written as the original projects write them --------------------------------------
def test_act_files_uncompressed(tmp_path: Path) -> None:
    src, eps = act_dir(tmp_path / "sim_transfer_cube_scripted")
    store = import_("hdf5-aloha", src, tmp_path / "a.zarr", image_size=None, progress=False)
    assert_episodes(store, [{**e, "img_left_wrist": e["left_wrist"]} for e in eps],
                    keys=("img", "img_left_wrist", "state", "action"))  # episode_0, episode_2, episode_10
    # every camera, "top" first though h5py lists left_wrist first
    assert store.attrs["cameras"] == ["top", "left_wrist"] and store.attrs["source_cameras"] == ["top", "left_wrist"]
    assert "camera" not in store.attrs and store.attrs["fps"] == 50
    assert store.attrs["task"] == "sim_transfer_cube_scripted"
    assert store.attrs["action_names"] == ALOHA_ACTION_NAMES and len(ALOHA_ACTION_NAMES) == 14
    wrist = import_("hdf5-aloha", src, tmp_path / "w.zarr", camera="left_wrist", image_size=None, progress=False)
    assert_episodes(wrist, [{**e, "img": e["left_wrist"]} for e in eps])
    assert wrist.attrs["camera"] == "left_wrist" and "cameras" not in wrist.attrs
    assert sorted(wrist.keys) == ["action", "img", "state"]
    one = import_("hdf5-aloha", src / "episode_2.hdf5", tmp_path / "one.zarr", image_size=None, progress=False)
    assert_episodes(one, eps[1:2])


@pytest.mark.parametrize("with_lengths", [True, False])
def test_act_files_jpeg_compressed(tmp_path: Path, with_lengths: bool) -> None:
    src, eps = act_dir(tmp_path / "aloha", compress=True)
    if not with_lengths:  # ACT's own loader decodes the padded rows without it
        for p in src.iterdir():
            with h5py.File(p, "a") as f:
                del f["compress_len"]
    store = import_("hdf5-aloha", src, tmp_path / "a.zarr", image_size=None, progress=False)
    assert_episodes(store, eps, keys=("state", "action"))
    q = 8
    for j, want in enumerate(eps):
        got = store.episode(j)["img"]
        assert got.shape == want["img"].shape
        assert np.abs(got.astype(int) - want["img"].astype(int)).mean() < 8
        # ACT's arrays hold pure red at [8:16, 8:16]; reversed channels would show blue there.
        red = got[:, q + 2:2 * q - 2, q + 2:2 * q - 2].reshape(-1, 3).mean(0)
        assert red[0] > 200 and red[1] < 60 and red[2] < 60, red
    assert validate(src) == ("hdf5-aloha", [])


def test_robomimic_file(tmp_path: Path) -> None:
    arrays, attrs, eps = robomimic_arrays()
    write_h5(tmp_path / "image.hdf5", arrays, attrs)
    store = import_("robomimic", tmp_path / "image.hdf5", tmp_path / "r.zarr", image_size=None, progress=False)
    assert_episodes(store, eps)  # demo_0, demo_2, demo_10: numeric order; state = sorted low-dim keys
    a = store.attrs
    assert (a["task"], a["fps"], a["cameras"], a["image_size"]) == ("Lift", 20, ["agentview", "robot0_eye_in_hand"],
                                                                   32)
    assert a["source_cameras"] == ["agentview_image", "robot0_eye_in_hand_image"]
    np.testing.assert_array_equal(store.episode(2)["img_robot0_eye_in_hand"],
                                  arrays["data/demo_10/obs/robot0_eye_in_hand_image"])
    assert a["state_keys"] == [[k, ROBOMIMIC_LOWDIM[k]] for k in sorted(ROBOMIMIC_LOWDIM)]
    assert store.episode(0)["action"].shape[1] == 7
    hand = import_("robomimic", tmp_path / "image.hdf5", tmp_path / "h.zarr", camera="robot0_eye_in_hand_image",
                   image_size=None, progress=False)
    np.testing.assert_array_equal(hand.episode(2)["img"], arrays["data/demo_10/obs/robot0_eye_in_hand_image"])
    assert hand.attrs["camera"] == "robot0_eye_in_hand_image" and "img_agentview" not in hand.keys
    assert validate(tmp_path / "image.hdf5") == ("robomimic", [])


def test_robomimic_cameras_without_agentview_in_name_order(tmp_path: Path) -> None:
    arrays, attrs, _ = robomimic_arrays((0,))
    arrays["data/demo_0/obs/sideview_image"] = arrays.pop("data/demo_0/obs/agentview_image")
    write_h5(tmp_path / "x.hdf5", arrays, attrs)
    store = import_("robomimic", tmp_path / "x.hdf5", tmp_path / "r.zarr", image_size=16, progress=False)
    assert store.attrs["cameras"] == ["robot0_eye_in_hand", "sideview"] and store.attrs["image_size"] == 16
    np.testing.assert_array_equal(store.episode(0)["img_sideview"],
                                  resize_frames(arrays["data/demo_0/obs/sideview_image"], 16))
    with pytest.raises(FormatError, match="no obs key 'agentview_image'; image keys: robot0_eye_in_hand_image, "
                                          "sideview_image") as e:
        import_("robomimic", tmp_path / "x.hdf5", tmp_path / "a.zarr", camera="agentview_image", image_size=None,
                progress=False)
    assert_clean_failure(e.value, tmp_path / "a.zarr")


def test_dp_pusht_zarr(tmp_path: Path) -> None:
    arrays = dp_arrays()
    write_zarr(tmp_path / "pusht_cchi_v7_replay.zarr", arrays)
    store = import_("zarr", tmp_path / "pusht_cchi_v7_replay.zarr", tmp_path / "p.zarr", image_size=None,
                    progress=False)
    bounds = [0, 5, 11, 18]
    want = [{"img": arrays["data/img"][a:b].astype(np.uint8), "state": arrays["data/state"][a:b],
             "action": arrays["data/action"][a:b], "keypoint": arrays["data/keypoint"][a:b]}
            for a, b in zip(bounds, bounds[1:])]
    assert_episodes(store, want, keys=("img", "state", "action", "keypoint"))
    assert store.keys == ["action", "img", "keypoint", "n_contacts", "state"]
    a = store.attrs
    assert (a["task"], a["fps"], a["image_size"], a["camera"]) == ("pusht_cchi_v7_replay", 10, 16, "img")
    assert store.seeds == [None] * 3


def test_own_store_through_zarr_importer(store_path: Path, tmp_path: Path) -> None:
    store = import_("zarr", store_path, tmp_path / "c.zarr", image_size=None, progress=False)
    src = EpisodeStore.open(store_path)
    assert_episodes(store, [src.episode(j) for j in range(3)])
    assert store.seeds == [10, 11, 12] and store.attrs["task"] == "pusht"


# --- bad input ---------------------------------------------------------------------------------
def _aloha_file(tmp_path: Path) -> Path:
    src, _ = act_dir(tmp_path / "aloha", numbers=(0, 1))
    return src


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 2 // 3])


def _h5_edit(path: Path, key: str, value: np.ndarray | None) -> None:
    with h5py.File(path, "a") as f:
        del f[key]
        if value is not None:
            f.create_dataset(key, data=value)


ALOHA_BREAKS: dict[str, tuple[Callable[[Path], None], str]] = {
    "truncated": (_truncate, "not a readable HDF5 file"),
    "missing action": (lambda p: _h5_edit(p, "action", None), r"key 'action' \(episode 1\): missing"),
    "short qpos": (lambda p: _h5_edit(p, "observations/qpos", np.zeros((4, 14), np.float32)),
                   r"\(episode 1\): arrays differ in length"),
    "float frames": (lambda p: _h5_edit(p, "observations/images/top", np.zeros((5, 32, 32, 3), np.float32)),
                     "frames must be uint8"),
    "text actions": (lambda p: _h5_edit(p, "action", np.full((5, 14), b"x")), "'action' must be numbers"),
    "empty": (lambda p: [_h5_edit(p, k, np.zeros((0, *s), d)) for k, s, d in
                         [("action", (14,), np.float32), ("observations/qpos", (14,), np.float32),
                          ("observations/images/top", (32, 32, 3), np.uint8),
                          ("observations/images/left_wrist", (32, 32, 3), np.uint8)]], "episode is empty"),
    "short camera": (lambda p: _h5_edit(p, "observations/images/left_wrist", np.zeros((4, 32, 32, 3), np.uint8)),
                     r"\(episode 1\): the views differ in frame count: img 5, img_left_wrist 4"),
    "nan": (lambda p: _h5_edit(p, "action", np.full((5, 14), np.nan, np.float32)), "non-finite"),
}


@pytest.mark.parametrize("case", sorted(ALOHA_BREAKS))
def test_bad_aloha_files(tmp_path: Path, case: str) -> None:
    src = _aloha_file(tmp_path)
    breaker, message = ALOHA_BREAKS[case]
    breaker(src / "episode_1.hdf5")
    out = tmp_path / "out.zarr"
    with pytest.raises(FormatError, match=message) as e:
        import_("hdf5-aloha", src, out, image_size=None, progress=False)
    assert "episode_1.hdf5" in str(e.value)
    assert_clean_failure(e.value, out)
    kind, problems = validate(src)
    assert kind == "hdf5-aloha" and problems and all("episode_1.hdf5" in p for p in problems), problems


def test_bad_aloha_camera_and_dims(tmp_path: Path) -> None:
    src = _aloha_file(tmp_path)
    with pytest.raises(FormatError, match="no camera 'front'; it has left_wrist, top"):
        import_("hdf5-aloha", src, tmp_path / "o.zarr", camera="front", image_size=64, progress=False)
    _h5_edit(src / "episode_1.hdf5", "action", np.zeros((5, 7), np.float32))
    with pytest.raises(FormatError, match=r"episode_1.hdf5 \(episode 1\): qpos/action have 14/7 dims") as e:
        import_("hdf5-aloha", src, tmp_path / "o.zarr", image_size=None, progress=False)
    assert_clean_failure(e.value, tmp_path / "o.zarr")
    assert any("dims per step" in p for p in validate(src)[1])


def test_bad_jpeg_rows(tmp_path: Path) -> None:
    src, _ = act_dir(tmp_path / "aloha", compress=True, numbers=(0, 1))
    with h5py.File(src / "episode_1.hdf5", "a") as f:
        f["observations/images/top"][4, 5:] = 0  # the last frame cut after 5 bytes
    with pytest.raises(FormatError, match=r"images/top' \(episode 1\): frame 4 is not a readable JPEG") as e:
        import_("hdf5-aloha", src, tmp_path / "o.zarr", image_size=None, progress=False)
    assert_clean_failure(e.value, tmp_path / "o.zarr")
    with h5py.File(src / "episode_0.hdf5", "a") as f:
        f["compress_len"][1, 0] = 1e9
    problems = validate(src)[1]
    assert problems[0].endswith("episode_0.hdf5 key 'compress_len' (episode 0): lengths must lie in 1..779 "
                                "(the JPEG rows' width).")
    # validate decodes each episode's first and last frames only
    assert "episode_1.hdf5 key 'observations/images/top' (episode 1): frame 4 is not" in problems[1]
    assert len(problems) == 2


ROBOMIMIC_BREAKS: dict[str, tuple[Callable[[dict], None], str]] = {
    "missing actions": (lambda a: a.pop("data/demo_2/actions"), r"key 'data/demo_2/actions' \(episode 1\): missing"),
    "short obs": (lambda a: a.update({"data/demo_2/obs/object": np.zeros((3, 10))}),
                  r"data/demo_2/obs/object' \(episode 1\): 3 steps, but actions has 5"),
    "int images": (lambda a: a.update({"data/demo_2/obs/agentview_image": np.zeros((5, 32, 32, 3), np.int32)}),
                   r"data/demo_2' \(episode 1\): frames must be uint8"),
    "empty": (lambda a: a.update({k: v[:0] for k, v in a.items() if k.startswith("data/demo_2/")}),
              r"data/demo_2' \(episode 1\): the episode is empty"),
    "wrong state size": (lambda a: a.update({"data/demo_2/obs/robot0_eef_pos": np.zeros((5, 4))}),
                         r"robot0_eef_pos' \(episode 1\): expected 3 numbers per step"),
}


@pytest.mark.parametrize("case", sorted(ROBOMIMIC_BREAKS))
def test_bad_robomimic_files(tmp_path: Path, case: str) -> None:
    arrays, attrs, _ = robomimic_arrays()
    breaker, message = ROBOMIMIC_BREAKS[case]
    breaker(arrays)
    write_h5(tmp_path / "r.hdf5", arrays, attrs)
    out = tmp_path / "out.zarr"
    with pytest.raises(FormatError, match=message) as e:
        import_("robomimic", tmp_path / "r.hdf5", out, image_size=None, progress=False)
    assert "r.hdf5" in str(e.value)
    assert_clean_failure(e.value, out)
    kind, problems = validate(tmp_path / "r.hdf5")
    assert kind == "robomimic" and problems and all("demo_2" in p for p in problems), problems


def test_truncated_robomimic_file(tmp_path: Path) -> None:
    arrays, attrs, _ = robomimic_arrays()
    write_h5(tmp_path / "r.hdf5", arrays, attrs)
    _truncate(tmp_path / "r.hdf5")
    with pytest.raises(FormatError, match="r.hdf5: not a readable HDF5 file") as e:
        import_("robomimic", tmp_path / "r.hdf5", tmp_path / "out.zarr", image_size=64, progress=False)
    assert_clean_failure(e.value, tmp_path / "out.zarr")
    assert validate(tmp_path / "r.hdf5")[1][0].startswith(f"{tmp_path / 'r.hdf5'}: not a readable HDF5 file")


ZARR_BREAKS: dict[str, tuple[Callable[[dict], None], str]] = {
    "ends decrease": (lambda a: a.update({"meta/episode_ends": np.array([5, 4, 18])}),
                      r"episode_ends' \(episode 1\): episode ends must increase strictly; entry 1 is 4 after 5"),
    "missing action": (lambda a: a.pop("data/action"), "key 'data/action': missing"),
    "short state": (lambda a: a.update({"data/state": a["data/state"][:12]}),
                    "key 'data/state': holds 12 frames but meta/episode_ends counts 18"),
    "frames out of range": (lambda a: a["data/img"].__setitem__(7, 300.0),
                            r"data/img' \(episode 1\): float frames must hold values in \[0, 255\]"),
    "rank-3 action": (lambda a: a.update({"data/action": a["data/action"][:, :, None]}),
                      r"\(episode 0\): 'action' must be numbers of shape \(T, D\)"),
}


@pytest.mark.parametrize("case", sorted(ZARR_BREAKS))
def test_bad_dp_zarr(tmp_path: Path, case: str) -> None:
    arrays = dp_arrays()
    breaker, message = ZARR_BREAKS[case]
    breaker(arrays)
    write_zarr(tmp_path / "d.zarr", arrays)
    out = tmp_path / "out.zarr"
    with pytest.raises(FormatError, match=message) as e:
        import_("zarr", tmp_path / "d.zarr", out, image_size=None, progress=False)
    assert "d.zarr" in str(e.value)
    assert_clean_failure(e.value, out)


def test_truncated_zarr_chunk(store_path: Path, tmp_path: Path) -> None:
    chunk = store_path / "data" / "state" / "0.0"
    chunk.write_bytes(chunk.read_bytes()[:10])
    with pytest.raises(FormatError, match=r"data/state' \(episode 0\): unreadable") as e:
        import_("zarr", store_path, tmp_path / "out.zarr", image_size=64, progress=False)
    assert_clean_failure(e.value, tmp_path / "out.zarr")
    kind, problems = validate(store_path)
    assert kind == "episode store" and len(problems) == 1 and "data/state' (episodes 0..2): frames 0..17" in problems[0]


# --- corrupted files: importers fail cleanly or succeed with a valid store ---------------------
def _import_or_fail(fmt: str, src: Path, out: Path) -> None:
    """Import; on failure the error is a one-line ValueError/OSError and ``out`` is absent; on
    success the store is valid."""
    try:
        store = import_(fmt, src, out, image_size=None, progress=False)
    except (ValueError, OSError) as e:
        assert_clean_failure(e, out)
        return
    assert store.n_episodes >= 1
    assert validate(out) == ("episode store", [])


def _scratch(tmp_path: Path) -> Path:
    d = tmp_path / uuid.uuid4().hex[:8]
    d.mkdir()
    return d


def _corrupt(data: bytes, flips: list[tuple[float, int]], cut: float | None) -> bytes:
    b = bytearray(data)
    for where_, value in flips:
        b[int(where_ * (len(b) - 1))] = value
    return bytes(b[: int(cut * len(b))] if cut is not None else b)


corruptions = st.tuples(
    st.lists(st.tuples(st.floats(0, 1), st.integers(0, 255)), min_size=1, max_size=8),
    st.none() | st.floats(0, 1),
)


@pytest.fixture(scope="module")
def pristine(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """One valid file of each kind, to corrupt copies of."""
    root = tmp_path_factory.mktemp("pristine")
    aloha, _ = act_dir(root / "aloha", compress=False, numbers=(0,))
    jpeg, _ = act_dir(root / "jpeg", compress=True, numbers=(0,))
    arrays, attrs, _ = robomimic_arrays((0, 1))
    write_h5(root / "r.hdf5", arrays, attrs)
    write_zarr(root / "d.zarr", dp_arrays())
    return {"aloha": aloha / "episode_0.hdf5", "jpeg": jpeg / "episode_0.hdf5", "robomimic": root / "r.hdf5",
            "zarr": root / "d.zarr"}


@FUZZ
@given(kind=st.sampled_from(["aloha", "jpeg", "robomimic"]), corruption=corruptions)
def test_corrupted_hdf5_files(pristine: dict[str, Path], tmp_path: Path, kind: str,
                              corruption: tuple[list[tuple[float, int]], float | None]) -> None:
    d = _scratch(tmp_path)
    src = d / "episode_0.hdf5"
    src.write_bytes(_corrupt(pristine[kind].read_bytes(), *corruption))
    _import_or_fail("robomimic" if kind == "robomimic" else "hdf5-aloha", src, d / "out.zarr")
    validate(src)  # reports, never raises


@FUZZ
@given(key=st.sampled_from(["data/img/0.0.0.0", "data/state/1.0", "data/action/0.0", "data/keypoint/.zarray",
                            "meta/episode_ends/0", "data/img/.zarray", ".zgroup"]),
       corruption=corruptions)
def test_corrupted_zarr_chunks(pristine: dict[str, Path], tmp_path: Path, key: str,
                               corruption: tuple[list[tuple[float, int]], float | None]) -> None:
    d = _scratch(tmp_path)
    src = d / "d.zarr"
    shutil.copytree(pristine["zarr"], src)
    (src / key).write_bytes(_corrupt((src / key).read_bytes(), *corruption))
    _import_or_fail("zarr", src, d / "out.zarr")


def _mutate(value: np.ndarray, how: str) -> np.ndarray | None:
    if how == "delete":
        return None
    if how == "empty":
        return value[:0]
    if how == "shorter":
        return value[:-1]
    if how == "longer":
        return np.concatenate([value, value[-1:]])
    if how == "add axis":
        return value[..., None]
    if how == "drop axis":
        return value[..., 0]
    return value.astype(how)  # a dtype


mutations = st.sampled_from(["delete", "empty", "shorter", "longer", "add axis", "drop axis",
                             "int16", "bool", "S4", "float16", "uint8", "float64"])


@settings(FUZZ, max_examples=15)
@given(kind=st.sampled_from(["aloha", "robomimic", "zarr"]), pick=st.integers(0, 100), how=mutations)
def test_changed_dtypes_shapes_lengths(tmp_path: Path, kind: str, pick: int, how: str) -> None:
    d = _scratch(tmp_path)
    if kind == "aloha":
        ep = episode(0, 5, s=14, a=14)
        arrays = {"observations/images/top": ep["img"], "observations/qpos": ep["state"],
                  "observations/qvel": ep["state"], "action": ep["action"]}
        attrs: dict = {"/": {"sim": True}}
    elif kind == "robomimic":
        arrays, attrs, _ = robomimic_arrays((0, 1))
    else:
        arrays, attrs = dp_arrays((5, 6)), {}
    key = sorted(arrays)[pick % len(arrays)]
    value = _mutate(arrays.pop(key), how)
    if value is not None:
        arrays[key] = value
    if kind == "zarr":
        write_zarr(d / "src.zarr", arrays)
        src, fmt = d / "src.zarr", "zarr"
    else:
        src = d / "episode_0.hdf5"
        write_h5(src, arrays, attrs)
        fmt = "robomimic" if kind == "robomimic" else "hdf5-aloha"
    _import_or_fail(fmt, src, d / "out.zarr")


# --- validate ----------------------------------------------------------------------------------
def test_validate_dp_zarr_and_broken_store(store_path: Path, tmp_path: Path) -> None:
    write_zarr(tmp_path / "d.zarr", dp_arrays())
    assert validate(tmp_path / "d.zarr") == ("Diffusion Policy zarr", [])
    (tmp_path / "d.zarr" / "data" / "action" / "0.0").write_bytes(b"xx")
    kind, problems = validate(tmp_path / "d.zarr")
    assert kind == "Diffusion Policy zarr" and len(problems) == 1 and "data/action" in problems[0]
    root = zarr.open_group(store_path, mode="r+")
    root.attrs["fps"] = 0
    root.attrs["image_size"] = 64
    state = root["data/state"]
    state[7] = np.nan
    _, problems = validate(store_path)
    assert len(problems) == 3, problems
    assert "'fps' is 0" in problems[1] and "'image_size' is 64; data/img holds 32x32" in problems[2]
    assert problems[0].endswith("key 'data/state' (episode 1): holds non-finite values.")


def test_validate_neither_format(tmp_path: Path) -> None:
    write_h5(tmp_path / "x.h5", {"foo": np.zeros(3)}, {})
    kind, problems = validate(tmp_path / "x.h5")
    assert kind == "hdf5" and "neither ALOHA" in problems[0]


# --- several cameras ---------------------------------------------------------------------------
def test_aloha_two_views_round_trip(two_view_store: Path, tmp_path: Path) -> None:
    out = export("hdf5-aloha", two_view_store, tmp_path / "aloha", progress=False)
    src = EpisodeStore.open(two_view_store)
    with h5py.File(out / "episode_1.hdf5") as f:
        assert sorted(f["observations/images"]) == ["side", "top"]
        assert json.loads(f.attrs["cameras"]) == ["top", "side"]
        np.testing.assert_array_equal(f["observations/images/side"][()], src.episode(1)["img_side"])
    assert validate(out) == ("hdf5-aloha", [])
    back = import_("hdf5-aloha", out, tmp_path / "back.zarr", image_size=None, progress=False)
    assert_episodes(back, [src.episode(j) for j in range(2)], keys=("img", "img_side", "state", "action"))
    assert back.attrs["cameras"] == ["top", "side"] and back.seeds == [0, 1]
    assert validate(back.path) == ("episode store", [])
    side = import_("hdf5-aloha", out, tmp_path / "side.zarr", camera="side", image_size=None, progress=False)
    assert_episodes(side, [{"img": src.episode(j)["img_side"]} for j in range(2)], keys=("img",))
    assert sorted(side.keys) == ["action", "img", "state"] and side.attrs["camera"] == "side"


def test_aloha_export_keeps_the_view_order(tmp_path: Path) -> None:
    """A store whose first view is not "top": the files' ``cameras`` attribute brings the
    order back (without it, "top" would come first)."""
    from conftest import make_two_view_store

    store = make_two_view_store(tmp_path / "s.zarr", cameras=("side", "top"))
    out = export("hdf5-aloha", store, tmp_path / "aloha", progress=False)
    back = import_("hdf5-aloha", out, tmp_path / "back.zarr", image_size=None, progress=False)
    assert back.attrs["cameras"] == ["side", "top"]
    src = EpisodeStore.open(store)
    assert_episodes(back, [src.episode(j) for j in range(2)], keys=("img", "img_top"))


def test_views_of_different_sizes_need_resizing(tmp_path: Path) -> None:
    src = tmp_path / "aloha"
    src.mkdir()
    ep = episode(0, 4, s=14, a=14)
    write_act(src / "episode_0.hdf5", {"top": ep["img"], "wrist": frames(4, 16, 3)}, ep["state"], ep["action"])
    with pytest.raises(FormatError, match=r"episode 0: the views' frames differ in size \(top 32x32, wrist 16x16\); "
                                          "import with --image-size") as e:
        import_("hdf5-aloha", src, tmp_path / "o.zarr", image_size=None, progress=False)
    assert_clean_failure(e.value, tmp_path / "o.zarr")
    store = import_("hdf5-aloha", src, tmp_path / "o.zarr", image_size=8, progress=False)
    assert store.array("img").shape[1:] == store.array("img_wrist").shape[1:] == (8, 8, 3)
    np.testing.assert_array_equal(store.episode(0)["img_wrist"], resize_frames(frames(4, 16, 3), 8))


def test_validate_finds_cameras_missing_from_an_episode(tmp_path: Path) -> None:
    src = _aloha_file(tmp_path)
    _h5_edit(src / "episode_1.hdf5", "observations/images/left_wrist", None)
    problems = validate(src)[1]
    assert len(problems) == 1 and "episode_1.hdf5 key 'observations/images' (episode 1): cameras top; the first " \
        "episode has left_wrist, top" in problems[0], problems
    with pytest.raises(FormatError, match=r"episode_1.hdf5 key 'observations/images' \(episode 1\): no camera "
                                          "'left_wrist'; it has top") as e:
        import_("hdf5-aloha", src, tmp_path / "o.zarr", image_size=None, progress=False)
    assert_clean_failure(e.value, tmp_path / "o.zarr")
    top = import_("hdf5-aloha", src, tmp_path / "t.zarr", camera="top", image_size=None, progress=False)
    assert top.n_episodes == 2

    arrays, attrs, _ = robomimic_arrays((0, 1))
    del arrays["data/demo_1/obs/robot0_eye_in_hand_image"]
    write_h5(tmp_path / "r.hdf5", arrays, attrs)
    problems = validate(tmp_path / "r.hdf5")[1]
    assert len(problems) == 1 and "demo_1/obs' (episode 1): image keys agentview_image; the first demo has " \
        "agentview_image, robot0_eye_in_hand_image" in problems[0], problems


def test_dp_zarr_with_two_image_arrays(tmp_path: Path) -> None:
    arrays = dp_arrays()
    arrays["data/wrist_image"] = np.concatenate([frames(t, 16, 40 + j) for j, t in enumerate((5, 6, 7))])
    write_zarr(tmp_path / "d.zarr", arrays)
    store = import_("zarr", tmp_path / "d.zarr", tmp_path / "p.zarr", image_size=None, progress=False)
    assert store.attrs["cameras"] == ["top", "wrist"] and store.attrs["source_cameras"] == ["img", "wrist_image"]
    assert store.keys == ["action", "img", "img_wrist", "keypoint", "n_contacts", "state"]
    np.testing.assert_array_equal(store.array("img_wrist")[:], arrays["data/wrist_image"])
    np.testing.assert_array_equal(store.array("img")[:], arrays["data/img"].astype(np.uint8))
    assert validate(store.path) == ("episode store", [])
    assert validate(tmp_path / "d.zarr") == ("Diffusion Policy zarr", [])
    for camera in ("wrist_image", "wrist"):  # the array's name or its view's
        one = import_("zarr", tmp_path / "d.zarr", tmp_path / f"{camera}.zarr", camera=camera, image_size=None,
                      progress=False)
        np.testing.assert_array_equal(one.array("img")[:], arrays["data/wrist_image"])
        assert "cameras" not in one.attrs and "img_wrist" not in one.keys
    del arrays["data/img"]  # no img: the image arrays in name order
    arrays["data/agentview_image"] = arrays["data/wrist_image"][:, ::-1].copy()
    write_zarr(tmp_path / "e.zarr", arrays)
    store = import_("zarr", tmp_path / "e.zarr", tmp_path / "e_out.zarr", image_size=None, progress=False)
    assert store.attrs["cameras"] == ["agentview", "wrist"]
    np.testing.assert_array_equal(store.array("img")[:], arrays["data/agentview_image"])


def test_own_two_view_store_through_zarr_importer(two_view_store: Path, tmp_path: Path) -> None:
    store = import_("zarr", two_view_store, tmp_path / "c.zarr", image_size=16, progress=False)
    src = EpisodeStore.open(two_view_store)
    assert store.attrs["cameras"] == ["top", "side"] and store.seeds == [0, 1]
    assert_episodes(store, [{k: resize_frames(src.episode(j)[k], 16) for k in ("img", "img_side")} for j in range(2)],
                    keys=("img", "img_side"))
    side = import_("zarr", two_view_store, tmp_path / "s.zarr", camera="side", image_size=None, progress=False)
    assert_episodes(side, [{"img": src.episode(j)["img_side"]} for j in range(2)], keys=("img",))
    assert side.keys == ["action", "img", "state"] and "cameras" not in side.attrs
