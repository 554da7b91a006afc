"""ACT (iwsim.policies.act.model): overfitting, the execution contract, temporal ensembling as
the paper's Algorithm 2, save/load, bad input. Tiny configs; one torch thread."""

import dataclasses

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from iwsim.core.config import from_dict, to_dict
from iwsim.policies.act.config import ACTConfig
from iwsim.policies.act.model import ACTPolicy, TemporalEnsemble
from iwsim.policies.common import Normalizer, PolicyBatch

pytestmark = pytest.mark.usefixtures("one_thread")

TINY = ACTConfig(chunk_size=4, dim=32, heads=2, enc_layers=1, dec_layers=1, vae_layers=1, ff_dim=64, dropout=0.0,
                 latent_dim=8, encoder_channels=(8, 8, 8), temporal_ensemble=0.01)
LOW, HIGH = np.array([0.0, -1.0, 10.0, 0.0]), np.array([1.0, 1.0, 12.0, 0.5])  # data units of actions and agent_pos


def make_policy(cfg: ACTConfig = TINY, seed: int = 0) -> ACTPolicy:
    torch.manual_seed(seed)
    return ACTPolicy(cfg, Normalizer(LOW, HIGH), Normalizer(LOW, HIGH))


def make_obs(b: int, seed: int = 0, size: int = 32, steps: int = 1, state_dim: int = 4) -> dict:
    rng = np.random.default_rng(seed)
    return {"image": rng.integers(0, 256, (b, steps, size, size, 3), dtype=np.uint8),
            "agent_pos": rng.uniform(LOW[:state_dim], HIGH[:state_dim], (b, steps, state_dim)).astype(np.float32)}


def make_batch(b: int = 4, tp: int = 6, seed: int = 0) -> PolicyBatch:
    g = torch.Generator().manual_seed(seed)
    pad = torch.zeros(b, tp, dtype=torch.bool)
    pad[0, 2:] = True  # one window runs past its episode's end, inside the chunk
    return PolicyBatch(torch.rand(b, 1, 3, 32, 32, generator=g) * 2 - 1, torch.rand(b, 1, 4, generator=g) * 2 - 1,
                       torch.rand(b, tp, 4, generator=g) * 2 - 1, pad)


