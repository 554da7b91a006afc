from pathlib import Path

import pytest
import torch

from iwsim.data.collect import collect

# Files whose every test is end to end (a demo run, the shipped checkpoint against MuJoCo).
SLOW_FILES = ("test_demo.py", "test_shipped_checkpoint.py")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if item.path.name in SLOW_FILES:
            item.add_marker(pytest.mark.slow)


@pytest.fixture(scope="session")
def play_store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small 64 px play store shared by the training tests: 4 episodes of 12 steps."""
    path = tmp_path_factory.mktemp("data") / "play.zarr"
    collect("pusht", "play", 4, out=path, steps=12, image_size=64, workers=1, seed=0, progress=False)
    return path


@pytest.fixture
def one_thread():
    """Tiny networks on two cores shared with other jobs: torch's default two threads
    oversubscribe them (tens of times slower here), one thread does not."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
