"""The fast path (issue 63): bf16 and the layouts where the CPU has the instructions, and
networks that compute on it what they compute in float32."""

import json
import logging
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.nn import functional as F

from iwsim.cli import main
from iwsim.core import precision
from iwsim.core.errors import InputError
from iwsim.core.precision import CpuInfo, Precision, bf16_available
from iwsim.core.trainer import compile_networks, training_precision
from iwsim.world_model.dynamics import Dynamics, DynamicsConfig, SpatialAttention

CPU = torch.device("cpu")
SHIPPED = Path(__file__).resolve().parents[1] / "checkpoints"
needs_bf16 = pytest.mark.skipif(not bf16_available(CPU), reason="this CPU has neither AMX nor AVX-512-BF16")


@pytest.fixture
def no_bf16_cpu(monkeypatch):
    """A CPU without bf16 instructions (an AVX2 machine)."""
    monkeypatch.setattr(precision, "cpu_info", lambda: CpuInfo("AVX2 test CPU", frozenset({"avx2", "fma"})))


def test_cpu_flags_pick_the_bf16_instructions():
    assert CpuInfo("x", frozenset({"avx512_bf16", "amx_bf16", "amx_tile"})).bf16 == "amx"
    assert CpuInfo("x", frozenset({"avx512f", "avx512_bf16"})).bf16 == "avx512_bf16"
    assert CpuInfo("x", frozenset({"avx2"})).bf16 is None
    assert precision.cpu_info().model  # this machine's, read from /proc/cpuinfo


def test_bf16_is_refused_or_off_without_the_instructions(no_bf16_cpu, caplog, play_store, tmp_path, one_thread):
    assert not bf16_available(CPU) and bf16_available(torch.device("cuda"))
    with pytest.raises(InputError, match="neither AMX nor AVX-512-BF16"):
        precision.require_bf16(CPU, "WorldModel.bf16")
    # a run that asks for bf16 (--bf16, or a config resumed on such a CPU) trains in float32 and says so
    with caplog.at_level(logging.WARNING, logger="iwsim"):
        assert training_precision(CPU, True) == Precision(bf16=False)
        assert main(["train", "ae", "--data", str(play_store), "--preset", "tiny", "--bf16", "--out",
                     str(tmp_path / "ae"), "--no-progress"]) == 0
    assert caplog.text.count("training in float32") == 2
    rows = [json.loads(line) for line in (tmp_path / "ae" / "metrics.jsonl").read_text().splitlines()]
    assert {r["path"] for r in rows if "loss" in r} == {"fp32"}


