"""Stage 2: the dynamics network's causality, conditioning and streaming cache, and the
WorldModel built on it (tiny, randomly initialised models)."""

import numpy as np
import pytest
import torch

from iwsim.autoencoder import Autoencoder
from iwsim.config import AE_PRESETS, DYNAMICS_PRESETS, VARIANTS, variant
from iwsim.models.dynamics import Dynamics, DynamicsConfig, attention_layout, sequence_layout
from iwsim.training.checkpoint import CheckpointError, load_tensors, save_model_dir
from iwsim.world_model import StreamState, WorldModel

CFG = DynamicsConfig(window=4, channels=(8, 16), heads=2, emb_dim=16)
LOW, HIGH = [-0.22] * 4, [0.22] * 4


def randomise(module: torch.nn.Module, seed: int = 0, std: float = 0.2) -> torch.nn.Module:
    """Random weights everywhere (the zero-initialised output layers would hide bugs)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * std)
    return module.eval()


def tiny_world_model(seed: int = 0, name: str = "ours") -> WorldModel:
    """A tiny randomly initialised world model, ours or a benchmark variant (see VARIANTS)."""
    torch.manual_seed(seed)
    cfg = variant(DYNAMICS_PRESETS["tiny"], name)
    ae = Autoencoder(AE_PRESETS["tiny"])
    return WorldModel(ae, randomise(Dynamics(cfg.dynamics), seed), cfg, LOW, HIGH).eval()


def inputs(b: int, frames: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    z = torch.randn(b, frames, 4, 16, 16, generator=g)
    levels = torch.randint(0, 1000, (b, frames), generator=g)
    actions = torch.rand(b, frames, 4, generator=g) * 2 - 1
    known = torch.ones(b, frames)
    return z, levels, actions, known


@torch.no_grad()
def test_training_layout_is_causal():
    """Changing context frame k or its action changes no prediction of frames <= k."""
    net = randomise(Dynamics(CFG))
    n = 6
    times, is_ctx = sequence_layout(n)
    z, lv, a, known = inputs(2, 2 * n)
    v, _ = net(z, lv, lv, a, known, times, is_ctx)
    k = 3
    z2, a2 = z.clone(), a.clone()
    z2[:, k] += torch.randn(4, 16, 16)
    a2[:, k] = -a2[:, k]
    for zz, aa in ((z2, a), (z, a2)):
        w, _ = net(zz, lv, lv, aa, known, times, is_ctx)
        targets, new = w[:, n:], v[:, n:]  # target j predicts frame j + 1
        torch.testing.assert_close(targets[:, :k], new[:, :k], rtol=0, atol=1e-5)
        assert (targets[:, k] - new[:, k]).abs().max() > 1e-3  # frame k + 1 sees context k
    # a target never influences anything but itself
    z3 = z.clone()
    z3[:, n + 2] += torch.randn(4, 16, 16)
    w, _ = net(z3, lv, lv, a, known, times, is_ctx)
    changed = (w - v).flatten(2).abs().amax(-1).amax(0) > 1e-5
    assert changed.tolist() == [i == n + 2 for i in range(2 * n)]


@torch.no_grad()
def test_window_bounds_the_context():
    """Target k + 1 sees context frames k - N + 2 .. k, i.e. N - 1 of them, at the first layer:
    a frame N steps back only reaches it through deeper layers."""
    attn = randomise(Dynamics(CFG)).tattn1
    n = 8
    times, is_ctx = sequence_layout(n)
    y = torch.randn(1, 2 * n, 8, 16, 16)
    out, _, _ = attn(y, attention_layout(times, is_ctx, None, CFG.window), None, None)
    y2 = y.clone()
    y2[:, 0] += torch.randn(8, 16, 16)  # context frame 0 (a constant shift would be normalised away)
    out2, _, _ = attn(y2, attention_layout(times, is_ctx, None, CFG.window), None, None)
    moved = (out2 - out).flatten(2).abs().amax(-1)[0] > 1e-6
    # context queries 0..N-1 and targets at times 1..N-1 see frame 0; later ones do not
    expect = [t < CFG.window if c else 1 <= t <= CFG.window - 1 for t, c in zip(times.tolist(), is_ctx.tolist())]
    assert moved.tolist() == expect


@torch.no_grad()
def test_film_conditioning_uses_the_action():
    net = randomise(Dynamics(CFG))
    times, is_ctx = sequence_layout(3)
    z, lv, a, known = inputs(1, 6)
    v, _ = net(z, lv, lv, a, known, times, is_ctx)
    a2 = a.clone()
    a2[:, -1] += 0.5  # the last target's action
    w, _ = net(z, lv, lv, a2, known, times, is_ctx)
    assert (w[:, -1] - v[:, -1]).abs().mean() > 1e-3
    torch.testing.assert_close(w[:, :-1], v[:, :-1])
    # an unknown action is not the same as a zero action
    known2 = known.clone()
    known2[:, -1] = 0
    a3 = a.clone()
    a3[:, -1] = 0
    u, _ = net(z, lv, lv, a3, known, times, is_ctx)
    u2, _ = net(z, lv, lv, a3, known2, times, is_ctx)
    assert (u[:, -1] - u2[:, -1]).abs().mean() > 1e-3


@torch.no_grad()
def test_cached_steps_equal_uncached():
    """Streaming with the key/value cache gives what one pass over the whole history gives."""
    net = randomise(Dynamics(CFG))
    b, k = 2, 9
    z, _, a, known = inputs(b, k)
    known[:, 0] = 0
    lv = torch.full((b, k), 15)
    x = torch.randn(b, 4, 16, 16)
    t = torch.full((b, 1), 999)
    times = torch.arange(k)
    is_ctx = torch.tensor([True] * (k - 1) + [False])
    full, _ = net(torch.cat([z[:, :-1], x[:, None]], 1), torch.cat([lv[:, :-1], t], 1),
                  torch.cat([lv[:, :-1], t], 1), a, known, times, is_ctx)
    cache = None
    for i in range(k - 1):
        _, cache = net(z[:, i:i + 1], lv[:, i:i + 1], lv[:, i:i + 1], a[:, i:i + 1], known[:, i:i + 1],
                       times[i:i + 1], torch.tensor([True]), cache)
        assert len(cache) == min(i + 1, CFG.window - 1)
    streamed, _ = net(x[:, None], t, t, a[:, -1:], known[:, -1:], times[-1:], torch.tensor([False]), cache)
    torch.testing.assert_close(streamed[:, 0], full[:, -1], rtol=0, atol=1e-5)


def test_world_model_streaming_matches_full_recompute():
    """WorldModel.step (cached, two frames per pass) equals re-running the network over the
    whole history for the new frame."""
    wm = tiny_world_model()
    g = torch.Generator().manual_seed(1)
    z0 = torch.randn(1, 1, 4, 16, 16, generator=g)
    acts = torch.rand(7, 1, 4, generator=g) * 2 - 1
    wm.reset_latents(z0, seed=3)
    zs = [z0[:, 0]]
    for i in range(7):
        zs.append(wm.step_latent(acts[i]))
    # recompute the last step without a cache: context = frames 0..6, and the noise the
    # 7th step drew (replayed: reset, 6 steps, then draw)
    wm.reset_latents(z0, seed=3)
    for i in range(6):
        wm.step_latent(acts[i])
    cache_len = wm.state.context_frames
    assert cache_len == wm.cfg.dynamics.window - 1
    k = 7
    ctx = torch.stack(zs[:k], 1)
    x = wm._noise((4, 16, 16))
    lv = torch.full((1, k), wm.cfg.context_level)
    a = torch.cat([torch.zeros(1, 1, 4), acts[:6].transpose(0, 1), acts[6:].transpose(0, 1)], 1)
    known = torch.ones(1, k + 1)
    known[:, 0] = 0
    t = torch.full((1, 1), 999)
    with torch.no_grad():
        v, _ = wm.dynamics(torch.cat([ctx, x[:, None]], 1), torch.cat([lv, t], 1), torch.cat([lv, torch.zeros_like(t)], 1),
                           a, known, torch.arange(k + 1), torch.tensor([True] * k + [False]))
    from iwsim.diffusion.consistency import jump

    expect = jump(lambda *_: v[:, -1], wm.schedule, x, torch.full((1,), 999), torch.zeros(1, dtype=torch.long), None)
    torch.testing.assert_close(zs[-1], expect, rtol=0, atol=1e-4)


def test_sliding_window_keeps_a_constant_state():
    wm = tiny_world_model()
    wm.reset(np.zeros((2, 64, 64, 3), np.uint8))
    shapes = []
    for _ in range(3 * wm.cfg.dynamics.window):
        wm.step(np.zeros((2, 4), np.float32))
        shapes.append([tuple(k.shape) for k in wm.state.cache.keys])
    n = wm.cfg.dynamics.window
    assert all(s == shapes[n] for s in shapes[n:])
    assert shapes[n][0][2] == n - 1  # the cache holds N - 1 context frames


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
    wm = tiny_world_model()
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (2, 3, 64, 64, 3), dtype=np.uint8)
    wm.reset(frames, actions=np.zeros((2, 2, 4), np.float32))
    assert wm.state.context_frames == 2 and wm.step(np.zeros((2, 4))).shape == (2, 64, 64, 3)
    with pytest.raises(ValueError, match="actions"):
        wm.reset(frames)


@pytest.mark.parametrize("name", ["ours", "deterministic", "diffusion"])
def test_save_load_round_trip(tmp_path, name):
    wm = tiny_world_model(name=name)
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (1, 64, 64, 3), dtype=np.uint8)
    actions = rng.uniform(-0.2, 0.2, (1, 4, 4)).astype(np.float32)
    wm.save(tmp_path / "wm")
    back = WorldModel.load(tmp_path / "wm")
    assert back.image_size == 64 and back.action_dim == 4
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
    save_model_dir(tmp_path / "no_dyn", {k: v for k, v in tensors.items() if k.startswith("ae.")}, config)
    with pytest.raises(CheckpointError, match="no dynamics weights"):
        WorldModel.load(tmp_path / "no_dyn")
    save_model_dir(tmp_path / "no_norm", tensors, {k: v for k, v in config.items() if k != "action_norm"})
    with pytest.raises(CheckpointError, match="'action_norm'"):
        WorldModel.load(tmp_path / "no_norm")
    (tmp_path / "no_file").mkdir()
    with pytest.raises(CheckpointError, match="missing"):
        WorldModel.load(tmp_path / "no_file")


@pytest.mark.parametrize("name", VARIANTS)
def test_every_objective_trains(name):
    """The loss of each benchmark variant is finite, reaches every parameter, and a few
    steps on one batch lower it."""
    from iwsim.diffusion.edm import training_sigmas
    from iwsim.diffusion.schedule import Schedule
    from iwsim.training.dynamics import DynamicsTrainModule, DynBatch

    cfg = variant(DYNAMICS_PRESETS["tiny"], name)
    torch.manual_seed(0)
    module = DynamicsTrainModule(Dynamics(cfg.dynamics), Schedule(cfg.schedule), cfg.objective)
    g = torch.Generator().manual_seed(0)
    b, n = 2, 4
    lo, hi = cfg.context_levels
    z = torch.randn(b, n + 1, 4, 16, 16, generator=g)
    batch = DynBatch(z, torch.rand(b, n + 1, 4, generator=g) * 2 - 1, torch.ones(b, n + 1),
                     torch.randint(lo, hi, (b, n), generator=g), torch.randn(b, n, 4, 16, 16, generator=g),
                     torch.full((b, n), 999), torch.zeros(b, n, dtype=torch.long),
                     torch.randn(b, n, 4, 16, 16, generator=g), training_sigmas(b * n, g).view(b, n))
    opt = torch.optim.Adam(module.parameters(), lr=1e-3)
    losses = []
    for _ in range(5):
        loss, _ = module(batch)
        opt.zero_grad()
        loss.backward()
        losses.append(loss.item())
        if len(losses) == 1:
            assert all(p.grad is not None for p in module.parameters())
        opt.step()
    assert np.isfinite(losses).all() and losses[-1] < losses[0]


def test_unknown_objective_is_rejected():
    import dataclasses

    cfg = dataclasses.replace(DYNAMICS_PRESETS["tiny"], objective="gan")
    with pytest.raises(ValueError, match="unknown objective 'gan'"):
        WorldModel(Autoencoder(AE_PRESETS["tiny"]), Dynamics(cfg.dynamics), cfg, LOW, HIGH)
    with pytest.raises(ValueError, match="unknown variant"):
        variant(cfg, "best")


def test_states_of_rollouts_started_apart_share_a_step():
    """Rollouts at different steps, stepped together through StreamState.cat and split
    again, give what each gives alone (the play server's batching of sessions)."""
    wm = tiny_world_model()
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (2, 64, 64, 3), dtype=np.uint8)
    acts = rng.uniform(-0.2, 0.2, (2, 12, 4)).astype(np.float32)
    n = wm.cfg.dynamics.window
    alone_a = wm.rollout(frames[:1], acts[:1, :n + 3], seed=5)[0]
    alone_b = wm.rollout(frames[1:], acts[1:, :n + 1], seed=6)[0]

    def run(frame: np.ndarray, a: np.ndarray, seed: int, steps: int) -> StreamState:
        wm.reset(frame[None], seed=seed)
        for t in range(steps):
            wm.step(a[None, t])
        return wm.state

    state_a = run(frames[0], acts[0], 5, n + 1)  # a is 2 steps ahead of b
    state_b = run(frames[1], acts[1], 6, n - 1)
    assert state_a.context_frames == state_b.context_frames == n - 1 and state_a.tau != state_b.tau
    wm.state = StreamState.cat([state_a, state_b])
    together = wm.step(np.stack([acts[0, n + 1], acts[1, n - 1]]))
    assert np.abs(together[0].astype(int) - alone_a[n + 1]).max() <= 1
    assert np.abs(together[1].astype(int) - alone_b[n - 1]).max() <= 1
    next_a, next_b = wm.state.split()
    wm.state = next_a
    assert np.abs(wm.step(acts[0, n + 2][None])[0].astype(int) - alone_a[n + 2]).max() <= 1
    wm.state = next_b
    assert np.abs(wm.step(acts[1, n][None])[0].astype(int) - alone_b[n]).max() <= 1
    wm.reset(frames[:1])
    with pytest.raises(ValueError, match="context lengths"):
        StreamState.cat([wm.state, next_a])
