"""The WorldModel (tiny, random weights): the sliding window, batching, resets from several
frames, the functional core under the stateful wrapper, its latents mode, joining and
splitting states, checkpoints, and bad input."""

import json

import numpy as np
import pytest
import torch

from iwsim.core.checkpoint import CheckpointError, load_tensors, save_model_dir
from iwsim.data.frames import to_uint8
from iwsim.world_model import StreamState, WorldModel
from iwsim.world_model.presets import VARIANTS
from tests.conftest import imports_dynamo
from tests.test_dynamics import tiny_world_model


def test_the_window_slides_and_keeps_a_constant_state():
    wm = tiny_world_model()
    wm.reset(np.zeros((2, 64, 64, 3), np.uint8))
    k = wm.cfg.dynamics.context
    shapes = set()
    for _ in range(3 * k):
        wm.step(np.zeros((2, 4), np.float32))
        shapes.add(tuple(wm.state.context.shape))
    assert shapes == {(2, k, 4, 16, 16)}


@pytest.mark.parametrize("name", VARIANTS)
def test_batched_step_equals_per_item_steps(name):
    wm = tiny_world_model(name=name)
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (3, 64, 64, 3), dtype=np.uint8)
    actions = rng.uniform(-0.2, 0.2, (3, 5, 4)).astype(np.float32)
    batched = wm.rollout(frames, actions, seed=[10, 11, 12])
    for i in range(3):
        single = wm.rollout(frames[i:i + 1], actions[i:i + 1], seed=10 + i)
        assert np.abs(single[0].astype(int) - batched[i].astype(int)).max() <= 1


def test_reset_with_several_context_frames():
    """Fewer frames than the window are padded with the first; more keep the last K."""
    wm = tiny_world_model()
    k = wm.cfg.dynamics.context
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (2, k + 2, 64, 64, 3), dtype=np.uint8)
    wm.reset(frames, actions=np.zeros((2, k + 1, 4), np.float32))
    assert wm.state.context.shape[1] == k and bool(wm.state.known.all())
    torch.testing.assert_close(wm.state.context, wm.standardize(wm.encode(frames[:, 2:].reshape(-1, 64, 64, 3))
                                                                 ).view(2, k, 4, 16, 16))
    assert wm.step(np.zeros((2, 4))).shape == (2, 64, 64, 3)
    wm.reset(frames[:, 0])
    assert not bool(wm.state.known.any())
    torch.testing.assert_close(wm.state.context[:, 0], wm.state.context[:, -1])
    with pytest.raises(ValueError, match="actions"):
        wm.reset(frames)


@pytest.mark.parametrize("name", ["ours", "deterministic", "diffusion", "film-actions"])
def test_save_load_round_trip(tmp_path, name):
    wm = tiny_world_model(name=name)
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (1, 64, 64, 3), dtype=np.uint8)
    actions = rng.uniform(-0.2, 0.2, (1, 4, 4)).astype(np.float32)
    wm.save(tmp_path / "wm")
    back = WorldModel.load(tmp_path / "wm")
    assert back.image_size == 64 and back.action_dim == 4 and back.cfg == wm.cfg
    np.testing.assert_array_equal(back.rollout(frames, actions), wm.rollout(frames, actions))
    with pytest.raises(FileExistsError):
        wm.save(tmp_path / "wm")


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_actions_are_rejected(bad):
    wm = tiny_world_model()
    wm.reset(np.zeros((1, 64, 64, 3), np.uint8))
    a = np.zeros((1, 4), np.float32)
    a[0, 2] = bad
    with pytest.raises(ValueError, match=f"finite, got {bad}"):
        wm.step(a)


def test_bad_shapes_and_frames_are_rejected():
    wm = tiny_world_model()
    with pytest.raises(RuntimeError, match="reset"):
        wm.step(np.zeros((1, 4)))
    with pytest.raises(ValueError, match="uint8"):
        wm.reset(np.zeros((1, 64, 64, 3), np.float32))
    with pytest.raises(ValueError, match="H = W = 64"):
        wm.reset(np.zeros((1, 96, 96, 3), np.uint8))
    wm.reset(np.zeros((2, 64, 64, 3), np.uint8))
    for shape in [(4,), (2, 3), (1, 4), (2, 4, 1)]:
        with pytest.raises(ValueError, match="shape"):
            wm.step(np.zeros(shape))


def test_checkpoint_missing_a_part(tmp_path):
    wm = tiny_world_model()
    wm.save(tmp_path / "wm")
    tensors = load_tensors(tmp_path / "wm" / "model.safetensors")
    config = WorldModel.load(tmp_path / "wm").describe()
    save_model_dir(tmp_path / "no_dyn", {k: v for k, v in tensors.items() if k.startswith("codec.")}, config)
    with pytest.raises(CheckpointError, match="no dynamics weights"):
        WorldModel.load(tmp_path / "no_dyn")
    save_model_dir(tmp_path / "no_norm", tensors, {k: v for k, v in config.items() if k != "action_norm"})
    with pytest.raises(CheckpointError, match="'action_norm'"):
        WorldModel.load(tmp_path / "no_norm")
    (tmp_path / "no_file").mkdir()
    with pytest.raises(CheckpointError, match="missing"):
        WorldModel.load(tmp_path / "no_file")


