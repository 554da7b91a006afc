import math

import numpy as np
import pytest
import torch

from iwsim.autoencoder import Autoencoder
from iwsim.config import AE_PRESETS, AEConfig, from_dict, to_dict
from iwsim.data.frames import to_model, to_uint8
from iwsim.metrics import psnr, ssim
from iwsim.models.autoencoder import DecoderUNet, Encoder


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
        assert from_dict(AEConfig, to_dict(cfg)) == cfg
    with pytest.raises(ValueError, match="unknown"):
        from_dict(AEConfig, {**to_dict(AE_PRESETS["tiny"]), "bogus": 1})


def test_metrics():
    a = torch.rand(3, 3, 32, 32)
    assert torch.all(psnr(a, a) > 90) and torch.allclose(ssim(a, a), torch.ones(3))
    b = (a + 0.1).clamp(0, 1)
    assert torch.all(psnr(a, b) < 25) and torch.all(ssim(a, b) < 1)
    torch.testing.assert_close(psnr(torch.zeros(1, 1, 4, 4), torch.full((1, 1, 4, 4), 0.1)), torch.tensor([20.0]))


def test_decode_frames_api():
    ae = Autoencoder(AE_PRESETS["tiny"]).eval()
    frames = np.zeros((2, 64, 64, 3), np.uint8)
    z = ae.encode(frames)
    out = ae.decode(z, jumps=2, generator=torch.Generator().manual_seed(0))
    assert out.shape == (2, 64, 64, 3) and out.dtype == np.uint8
    with pytest.raises(ValueError, match="frames"):
        ae.encode(np.zeros((2, 32, 32, 3), np.uint8))


def test_frozen_inference_matches_eager():
    torch.manual_seed(0)
    ae = Autoencoder(AE_PRESETS["tiny"]).eval()
    torch.nn.init.normal_(ae.decoder.conv_out.weight, std=0.1)  # zero-initialised: give it an output
    frames = np.random.default_rng(0).integers(0, 256, (3, 64, 64, 3), dtype=np.uint8)
    z = ae.encode(frames)
    eager = ae.decode(z, jumps=2, generator=torch.Generator().manual_seed(1))
    ae.freeze_for_inference()
    torch.testing.assert_close(ae.encode(frames), z, rtol=1e-4, atol=1e-4)
    frozen = ae.decode(z, jumps=2, generator=torch.Generator().manual_seed(1))
    assert np.abs(frozen.astype(int) - eager.astype(int)).max() <= 1
