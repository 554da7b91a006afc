"""Stage 2: the dynamics network, its objectives and unrolled training (tiny models), and a
short training run that must learn to use its actions. The WorldModel built on it:
``test_world_model.py``; ``tiny_world_model`` here is the other tests' tiny model."""

import dataclasses

import numpy as np
import pytest
import torch

from iwsim.core.errors import InputError
from iwsim.diffusion.edm import training_sigmas
from iwsim.world_model import WorldModel
from iwsim.world_model.codecs.consistency import Autoencoder
from iwsim.world_model.dynamics import Dynamics, DynamicsConfig, blobs, widen_window
from iwsim.world_model.dynamics_data import DynBatch, latent_stats
from iwsim.world_model.presets import AE_PRESETS, DYNAMICS_PRESETS, VARIANTS, variant
from iwsim.world_model.train_dynamics import DynamicsTrainModule

LOW, HIGH = [-0.22] * 4, [0.22] * 4
POINTS = {"point_index": ((0, 1), (2, 3)), "point_scale": (0.22 / 0.26,) * 4, "point_offset": (0.0,) * 4}


def randomise(module: torch.nn.Module, seed: int = 0, std: float = 0.2) -> torch.nn.Module:
    """Random weights everywhere (the zero-initialised output layers would hide bugs)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * std)
    return module.eval()


STATE = {"state_dim": 4, "state_point_scale": (0.2 / 0.26,) * 4, "state_point_offset": (0.0,) * 4,
         "state_action_scale": (0.22 / 0.2,) * 4, "state_action_offset": (0.0,) * 4}


def tiny_cfg(name: str = "ours"):
    """The tiny preset as variant ``name``, with the sizes training takes from T-push data
    (its points; the pushers' state for the ``state`` variant)."""
    cfg = variant(DYNAMICS_PRESETS["tiny"], name)
    points = POINTS if cfg.dynamics.positional_actions else {}
    state = STATE if cfg.predict_state and points else {"state_dim": 4} if cfg.predict_state else {}
    return dataclasses.replace(cfg, dynamics=dataclasses.replace(cfg.dynamics, **points, **state))


def tiny_world_model(seed: int = 0, name: str = "ours", **inference) -> WorldModel:
    """A tiny randomly initialised world model, ours or a benchmark variant (see VARIANTS),
    with ``inference`` options of the stage-2 config (e.g. ``rest_threshold``)."""
    torch.manual_seed(seed)
    cfg = dataclasses.replace(tiny_cfg(name), **inference)
    ae = Autoencoder(AE_PRESETS["tiny"])
    state = ([-0.2] * 4, [0.2] * 4) if cfg.dynamics.state_dim else ((), ())
    return WorldModel(ae, randomise(Dynamics(cfg.dynamics), seed), cfg, LOW, HIGH, None, 1.0, *state).eval()


def test_blobs_sit_where_the_action_points():
    """A position in image coordinates (x right, y up) peaks in the latent cell under it."""
    pos = torch.tensor([[[-1 + 2 * 3.5 / 16, 1 - 2 * 10.5 / 16, 0.0, 0.0]]])  # cell (row 10, col 3)
    b = blobs(pos, ((0, 1), (2, 3)), 16, 0.75)
    assert b.shape == (1, 1, 2, 16, 16)
    assert divmod(int(b[0, 0, 0].argmax()), 16) == (10, 3)
    assert divmod(int(b[0, 0, 1].argmax()), 16) in {(7, 7), (7, 8), (8, 7), (8, 8)}  # the centre
    assert b.max() == pytest.approx(1.0, abs=0.05)


@torch.no_grad()
def test_a_scene_at_rest_stays_at_rest_while_the_setpoint_holds():
    """``rest_threshold``: from a still start whose held setpoint is known, every next
    latent is the first one exactly while the setpoint holds, and a moving setpoint
    changes it; off (0), a still scene creeps; with the held setpoint unknown, the first
    step is the network's."""
    size = tiny_world_model().image_size
    frame = torch.randint(0, 256, (2, size, size, 3), generator=torch.Generator().manual_seed(0), dtype=torch.uint8)
    held = torch.tensor([[0.1, -0.2, 0.3, 0.0]] * 2)
    for threshold in (0.05, 0.0):
        wm = tiny_world_model(rest_threshold=threshold)
        z0 = wm.encode(frame)
        wm.reset(z0[:, None], held=held, latents=True)
        still = [torch.equal(wm.step(held, latents=True), z0) for _ in range(4)]
        assert still == [threshold > 0] * 4
        assert not torch.equal(wm.step(held + 0.1, latents=True), z0)
    wm = tiny_world_model(rest_threshold=0.05)
    wm.reset(z0[:, None], latents=True)
    assert not torch.equal(wm.step(held, latents=True), z0)


@pytest.mark.parametrize("spatial,film", [(True, False), (False, True)])
@torch.no_grad()
def test_every_action_pathway_reaches_the_output(spatial, film):
    """Wiring only (an untrained network): the output depends on the current and the
    previous action through the pathway that is switched on."""
    cfg = DynamicsConfig(context=2, channels=8, blocks=2, heads=2, emb_dim=16, action_channels=2,
                         spatial_actions=spatial, action_film=film)
    net = randomise(Dynamics(cfg))
    g = torch.Generator().manual_seed(0)
    x, ctx = torch.randn(2, 4, 16, 16, generator=g), torch.randn(2, 2, 4, 16, 16, generator=g)
    t, s, lab = torch.full((2,), 999.0), torch.zeros(2), torch.full((2,), 100.0)
    a = torch.rand(2, 2, 4, generator=g) * 2 - 1
    out = net(x, ctx, t, s, lab, a)
    for k in (0, 1):
        a2 = a.clone()
        a2[:, k] = -a2[:, k]
        assert (net(x, ctx, t, s, lab, a2) - out).abs().max() > 1e-3


@torch.no_grad()
def test_the_unet_variant_runs_its_middle_at_half_resolution():
    """down=1: the attention sees an 8 x 8 grid of twice the channels for a 16 x 16 latent, the
    output keeps the latent's shape and every cell still reaches every other; down=0 has the
    parameters every earlier model was saved with."""
    cfg = DynamicsConfig(context=2, channels=8, blocks=4, heads=2, emb_dim=16, action_channels=2, down=1)
    net = randomise(Dynamics(cfg))
    seen = []
    net.attn.register_forward_hook(lambda m, i, o: seen.append(tuple(i[0].shape)))
    g = torch.Generator().manual_seed(0)
    x, ctx = torch.randn(2, 4, 16, 16, generator=g), torch.randn(2, 2, 4, 16, 16, generator=g)
    t, s, lab, a = torch.full((2,), 999.0), torch.zeros(2), torch.full((2,), 100.0), torch.zeros(2, 2, 4)
    out = net(x, ctx, t, s, lab, a)
    assert out.shape == x.shape and seen == [(2, 16, 8, 8)]
    far = ctx.clone()
    far[:, :, :, 0, 0] += 1.0  # one corner cell of the window moves the opposite corner
    assert (net(x, far, t, s, lab, a) - out)[:, :, -1, -1].abs().max() > 1e-4
    flat = {k.split(".")[0] for k in Dynamics(dataclasses.replace(cfg, down=0)).state_dict()}
    assert not flat & {"down", "up", "blocks_in", "blocks_out"}
    with pytest.raises(InputError, match="down takes 0 or 1"):
        Dynamics(dataclasses.replace(cfg, down=2))
    with pytest.raises(InputError, match="even latent size"):
        Dynamics(dataclasses.replace(cfg, latent_size=15))


@torch.no_grad()
def test_a_widened_window_computes_the_same_function_whatever_the_older_latents():
    """widen_window: a 2-latent network made into a 5-latent one gives the same output
    for any 3 older latents, and they reach it once their weights move."""
    cfg = DynamicsConfig(context=2, channels=8, blocks=2, heads=2, emb_dim=16, action_channels=2)
    net = randomise(Dynamics(cfg))
    wide = Dynamics(dataclasses.replace(cfg, context=5))
    wide.load_state_dict(widen_window(net.state_dict(), cfg, 5))
    g = torch.Generator().manual_seed(0)
    x, ctx, older = (torch.randn(2, *shape, generator=g) for shape in ((4, 16, 16), (2, 4, 16, 16), (3, 4, 16, 16)))
    t, s, lab, a = torch.full((2,), 999.0), torch.zeros(2), torch.full((2,), 100.0), torch.rand(2, 2, 4) * 2 - 1
    out = net(x, ctx, t, s, lab, a)
    torch.testing.assert_close(wide(x, torch.cat([older, ctx], 1), t, s, lab, a), out, atol=1e-5, rtol=0)
    wide.conv_in.weight.add_(0.1)
    assert (wide(x, torch.cat([older, ctx], 1), t, s, lab, a) - wide(x, torch.cat([-older, ctx], 1), t, s, lab, a)
            ).abs().max() > 1e-3
    with pytest.raises(InputError, match="can only be widened: the model holds 2 latents, asked for 1"):
        widen_window(net.state_dict(), cfg, 1)


def batch_for(cfg, z: torch.Tensor, actions: torch.Tensor, g: torch.Generator) -> DynBatch:
    """A DynBatch of windows z (B, K+n, C, h, w) and actions (B, n+1, A) with random noise."""
    b, k = z.shape[0], cfg.dynamics.context
    n = z.shape[1] - k
    lo, hi = cfg.context_sigma
    return DynBatch(z, actions, lo + (hi - lo) * torch.rand(b, n, generator=g),
                    torch.randn(b, n, k, *z.shape[2:], generator=g), torch.full((b, n), 999),
                    torch.zeros(b, n, dtype=torch.long), training_sigmas(b * n, g).view(b, n),
                    torch.randn(b, n, *z.shape[2:], generator=g), torch.randn(b, n, *z.shape[2:], generator=g),
                    torch.rand(b, n + 1, cfg.dynamics.state_dim, generator=g) * 2 - 1 if cfg.dynamics.state_dim
                    else None)


@pytest.mark.parametrize("name", VARIANTS)
def test_every_variant_trains(name):
    """The unrolled loss of each variant is finite, reaches every parameter, and a few
    steps on one batch lower it."""
    cfg = tiny_cfg(name)
    torch.manual_seed(0)
    module = DynamicsTrainModule(Dynamics(cfg.dynamics), cfg)
    g = torch.Generator().manual_seed(0)
    b, n, k = 2, 3, cfg.dynamics.context
    batch = batch_for(cfg, torch.randn(b, k + n, 4, 16, 16, generator=g), torch.rand(b, n + 1, 4, generator=g) * 2 - 1,
                      g)
    opt = torch.optim.Adam(module.parameters(), lr=1e-3)
    losses = []
    for _ in range(5):
        loss, parts = module(batch)
        opt.zero_grad()
        loss.backward()
        losses.append(loss.item())
        if len(losses) == 1:
            assert parts["unroll"] == n
            unused = {"action_mlp"} if not cfg.dynamics.action_film else {"action_grid"}
            assert all(p.grad is not None for name_, p in module.named_parameters()
                       if name_.split(".")[1] not in unused)
        opt.step()
    assert np.isfinite(losses).all() and losses[-1] < losses[0]


@pytest.mark.parametrize("through,every", [(True, 0), (False, 0), (True, 1), (True, 3)])
def test_the_gradient_reaches_the_first_unrolled_step(through, every):
    """With ``unroll_grad`` the last prediction's loss depends, through the fed-back
    predictions, on what the first one saw (its context noise); detached, or cut after
    every prediction (``unroll_grad_every`` 1), it does not; cut every 3 (beyond these 3
    predictions) it does."""
    cfg = dataclasses.replace(tiny_cfg(), unroll_grad=through, unroll_grad_every=every)
    torch.manual_seed(0)
    module = DynamicsTrainModule(randomise(Dynamics(cfg.dynamics)), cfg)
    g = torch.Generator().manual_seed(0)
    b, n, k = 2, 3, cfg.dynamics.context
    batch = batch_for(cfg, torch.randn(b, k + n, 4, 16, 16, generator=g), torch.rand(b, n + 1, 4, generator=g) * 2 - 1,
                      g)
    batch.ctx_eps.requires_grad_(True)
    module.unroll(batch)[0][:, -1].sum().backward()
    first = batch.ctx_eps.grad[:, 0].abs().max().item()
    assert (first > 0) == (through and every != 1)
    assert batch.ctx_eps.grad[:, -1].abs().max().item() > 0


def test_latent_stats_in_passes_match_the_whole_at_once():
    g = torch.Generator().manual_seed(0)
    latents = (torch.randn(300, 4, 3, 3, generator=g) * 2 + 5).half()
    idx = np.arange(0, 300, 3)
    mean, scale = latent_stats(latents, idx, block=7)
    whole = latents[torch.from_numpy(idx)].float()
    torch.testing.assert_close(mean, whole.mean(0))
    assert scale == pytest.approx(float(whole.var(0).mean().sqrt()), rel=1e-5)


def test_unknown_objective_is_rejected():
    cfg = dataclasses.replace(DYNAMICS_PRESETS["tiny"], objective="gan")
    with pytest.raises(ValueError, match="unknown objective 'gan'"):
        WorldModel(Autoencoder(AE_PRESETS["tiny"]), Dynamics(cfg.dynamics), cfg, LOW, HIGH)
    with pytest.raises(ValueError, match="unknown variant"):
        variant(cfg, "best")
    with pytest.raises(ValueError, match="unknown variant 'best'"):
        variant(cfg, "long-unroll+best")


def test_variants_joined_by_plus_apply_in_turn():
    """A baseline trained like ours (``long-unroll+deterministic``) changes both."""
    cfg = DYNAMICS_PRESETS["pusht-64"]
    both = variant(cfg, "long-unroll+deterministic")
    assert both.unroll == variant(cfg, "long-unroll").unroll != cfg.unroll
    assert both.objective == "regression" and both.unroll_grad_every == 8
    assert variant(cfg, "window-6+no-points").dynamics == dataclasses.replace(
        cfg.dynamics, context=6, positional_actions=False)


def action_world(n: int, g: torch.Generator, positional: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Synthetic two-frame episodes where only the action decides a frame, on a static
    background (channels 1-3): frame t's channel 0 holds a dot where action t (the one
    that produced it) puts the first point (``positional``, a pusher), or a level
    proportional to its first entry (any action vector, e.g. a gripper's opening).
    Returns latents (n, 2, 4, 16, 16) and actions (n, 2, 4) in [-1, 1]."""
    a = torch.rand(n, 2, 4, generator=g) * 1.6 - 0.8
    bg = torch.randn(1, 1, 3, 16, 16, generator=g).expand(n, 2, 3, 16, 16)
    if positional:
        first = blobs(a * 0.22 / 0.26, ((0, 1),), 16, 1.0)[:, :, 0] * 3  # (n, 2, 16, 16)
    else:
        first = 2 * a[:, :, :1, None].expand(n, 2, 16, 16)
    return torch.cat([first[:, :, None], bg], 2), a


@pytest.mark.slow
@pytest.mark.parametrize("positional", [False, True])
def test_a_short_training_run_learns_to_follow_the_action(positional):
    """Trained for a few hundred tiny steps on a world where only the action decides the
    next frame, the model follows the action (the dot lands where it is commanded, the
    level matches) and shuffled actions do clearly worse."""
    cfg = tiny_cfg() if positional else tiny_cfg("no-points")
    cfg = dataclasses.replace(cfg, dynamics=dataclasses.replace(cfg.dynamics, channels=16, blocks=2,
                                                                action_channels=4), changed_weight=0.0)
    torch.manual_seed(0)
    module = DynamicsTrainModule(Dynamics(cfg.dynamics), cfg)
    opt = torch.optim.Adam(module.parameters(), lr=3e-3)
    g = torch.Generator().manual_seed(0)
    k = cfg.dynamics.context
    for _ in range(250):
        z, a = action_world(16, g, positional)
        # the window: K copies of frame 0 (produced by a[:, 0]); the target: frame 1, by a[:, 1]
        zz = torch.cat([z[:, :1].expand(16, k, 4, 16, 16), z[:, 1:]], 1)
        loss, _ = module(batch_for(cfg, zz, a, g))
        opt.zero_grad()
        loss.backward()
        opt.step()
    wm = WorldModel(Autoencoder(AE_PRESETS["tiny"]), module.dynamics.eval(), cfg, LOW, HIGH)
    z, a = action_world(64, torch.Generator().manual_seed(1), positional)
    with torch.no_grad():
        def predict(actions: torch.Tensor) -> torch.Tensor:  # one step from K copies of frame 0, made by a[:, 0]
            state = wm.reset_state(z[:, :1].expand(64, k, 4, 16, 16), a[:, :1].expand(64, k - 1, 4), latents=True)
            return wm.step_state(state, actions, latents=True)[1]

        y = predict(a[:, 1])
        true = ((y - z[:, 1]) ** 2).mean().item()
        shuffled = ((predict(a[:, 1].roll(1, 0)) - z[:, 1]) ** 2).mean().item()
    assert shuffled > 2 * true
    if positional:
        def cell(maps: torch.Tensor) -> torch.Tensor:  # (n, 16, 16) -> (n, 2) row, column of the peak
            i = maps.flatten(1).argmax(1)
            return torch.stack([i // 16, i % 16], 1).float()

        assert (cell(y[:, 0]) - cell(z[:, 1, 0])).norm(dim=1).median() <= 1.5
    else:
        assert (y[:, 0].mean((1, 2)) - z[:, 1, 0].mean((1, 2))).abs().median() < 0.2


def test_cli_help_names_every_variant(capsys):
    from iwsim.cli import main

    with pytest.raises(SystemExit):
        main(["train", "dynamics", "--help"])
    text = " ".join(capsys.readouterr().out.split()).replace("- ", "-")  # argparse wraps at hyphens
    for name in VARIANTS:
        assert name in text, name