def test_states_of_rollouts_started_apart_share_a_step():
    """Rollouts at different steps, stepped together through StreamState.cat and split
    again, give what each gives alone (the play server's batching of sessions)."""
    wm = tiny_world_model()
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (2, 64, 64, 3), dtype=np.uint8)
    acts = rng.uniform(-0.2, 0.2, (2, 12, 4)).astype(np.float32)
    alone_a = wm.rollout(frames[:1], acts[:1, :6], seed=5)[0]
    alone_b = wm.rollout(frames[1:], acts[1:, :4], seed=6)[0]

    def run(frame: np.ndarray, a: np.ndarray, seed: int, steps: int) -> StreamState:
        wm.reset(frame[None], seed=seed)
        for t in range(steps):
            wm.step(a[None, t])
        return wm.state

    state_a = run(frames[0], acts[0], 5, 4)  # a is 2 steps ahead of b
    state_b = run(frames[1], acts[1], 6, 2)
    wm.state = StreamState.cat([state_a, state_b])
    together = wm.step(np.stack([acts[0, 4], acts[1, 2]]))
    assert np.abs(together[0].astype(int) - alone_a[4]).max() <= 1
    assert np.abs(together[1].astype(int) - alone_b[2]).max() <= 1
    next_a, next_b = wm.state.split()
    wm.state = next_a
    assert np.abs(wm.step(acts[0, 5][None])[0].astype(int) - alone_a[5]).max() <= 1
    wm.state = next_b
    assert np.abs(wm.step(acts[1, 3][None])[0].astype(int) - alone_b[3]).max() <= 1


def test_the_functional_core_equals_the_stateful_wrapper_and_keeps_no_state():
    wm = tiny_world_model()
    rng = np.random.default_rng(1)
    frames = rng.integers(0, 256, (2, 64, 64, 3), dtype=np.uint8)
    acts = rng.uniform(-0.2, 0.2, (2, 5, 4)).astype(np.float32)
    expected = wm.rollout(frames, acts, seed=3)
    wm.reset(frames[:1], seed=9)
    held = wm.state
    state = wm.reset_state(frames, seed=3)
    out = []
    for t in range(acts.shape[1]):
        context = state.context.clone()
        new, frame = wm.step_state(state, acts[:, t])
        assert torch.equal(state.context, context) and new is not state  # the old state is left as it was
        state = new
        out.append(frame)
    np.testing.assert_array_equal(np.stack(out, 1), expected)
    assert wm.state is held  # the wrapper's rollout is untouched


@pytest.mark.parametrize("reencode", [False, True])
def test_the_latents_mode_is_the_same_step_in_the_models_units(reencode, monkeypatch):
    """``latents=True`` steps as the frames mode does, in the model's units: decoding its
    latents from where the generators stand gives the frame, and it decodes nothing itself
    unless ``reencode``, which both modes apply alike (the same states), one decoding per step."""
    wm = tiny_world_model()
    wm.reencode = reencode
    rng = np.random.default_rng(2)
    frames = rng.integers(0, 256, (2, 64, 64, 3), dtype=np.uint8)
    acts = rng.uniform(-0.2, 0.2, (2, 4, 4)).astype(np.float32)
    decodes = []
    decode = wm.codec.decode
    monkeypatch.setattr(wm.codec, "decode", lambda *args: decodes.append(1) or decode(*args))
    frames_state = wm.reset_state(frames, seed=3)
    latents_state = wm.reset_state(wm.encode(frames)[:, None], seed=3, latents=True)
    assert torch.equal(latents_state.context, frames_state.context)
    for t in range(acts.shape[1]):
        frames_state, frame = wm.step_state(frames_state, acts[:, t])
        assert len(decodes) == 1
        latents_state, z = wm.step_state(latents_state, wm.normalize_actions(acts[:, t]), latents=True)
        assert len(decodes) == 1 + reencode and z.shape == (2, 4, 16, 16)
        if not reencode:
            np.testing.assert_array_equal(to_uint8(wm.decode_latents(z, latents_state.generators)), frame)
        assert torch.equal(latents_state.context, frames_state.context)
        decodes.clear()
    with pytest.raises(ValueError, match="context latents"):
        wm.reset_state(wm.encode(frames), latents=True)


def test_loading_a_world_model_leaves_torch_dynamo_unimported(tmp_path):
    """Building a consistency decoder on the meta device (to count its weights before
    loading) computed its noise schedule through torch's reference ops, whose first use
    imports torch._dynamo: 2-3 s more for every process that loaded such a model."""
    path = tiny_world_model().save(tmp_path / "wm")
    assert json.loads((path / "config.json").read_text())["codec"]["kind"] == "consistency-ae"
    assert not imports_dynamo("from iwsim.world_model import WorldModel; WorldModel.load(sys.argv[1])", path)
