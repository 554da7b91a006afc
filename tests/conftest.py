import os
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch

from iwsim.envs.collect import collect

# Files whose every test is end to end (a demo run, the shipped checkpoint against MuJoCo).
SLOW_FILES = ("test_demo.py", "test_shipped_checkpoint.py", "test_shipped_pile.py")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if item.path.name in SLOW_FILES:
            item.add_marker(pytest.mark.slow)
    # The files with the most end-to-end (slow) tests first: `make test` hands whole files to
    # its two workers in this order (--dist loadfile --no-loadscope-reorder), and a long file
    # started last would leave one worker idle while the other finishes it. A stable sort: a
    # file's tests stay together and in order.
    slow = Counter(item.path for item in items if item.get_closest_marker("slow"))
    items.sort(key=lambda item: -slow[item.path])


def imports_dynamo(load: str, path: Path) -> bool:
    """Whether ``load`` (Python code that loads ``sys.argv[1]``), run in a fresh process on
    ``path``, imports torch._dynamo: its first import costs that process about 2 s."""
    code = f"import sys; {load}; print('torch._dynamo' in sys.modules)"
    run = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, check=True)
    return run.stdout.split() == ["True"]


def run_recipe(recipe: Path, tmp_path: Path) -> subprocess.CompletedProcess:
    """A shipped checkpoint's ``recipe.sh`` shrunk to seconds (SCALE=tiny, no yardstick), run
    from the repository's root with its models under ``tmp_path/out`` and its stores under
    ``tmp_path/data``; a second call resumes the first."""
    env = {**os.environ, "SCALE": "tiny", "YARDSTICK": "0", "OUT": str(tmp_path / "out"),
           "DATA": str(tmp_path / "data"), "IWSIM": str(Path(sys.executable).parent / "iwsim"),
           "PYTHON": sys.executable}
    return subprocess.run(["bash", str(recipe)], env=env, cwd=recipe.parents[2], capture_output=True, text=True)


@pytest.fixture(scope="session")
def play_store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small 64 px play store shared by the training tests: 4 episodes of 12 steps."""
    path = tmp_path_factory.mktemp("data") / "play.zarr"
    collect("pusht", "play", 4, out=path, steps=12, image_size=64, workers=1, seed=0, progress=False)
    return path


def two_view_episode(j: int, t: int, size: int = 32, second: str = "side") -> dict[str, np.ndarray]:
    """Episode j of two camera views that look unlike each other (smooth, so that video
    codecs keep them well): ``img`` warm stripes across, ``img_<second>`` cool stripes down,
    both moving with time; 4-D state and action."""
    y, x = np.mgrid[0:size, 0:size] / size
    rng = np.random.default_rng(200 + j)
    first, other = np.empty((2, t, size, size, 3), np.uint8)
    for k in range(t):
        u = 0.5 + 0.5 * np.sin(2 * np.pi * (x + 0.1 * k + 0.2 * j))
        v = 0.5 + 0.5 * np.sin(2 * np.pi * (y + 0.15 * k + 0.1 * j))
        # brightness stripes of one tint per view: H.264 in yuv420p halves the colour resolution
        first[k] = np.stack([90 + 120 * u, 50 + 120 * u, 20 + 120 * u], axis=-1)
        other[k] = np.stack([20 + 120 * v, 50 + 120 * v, 90 + 120 * v], axis=-1)
    return {"img": first, f"img_{second}": other, "state": rng.standard_normal((t, 4)).astype(np.float32),
            "action": rng.standard_normal((t, 4)).astype(np.float32)}


def make_two_view_store(path: Path, episodes: int = 2, cameras: tuple[str, str] = ("top", "side"),
                        size: int = 32, **attrs) -> Path:
    """A store of two views ``cameras`` (``data/img`` and ``data/img_<cameras[1]>``) made
    directly with EpisodeStore: episodes of 5, 6, ... steps, seeds 0, 1, ..."""
    from iwsim.data.store import EpisodeStore

    store = EpisodeStore.create(path, {"task": "pusht", "fps": 10, "image_size": size, "cameras": list(cameras),
                                       "action_names": ["left_x", "left_y", "right_x", "right_y"], **attrs})
    for j in range(episodes):
        store.append(two_view_episode(j, 5 + j, size, cameras[1]), seed=j)
    store.close()
    return path


@pytest.fixture(scope="session")
def two_view_store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A store of the views top and side: 2 episodes of 5 and 6 steps at 32 px."""
    return make_two_view_store(tmp_path_factory.mktemp("views") / "two.zarr")


