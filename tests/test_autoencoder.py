import math

import numpy as np
import pytest
import torch

from iwsim.core.config import from_dict, to_dict
from iwsim.core.metrics import psnr, ssim
from iwsim.data.frames import to_model, to_uint8
from iwsim.world_model.codecs.base import Codec
from iwsim.world_model.codecs.consistency import Autoencoder
from iwsim.world_model.codecs.consistency_net import DecoderUNet, Encoder
from iwsim.world_model.presets import AE_PRESETS, AEConfig


@pytest.mark.parametrize("preset", ["tiny", "pusht-64"])
def test_shapes_and_latent_norm(preset):
    cfg = AE_PRESETS[preset]
    enc, dec = Encoder(cfg.encoder), DecoderUNet(cfg.decoder)
    x = torch.rand(2, 3, 64, 64) * 2 - 1
    z = enc(x)
    assert z.shape == (2, 4, 16, 16)
    torch.testing.assert_close(z.norm(dim=1), torch.full((2, 16, 16), math.sqrt(4)))
    v = dec(x, torch.tensor([999, 3]), torch.tensor([0, 1]), z)
    assert v.shape == x.shape


def test_encoder_rejects_wrong_rank():
    with pytest.raises(AssertionError):
        Encoder()(torch.zeros(3, 64, 64))


def test_frame_conversion_round_trip():
    frames = np.random.default_rng(0).integers(0, 256, (2, 8, 8, 3), dtype=np.uint8)
    x = to_model(frames)
    assert x.shape == (2, 3, 8, 8) and x.min() >= -1 and x.max() <= 1
    assert np.array_equal(to_uint8(x), frames)
    with pytest.raises(ValueError, match="uint8"):
        to_model(frames.astype(np.float32))


def test_config_json_round_trip():
    for cfg in AE_PRESETS.values():
        assert from_dict(type(cfg), to_dict(cfg)) == cfg
    with pytest.raises(ValueError, match="unknown"):
        from_dict(AEConfig, {**to_dict(AE_PRESETS["tiny"]), "bogus": 1})


def test_metrics():
    a = torch.rand(3, 3, 32, 32)
    assert torch.all(psnr(a, a) > 90) and torch.allclose(ssim(a, a), torch.ones(3))
    b = (a + 0.1).clamp(0, 1)
    assert torch.all(psnr(a, b) < 25) and torch.all(ssim(a, b) < 1)
    torch.testing.assert_close(psnr(torch.zeros(1, 1, 4, 4), torch.full((1, 1, 4, 4), 0.1)), torch.tensor([20.0]))


def test_codec_interface():
    """The consistency autoencoder is a Codec: latents of latent_shape, frames in [-1, 1]
    back, the same noise giving the same frames."""
    ae = Autoencoder(AE_PRESETS["tiny"]).eval()
    assert isinstance(ae, Codec) and ae.latent_shape == (4, 16, 16) and ae.stochastic
    with torch.no_grad():
        z = ae.encode(torch.zeros(2, 3, 64, 64))
        assert z.shape == (2, *ae.latent_shape)
        out = ae.decode(z, jumps=2, generator=torch.Generator().manual_seed(0))
        assert out.shape == (2, 3, 64, 64) and out.abs().max() <= 1
        noise = torch.randn(2, 3, 64, 64)
        torch.testing.assert_close(ae.decode(z, noise), ae.decode(z, noise))


def test_frozen_inference_matches_eager():
    torch.manual_seed(0)
    ae = Autoencoder(AE_PRESETS["tiny"]).eval()
    torch.nn.init.normal_(ae.decoder.conv_out.weight, std=0.1)  # zero-initialised: give it an output
    frames = torch.rand(3, 3, 64, 64, generator=torch.Generator().manual_seed(0)) * 2 - 1
    with torch.no_grad():
        z = ae.encode(frames)
        eager = ae.decode(z, jumps=2, generator=torch.Generator().manual_seed(1))
    ae.freeze_for_inference()
    with torch.no_grad():
        torch.testing.assert_close(ae.encode(frames), z, rtol=1e-4, atol=1e-4)
        frozen = ae.decode(z, jumps=2, generator=torch.Generator().manual_seed(1))
    assert (to_uint8(frozen).astype(int) - to_uint8(eager).astype(int)).__abs__().max() <= 1


def test_train_ae_help_names_every_preset(capsys):
    from iwsim.cli import main

    with pytest.raises(SystemExit):
        main(["train", "ae", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert all(name in text for name in AE_PRESETS), [n for n in AE_PRESETS if n not in text]
