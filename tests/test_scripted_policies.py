import numpy as np
import pytest

from iwsim.envs.pusht import BimanualPushTEnv
from iwsim.envs.scripted import ExpertPolicy, make_policy, record_episode


@pytest.mark.slow
@pytest.mark.parametrize("source", ["state", "pixels"])
def test_expert_solves_an_episode(source):
    env = BimanualPushTEnv(64)
    pol = ExpertPolicy(pose_source=source)
    obs, info = env.reset(seed=100000)
    pol.reset(obs, info)
    best = 0.0
    for _ in range(150):
        obs, _, _, _, info = env.step(pol(obs, info))
        best = max(best, info["iou"])
    env.close()
    assert best >= 0.9


def test_play_touches_the_block_and_is_deterministic():
    a = record_episode("pusht", "play", seed=3, steps=80)
    b = record_episode("pusht", "play", seed=3, steps=80)
    assert all(np.array_equal(a[k], b[k]) for k in a)
    assert (a["n_contacts"] > 0).mean() > 0.15
    assert np.abs(np.diff(a["block_pose"], axis=0)).sum() > 0.05  # the block moved


def test_unknown_policy():
    with pytest.raises(ValueError, match="unknown policy"):
        make_policy("dance", 0)
