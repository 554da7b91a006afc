import torch

from iwsim.diffusion.consistency import JumpModel, jump_levels, sample_jumps, sample_levels, two_jump_loss
from iwsim.diffusion.schedule import NOISE_CLIP, Schedule, gaussian
from iwsim.world_model.codecs.consistency_net import DecoderConfig, DecoderUNet, Encoder, EncoderConfig


def random_net(x, t, s, cond):
    # Any network: the identities below must hold whatever it outputs.
    return torch.sin(x * 3 + t.view(-1, 1, 1, 1) * 0.01) + cond.mean()


def test_schedule_endpoints():
    sch = Schedule()
    assert sch.alpha_bar[0] == 1.0 and sch.alpha_bar[-1] < 1e-4
    assert torch.all(sch.alpha_bar[1:] < sch.alpha_bar[:-1])  # strictly more noise per level
    x0, eps = torch.randn(4, 3, 8, 8), torch.randn(4, 3, 8, 8)
    assert torch.equal(sch.noise(x0, torch.zeros(4, dtype=torch.long), eps), x0)  # x_t at t = 0 is x0


def test_jump_identities():
    sch = Schedule()
    x, cond = torch.randn(5, 3, 8, 8), torch.randn(5, 4, 2, 2)
    t = torch.tensor([1, 10, 300, 700, 999])
    jump = JumpModel(random_net, sch)
    torch.testing.assert_close(jump(x, t, t, cond=cond), x, rtol=1e-5, atol=1e-5)  # s = t
    zero = torch.zeros(5, dtype=torch.long)
    torch.testing.assert_close(jump(x, zero, zero, cond=cond), x)


def test_perfect_network_jumps_exactly():
    """With the true v, a jump t -> s lands on the same-noise x_s."""
    sch = Schedule()
    x0, eps = torch.randn(3, 3, 8, 8), torch.randn(3, 3, 8, 8)
    t, s = torch.tensor([999, 500, 20]), torch.tensor([0, 250, 19])

    def oracle(x_t, tt, ss, cond):
        a, b = sch.coefficients(tt, x_t)
        return a * eps - b * x0

    jump = JumpModel(oracle, sch)
    torch.testing.assert_close(jump(sch.noise(x0, t, eps), t, s, cond=None), sch.noise(x0, s, eps),
                               rtol=1e-4, atol=1e-4)
    loss, _ = two_jump_loss(jump, x0, t, s, eps, {"cond": None})
    assert loss.item() < 1e-8


def test_levels_and_noise():
    g = torch.Generator().manual_seed(0)
    t, s = sample_levels(1000, 1000, g, top_fraction=0.5)
    assert t.min() >= 1 and t.max() <= 1000 and torch.all(s < t) and s.min() >= 0
    assert 0.4 < (t == 999).float().mean() < 0.6
    assert jump_levels(3, 999) == [999, 666, 333, 0] and jump_levels(1, 999) == [999, 0]
    assert gaussian((10000,), g).abs().max() <= NOISE_CLIP


def test_sampler_is_deterministic_for_a_generator():
    torch.manual_seed(0)
    enc, dec = Encoder(EncoderConfig(channels=(8, 8, 8))), DecoderUNet(DecoderConfig(channels=(8, 8, 8), emb_dim=16))
    for p in dec.conv_out.parameters():  # zero-initialised: give it an output
        torch.nn.init.normal_(p, std=0.1)
    sch = Schedule()
    z = enc(torch.rand(2, 3, 32, 32) * 2 - 1)
    runs = [sample_jumps(JumpModel(dec, sch), gaussian((2, 3, 32, 32), torch.Generator().manual_seed(s)),
                         jump_levels(k, sch.T - 1), {"z": z})
            for k, s in ((3, 1), (3, 1), (3, 2))]
    assert torch.equal(runs[0], runs[1]) and not torch.equal(runs[0], runs[2])