@pytest.fixture
def one_thread():
    """Tiny networks on two cores shared with other jobs: torch's default two threads
    oversubscribe them (tens of times slower here), one thread does not."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


# -- a second task, built here: a 2-D point pusher drawn by a tiny renderer ---------------------

POINT_BACKGROUND, POINT_COLOUR, POINT_RADIUS = (230, 230, 225), (40, 90, 220), 5.0


def render_point(pos: np.ndarray, size: int = 64) -> np.ndarray:
    """Frames (..., size, size, 3) uint8 of a disk at positions (..., 2) in [-1, 1] (x right, y up)."""
    centre = (np.asarray(pos, np.float64)[..., None, None, :] * [1, -1] + 1) / 2 * size
    yy, xx = np.mgrid[0:size, 0:size] + 0.5
    inside = (xx - centre[..., 0]) ** 2 + (yy - centre[..., 1]) ** 2 <= POINT_RADIUS**2
    return np.where(inside[..., None], POINT_COLOUR, POINT_BACKGROUND).astype(np.uint8)


def point_episodes(episodes: int = 6, steps: int = 20, seed: int = 0) -> dict[str, np.ndarray]:
    """Diffusion Policy's ReplayBuffer layout of a point robot under position control: a
    smooth random walk of 2-D targets in [-0.8, 0.8]; frame t shows the point where action
    t - 1 put it (img float32 in [0, 255], as DP's Push-T file), ``state`` is that position."""
    rng = np.random.default_rng(seed)
    imgs, states, actions = [], [], []
    for _ in range(episodes):
        pos = rng.uniform(-0.5, 0.5, 2)
        vel = np.zeros(2)
        for _ in range(steps):
            vel = 0.7 * vel + rng.normal(0, 0.06, 2)
            target = np.clip(pos + vel, -0.8, 0.8)
            imgs.append(render_point(pos))
            states.append(pos.copy())
            actions.append(target)
            pos = target
    return {"data/img": np.stack(imgs).astype(np.float32), "data/state": np.asarray(states, np.float32),
            "data/action": np.asarray(actions, np.float32),
            "meta/episode_ends": np.arange(1, episodes + 1, dtype=np.int64) * steps}


def train_tiny_world_model(store: Path, root: Path, *make_store: list[str]) -> Path:
    """Run the commands ``make_store`` that write the episode store ``store``, then ``train
    ae`` / ``train dynamics`` (tiny presets, one thread) and ``export-model`` into ``root``,
    as a user would. Returns the world model's checkpoint."""
    from iwsim.cli import main

    ae, dyn, wm = root / "ae", root / "dyn", root / "wm"
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for argv in (*make_store,
                     ["train", "ae", "--data", str(store), "--preset", "tiny", "--out", str(ae), "--no-progress"],
                     ["train", "dynamics", "--data", str(store), "--ae", str(ae), "--preset", "tiny", "--out",
                      str(dyn), "--no-progress"],
                     ["export-model", "--run", str(dyn), "--out", str(wm)]):
            assert main(argv) == 0, argv
    finally:
        torch.set_num_threads(n)
    return wm


@pytest.fixture(scope="session")
def point_model(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A world model of the point task, made as a user would: a Diffusion Policy Zarr ->
    ``data import`` -> ``train ae`` / ``train dynamics`` (tiny presets) -> ``export-model``.
    Returns the paths of the source, the store and the checkpoint."""
    import zarr

    root = tmp_path_factory.mktemp("point")
    src = root / "point.zarr"
    group = zarr.open_group(src, mode="w", zarr_format=2)
    for key, value in point_episodes().items():
        group.create_array(key, shape=value.shape, dtype=value.dtype, fill_value=0)[...] = value
    group.attrs.update({"fps": 10, "action_names": ["x", "y"]})
    store = root / "store.zarr"
    wm = train_tiny_world_model(store, root, ["data", "import", "--format", "zarr", "--in", str(src), "--out",
                                              str(store), "--image-size", "64"])
    return {"source": src, "store": store, "checkpoint": wm, "run": root / "dyn"}


@pytest.fixture(scope="session")
def pile_model(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A tiny world model of pile sweeping, made as a user would: ``collect --task pilesweep
    --policy expert`` -> ``train ae`` / ``train dynamics`` (tiny presets) -> ``export-model``.
    Returns the paths of the store (3 expert episodes of 12 steps) and the checkpoint."""
    root = tmp_path_factory.mktemp("pile")
    store = root / "expert.zarr"
    wm = train_tiny_world_model(store, root, ["collect", "--task", "pilesweep", "--policy", "expert", "--episodes",
                                              "3", "--steps", "12", "--workers", "1", "--out", str(store),
                                              "--no-progress"])
    return {"store": store, "checkpoint": wm}