def test_attention_is_scaled_dot_product_attention():
    """The written-out attention computes what F.scaled_dot_product_attention did (the
    checkpoints trained before it load and give the same outputs)."""
    torch.manual_seed(0)
    attn = SpatialAttention(16, 4)
    torch.nn.init.normal_(attn.out.weight)
    x = torch.randn(3, 16, 8, 8)
    n, c, h, w = x.shape
    q, k, v = attn.qkv(attn.norm(x)).view(n, 3, 4, c // 4, h * w).transpose(-1, -2).unbind(1)
    want = x + attn.out(F.scaled_dot_product_attention(q, k, v).transpose(-1, -2).reshape(n, c, h, w))
    torch.testing.assert_close(attn(x), want, rtol=1e-5, atol=1e-5)


def tiny_dynamics() -> tuple[Dynamics, tuple[torch.Tensor, ...]]:
    torch.manual_seed(0)
    cfg = DynamicsConfig(latent_channels=4, latent_size=8, context=3, channels=16, blocks=2, heads=2, emb_dim=32,
                         action_channels=2)
    net = Dynamics(cfg)
    for p in net.parameters():  # zero-initialised outputs would make every comparison trivial
        torch.nn.init.normal_(p, std=0.1)
    b = 2
    args = (torch.randn(b, 4, 8, 8), torch.randn(b, 3, 4, 8, 8), torch.full((b,), 999.0), torch.zeros(b),
            torch.full((b,), 100.0), torch.rand(b, 2, 4) * 2 - 1)
    return net, args


@needs_bf16
def test_dynamics_under_bf16_stays_within_tolerance_of_float32():
    net, args = tiny_dynamics()
    with torch.no_grad():
        fp32 = net(*args)
        with Precision(bf16=True).autocast(CPU):
            bf16 = net(*args).float()
    err = (bf16 - fp32).abs().max() / fp32.abs().max()
    assert 0 < err < 0.05  # bf16 has 8 bits of mantissa: a few per cent of the output's range


@pytest.mark.slow
def test_compiled_dynamics_computes_what_eager_does(one_thread):
    net, args = tiny_dynamics()

    class Module(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.dynamics = net

        def compile_targets(self):
            return (self.dynamics,)

    module = Module()
    keys = list(module.state_dict())
    want = net(*args)
    compile_networks(module)
    assert list(module.state_dict()) == keys  # the checkpoint's names stay
    got = net(*args)
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)
    got.square().mean().backward()
    assert all(p.grad is not None for p in net.parameters() if p.requires_grad)


@needs_bf16
def test_the_fast_world_model_renders_what_float32_does(one_thread):
    from iwsim.world_model import WorldModel

    wm = WorldModel.load(SHIPPED / "pusht-64")
    frame = np.zeros((2, 64, 64, 3), np.uint8) + 200
    actions = np.linspace(-0.1, 0.1, 2 * 10 * 4, dtype=np.float32).reshape(2, 10, 4)
    want = wm.rollout(frame, actions)
    wm.bf16 = True
    got = wm.rollout(frame, actions)
    diff = np.abs(got.astype(int) - want.astype(int))
    assert got.dtype == np.uint8 and got.shape == want.shape
    assert diff.mean() < 2 and diff.max() > 0  # grey levels: bf16 really ran, and stayed close
    wm.bf16 = False
    np.testing.assert_array_equal(wm.rollout(frame, actions), want)  # float32 again, exactly


def test_fast_world_model_is_refused_without_bf16(no_bf16_cpu):
    from iwsim.world_model import WorldModel

    wm = WorldModel.load(SHIPPED / "pusht-64")
    with pytest.raises(InputError, match="WorldModel.bf16"):
        wm.bf16 = True
    assert not wm.bf16


def test_export_model_bf16_is_an_inference_setting(tmp_path, monkeypatch):
    """``export-model --bf16``: the checkpoint asks for bf16 inference (the weights
    unchanged); it runs so where the CPU has the instructions and in float32 elsewhere."""
    from iwsim.core.checkpoint import load_json
    from iwsim.world_model import WorldModel
    from tests.test_dynamics import tiny_world_model

    src = tiny_world_model().save(tmp_path / "wm")
    out = tmp_path / "bf16"
    assert main(["export-model", "--run", str(src), "--out", str(out), "--bf16"]) == 0
    assert (out / "model.safetensors").read_bytes() == (src / "model.safetensors").read_bytes()
    assert load_json(out / "config.json")["provenance"]["inference"]["inference_bf16"] == [False, True]
    assert WorldModel.load(out).cfg.inference_bf16 and not WorldModel.load(src).bf16
    assert WorldModel.load(out).bf16 == bf16_available(CPU)
    monkeypatch.setattr(precision, "cpu_info", lambda: CpuInfo("AVX2 test CPU", frozenset({"avx2"})))
    assert not WorldModel.load(out).bf16  # float32 on a CPU without the instructions
    assert main(["export-model", "--run", str(out), "--out", str(tmp_path / "back"), "--no-bf16"]) == 0
    assert not WorldModel.load(tmp_path / "back").cfg.inference_bf16


@needs_bf16
def test_the_codec_under_bf16_stays_within_tolerance_of_float32(one_thread):
    from iwsim.world_model import WorldModel

    wm = WorldModel.load(SHIPPED / "pusht-64")
    frames = np.random.default_rng(0).integers(0, 256, (3, 64, 64, 3), dtype=np.uint8)
    z, images = wm.encode(frames), wm.decode(wm.encode(frames))
    wm.bf16 = True
    z16, images16 = wm.encode(frames), wm.decode(z)
    assert z16.dtype == torch.float32 and images16.dtype == np.uint8
    assert 0 < (z16 - z).abs().max() / z.abs().max() < 0.05
    assert np.abs(images16.astype(int) - images.astype(int)).mean() < 2


@needs_bf16
@pytest.mark.parametrize("name", ["dp", "act"])
def test_policy_losses_under_bf16_stay_within_tolerance_of_float32(name, one_thread):
    """What ``train policy --bf16`` runs: the training loss under autocast, against float32's."""
    from iwsim.policies.common import PolicyBatch
    from iwsim.policies.factory import load_policy

    policy = load_policy(SHIPPED / f"{name}-pusht-64").eval()  # no dropout: the same function twice
    to, tp = policy.obs_horizon, getattr(policy.cfg, "horizon", None) or policy.cfg.chunk_size
    g = torch.Generator().manual_seed(0)
    batch = PolicyBatch(torch.rand(8, to, 3, 64, 64, generator=g) * 2 - 1, torch.rand(8, to, 4, generator=g) * 2 - 1,
                        torch.rand(8, tp, 4, generator=g) * 2 - 1, torch.zeros(8, tp, dtype=torch.bool))
    losses = []
    for bf16 in (False, True):
        torch.manual_seed(0)  # the same diffusion steps and noise, the same CVAE sample
        with torch.no_grad(), Precision(bf16=bf16).autocast(CPU):
            losses.append(policy(batch)[0].float().item())
    assert losses[0] != losses[1] and abs(losses[1] - losses[0]) < 0.05 * abs(losses[0]) + 1e-3
