from pathlib import Path

import pytest

from iwsim.data.collect import collect


@pytest.fixture(scope="session")
def play_store(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small 64 px play store shared by the training tests: 4 episodes of 12 steps."""
    path = tmp_path_factory.mktemp("data") / "play.zarr"
    collect("pusht", "play", 4, out=path, steps=12, image_size=64, workers=1, seed=0, progress=False)
    return path