@pytest.mark.parametrize("tokens, stride", [("cells", 1), ("keypoints", 1), ("cells", 2)])
def test_overfits_a_handful_of_transitions(tokens, stride):
    policy = make_policy(dataclasses.replace(TINY, image_tokens=tokens, keypoints=8, encoder_stride=stride))
    batch = make_batch()
    opt = torch.optim.Adam(policy.parameters(), lr=1e-3)
    losses, l1s = [], []
    for _ in range(100):
        loss, metrics = policy(batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
        l1s.append(metrics["l1"])
    assert set(metrics) == {"l1", "kl"}
    assert losses[-1] < 0.1 * losses[0] and l1s[-1] < 0.3 * l1s[0]
    # Inference (z = 0) reproduces the demonstrated chunks too, where they are not padding.
    image = ((batch.image.permute(0, 1, 3, 4, 2) + 1) * 127.5).round().to(torch.uint8)
    obs = {"image": image.numpy(), "agent_pos": policy.state_norm.unnormalize(batch.agent_pos).numpy()}
    err = (policy.action_norm.normalize(policy.predict_chunk(obs)) - batch.action[:, :4]).abs()
    assert err[~batch.action_is_pad[:, :4]].mean() < 0.3 * l1s[0]


def test_loss_ignores_padded_actions():
    policy = make_policy()
    batch = make_batch()
    changed = dataclasses.replace(batch, action=batch.action.clone())
    changed.action[0, 2:] = 5.0  # only padded positions of the chunk (and beyond it) change
    torch.manual_seed(1)
    a = policy(batch)[0].item()
    torch.manual_seed(1)
    b = policy(changed)[0].item()
    assert a == pytest.approx(b, rel=1e-6)


def test_observe_state_false_acts_from_the_image_alone():
    obs = make_obs(3)
    moved = {**obs, "agent_pos": make_obs(3, seed=1)["agent_pos"]}  # the same images, other pusher positions
    blind = make_policy(dataclasses.replace(TINY, observe_state=False))
    np.testing.assert_array_equal(blind.predict_chunk(obs).numpy(), blind.predict_chunk(moved).numpy())
    seeing = make_policy()
    assert not np.allclose(seeing.predict_chunk(obs).numpy(), seeing.predict_chunk(moved).numpy())


@pytest.mark.parametrize("m, steps", [(0.01, 1), (None, 1), (None, 3)])
def test_predict_action_returns_ta_actions_in_bounds(m, steps):
    policy = make_policy(dataclasses.replace(TINY, temporal_ensemble=m, n_action_steps=steps))
    with torch.no_grad():
        policy.action_head.bias.fill_(3.0)  # push raw outputs out of [-1, 1]: they are clipped to the data's range
    policy.reset()
    for call in range(3):
        act = policy.predict_action(make_obs(2, seed=call))
        assert act.shape == (2, steps, 4) and act.dtype == np.float32
        assert np.all(act >= LOW - 1e-6) and np.all(act <= HIGH + 1e-6)


def ensemble_by_hand(chunks: list[np.ndarray], m: float) -> np.ndarray:
    """The original code's form: a table of every prediction per (query step, step),
    weights exp(-m i) over the predictions for step t, the oldest first."""
    n, (b, k, a) = len(chunks), chunks[0].shape
    table = np.full((n, n + k, b, a), np.nan)
    out = []
    for t, chunk in enumerate(chunks):
        table[t, t:t + k] = chunk.transpose(1, 0, 2)
        preds = table[:t + 1, t][~np.isnan(table[:t + 1, t, 0, 0])]  # (n_t, B, A), query order
        w = np.exp(-m * np.arange(len(preds)))
        out.append((w[:, None, None] * preds).sum(0) / w.sum())
    return np.stack(out, 1)  # (B, T, A)


def patch_chunks(monkeypatch: pytest.MonkeyPatch, policy: ACTPolicy, chunks: list[np.ndarray]) -> None:
    it = iter(chunks)
    monkeypatch.setattr(policy, "predict_chunk", lambda obs: torch.from_numpy(next(it)).float())


@pytest.mark.parametrize("m", [0.01, 0.7, 0.0])
def test_temporal_ensemble_is_the_papers_weighted_average(monkeypatch, m):
    k = TINY.chunk_size
    policy = make_policy(dataclasses.replace(TINY, temporal_ensemble=m))
    rng = np.random.default_rng(0)
    chunks = [rng.normal(size=(3, k, 4)) for _ in range(7)]  # more steps than k: old predictions drop out
    patch_chunks(monkeypatch, policy, chunks)
    got = np.concatenate([policy.predict_action(make_obs(3)) for _ in chunks], 1)
    np.testing.assert_allclose(got, ensemble_by_hand(chunks, m), rtol=1e-5, atol=1e-5)
    # Step 1 spelled out: chunk 0's second action (w_0 = 1) and chunk 1's first (w_1 = e^-m).
    w1 = np.exp(-m)
    np.testing.assert_allclose(got[:, 1], (chunks[0][:, 1] + w1 * chunks[1][:, 0]) / (1 + w1), rtol=1e-5, atol=1e-6)


def test_reset_forgets_and_items_are_independent(monkeypatch):
    k, m = TINY.chunk_size, 0.5
    rng = np.random.default_rng(1)
    chunks = [rng.normal(size=(2, k, 4)) for _ in range(5)]
    policy = make_policy(dataclasses.replace(TINY, temporal_ensemble=m))
    patch_chunks(monkeypatch, policy, chunks + chunks[:2])
    both = np.concatenate([policy.predict_action(make_obs(2)) for _ in range(5)], 1)
    policy.reset()
    after = [policy.predict_action(make_obs(2)) for _ in range(2)]
    np.testing.assert_allclose(np.concatenate(after, 1), both[:, :2], rtol=1e-6)  # as a fresh episode
    np.testing.assert_array_equal(after[0][:, 0], chunks[0][:, 0].astype(np.float32))
    for i in range(2):  # each batch item alone gives what it got in the batch
        alone = TemporalEnsemble(m, k)
        solo = torch.stack([alone.update(torch.from_numpy(c[i:i + 1]).float()) for c in chunks], 1).numpy()
        np.testing.assert_allclose(solo[0], both[i], rtol=1e-6)
    with pytest.raises(ValueError, match="call reset"):
        alone.update(torch.zeros(2, k, 4))


def test_save_load_round_trip_carries_normalisation(tmp_path):
    policy = make_policy(seed=0)
    opt = torch.optim.Adam(policy.parameters(), lr=1e-3)
    loss, _ = policy(make_batch())
    loss.backward()
    opt.step()
    save_file(policy.state_dict(), tmp_path / "model.safetensors")
    cfg = from_dict(ACTConfig, to_dict(TINY))  # as config.json stores it
    assert cfg == TINY
    torch.manual_seed(1)  # other initial weights, to be overwritten
    fresh = ACTPolicy(cfg, Normalizer(np.zeros(4), np.ones(4)), Normalizer(np.zeros(4), np.ones(4)))
    fresh.load_state_dict(load_file(tmp_path / "model.safetensors"))
    torch.testing.assert_close(fresh.action_norm.high, policy.action_norm.high)
    for call in range(3):
        obs = make_obs(2, seed=call)
        np.testing.assert_array_equal(fresh.predict_action(obs), policy.predict_action(obs))


def test_bad_input_is_a_clear_error():
    policy = make_policy()
    with pytest.raises(ValueError, match="observes 1 steps, got 2"):
        policy.predict_action(make_obs(2, steps=2))
    with pytest.raises(ValueError, match="4-D agent_pos, got 3"):
        policy.predict_action(make_obs(2, state_dim=3))
    short = make_batch(tp=TINY.chunk_size - 1)
    with pytest.raises(ValueError, match=r"expected action \(B, >=4, 4\)"):
        policy(short)
    with pytest.raises(ValueError, match="n_action_steps must be 1"):
        dataclasses.replace(TINY, n_action_steps=2)
    with pytest.raises(ValueError, match="obs_horizon must be 1"):
        dataclasses.replace(TINY, obs_horizon=2)
    with pytest.raises(ValueError, match="image_tokens must be 'cells' or 'keypoints', got 'pixels'"):
        dataclasses.replace(TINY, image_tokens="pixels")
    with pytest.raises(ValueError, match="encoder_stride must be 1 or 2, got 4"):
        dataclasses.replace(TINY, encoder_stride=4)
