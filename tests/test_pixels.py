import numpy as np
import pytest

from iwsim.envs.pusht import geometry as geo
from iwsim.envs.pusht import pixels
from iwsim.envs.pusht.sim import GOAL_POSE, PALETTE, BimanualPushTEnv


@pytest.fixture(scope="module")
def frames():
    env = BimanualPushTEnv(64)
    rng = np.random.default_rng(7)
    out = []
    for k in range(6):
        state = env.sample_state(rng)
        if k % 2 == 0:
            state[4:] = GOAL_POSE + rng.normal(0, [0.02, 0.02, 0.2])
        obs, info = env.reset(options={"reset_to_state": state})
        out.append((obs["pixels"], info))
    env.close()
    return out


def test_pixel_iou_tracks_geometric_iou(frames):
    errs = [abs(pixels.pixel_iou(f) - info["iou"]) for f, info in frames]
    assert max(errs) < 0.04 and np.mean(errs) < 0.02
    batch = pixels.pixel_iou(np.stack([f for f, _ in frames]))
    assert batch.shape == (len(frames),)


def test_pose_estimator(frames):
    for f, info in frames:
        est = pixels.estimate_block_pose(f)
        assert est.found and est.fit_iou > 0.9
        assert np.linalg.norm(est.pose[:2] - info["block_pose"][:2]) < 0.003
        assert abs(geo.wrap_angle(est.pose[2] - info["block_pose"][2])) < np.radians(2)


def test_no_block_no_pose():
    table = np.round(np.array(PALETTE["table"]) * 255).astype(np.uint8)
    frame = np.broadcast_to(table, (64, 64, 3)).copy()
    assert not pixels.estimate_block_pose(frame).found
    assert pixels.block_fraction(frame).max() == 0.0
    assert pixels.pixel_iou(frame) == 0.0


def test_bad_frame_shape():
    with pytest.raises(ValueError, match="RGB"):
        pixels.pixel_iou(np.zeros((64, 64), np.uint8))


def test_colour_fractions_of_many_frames_are_those_of_each_frame(frames, monkeypatch):
    """More pixels than a pass models at once (``CHUNK_PIXELS``) go through in parts, with
    the same fractions as each frame alone."""
    from iwsim.envs.tabletop import palette

    monkeypatch.setattr(palette, "CHUNK_PIXELS", 3 * 64 * 64)
    stack = np.stack([f for f, _ in frames[:4]] * 2).reshape(2, 4, *frames[0][0].shape)
    names = ("block", "left", "right")
    many = pixels.colour_fractions(stack, names)
    assert many.shape == (2, 4, 3, *stack.shape[2:4])
    for i, j in np.ndindex(2, 4):
        np.testing.assert_array_equal(many[i, j], pixels.colour_fractions(stack[i, j], names))
