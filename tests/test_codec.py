"""The codec seam: a second codec (conv-ae, x2 downsampling) trains and rolls out through
the same WorldModel; checkpoints written before the seam still load."""

import json

import numpy as np
import pytest
import torch

from iwsim.cli import main
from iwsim.core.checkpoint import load_json, load_tensors, save_model_dir
from iwsim.core.config import to_dict
from iwsim.core.errors import InputError
from iwsim.world_model import Codec, WorldModel
from iwsim.world_model.codecs import build_codec, kind_of, load_codec
from iwsim.world_model.presets import AE_PRESETS
from tests.test_dynamics import tiny_world_model


@pytest.mark.parametrize("preset", sorted(set(AE_PRESETS) - {"pusht-128"}))
def test_every_codec_preset_builds_a_codec_with_its_latent_shape(preset):
    cfg = AE_PRESETS[preset]
    codec = build_codec(kind_of(cfg), to_dict(cfg)).eval()
    assert isinstance(codec, Codec)
    with torch.no_grad():
        z = codec.encode(torch.zeros(2, 3, 64, 64))
        assert z.shape == (2, *codec.latent_shape)
        x = codec.decode(z, torch.zeros(2, 3, 64, 64) if codec.stochastic else None)
    assert x.shape == (2, 3, 64, 64) and x.abs().max() <= 1


def test_the_foreground_weight_counts_what_differs_from_the_background():
    """A pusher is ~20 of 4096 pixels: the coarse codecs weight what differs from the
    scene's median frame, so an error there costs more than the same error elsewhere."""
    import dataclasses

    cfg = dataclasses.replace(AE_PRESETS["tiny-conv"], foreground_weight=10.0)
    codec = build_codec("conv-ae", to_dict(cfg))
    frames = torch.full((5, 3, 64, 64), 0.8)
    frames[0, :, 10:13, 10:13] = -0.5  # a dot in one frame: the median is the floor
    codec.prepare(frames)
    torch.testing.assert_close(codec.background, torch.full((1, 3, 64, 64), 0.8))
    x0 = frames[:1]
    z = codec.encode(x0)
    loss = {}
    for where in ("dot", "floor"):
        target = x0.clone()
        rows = slice(10, 13) if where == "dot" else slice(40, 43)
        target[:, :, rows, rows] += 0.3
        codec.decoder.forward = lambda _z, t=target: t  # the decoder's output, fixed
        loss[where] = codec.loss(x0, z, {})[0].item()
    assert loss["dot"] > 5 * loss["floor"]
    plain = build_codec("conv-ae", to_dict(AE_PRESETS["tiny-conv"]))
    plain.prepare(frames)  # no foreground weight: nothing to take
    assert plain.background.abs().max() == 0


def test_a_symmetric_foreground_weight_costs_a_painted_dot_as_much_as_a_missed_one():
    """Weighting the target's foreground alone makes the decoder paint foreground where it
    is unsure (a missed dot costs 11x a painted one); ``foreground_symmetric`` weights both."""
    import dataclasses

    loss = {}
    for symmetric in (False, True):
        cfg = dataclasses.replace(AE_PRESETS["tiny-conv"], foreground_weight=10.0, foreground_symmetric=symmetric)
        codec = build_codec("conv-ae", to_dict(cfg))
        floor, dot = torch.full((1, 3, 64, 64), 0.8), torch.full((1, 3, 64, 64), 0.8)
        dot[:, :, 10:13, 10:13] = -0.5
        codec.prepare(torch.cat([floor, floor, dot]))  # the background: the floor
        z = codec.encode(floor)
        for case, (target, painted) in {"missed": (dot, floor), "painted": (floor, dot)}.items():
            codec.decoder.forward = lambda _z, t=painted: t  # the decoder's output, fixed
            loss[symmetric, case] = codec.loss(target, z, {})[0].item()
    assert loss[False, "missed"] > 5 * loss[False, "painted"]
    assert loss[True, "missed"] == pytest.approx(loss[True, "painted"])


def test_a_codec_and_a_dynamics_of_other_latents_are_refused():
    wm = tiny_world_model()
    conv = build_codec("conv-ae", to_dict(AE_PRESETS["tiny-conv"]))  # 32 x 32 latents, the dynamics 16 x 16
    with pytest.raises(InputError, match="latents"):
        WorldModel(conv, wm.dynamics, wm.cfg, wm.action_low, wm.action_high)
    with pytest.raises(InputError, match="unknown codec"):
        build_codec("vq", {})


@pytest.mark.slow
def test_a_second_codec_trains_and_rolls_out_through_the_same_world_model(play_store, tmp_path, one_thread):
    ae, dyn = tmp_path / "ae", tmp_path / "dyn"
    assert main(["train", "ae", "--data", str(play_store), "--preset", "tiny-conv", "--out", str(ae),
                 "--no-progress"]) == 0
    codec = load_codec(ae / "checkpoints" / "last")
    assert codec.kind == "conv-ae" and codec.latent_shape == (4, 32, 32)
    assert main(["train", "dynamics", "--data", str(play_store), "--ae", str(ae), "--preset", "tiny",
                 "--out", str(dyn), "--no-progress"]) == 0
    wm = WorldModel.load(dyn / "checkpoints" / "last")
    assert wm.codec.kind == "conv-ae" and wm.latent_shape == (4, 32, 32) and wm.cfg.dynamics.latent_size == 32
    frames = np.zeros((2, 64, 64, 3), np.uint8)
    video = wm.rollout(frames, np.zeros((2, 5, 4), np.float32))
    assert video.shape == (2, 5, 64, 64, 3) and video.dtype == np.uint8
    # deterministic codec, noise only in the dynamics: the same seed gives the same video
    np.testing.assert_array_equal(video, wm.rollout(frames, np.zeros((2, 5, 4), np.float32)))
    config = json.loads((dyn / "checkpoints" / "last" / "config.json").read_text())
    assert config["codec"]["kind"] == "conv-ae"


def test_checkpoints_from_before_the_codec_seam_load(tmp_path):
    """The old layout: the autoencoder's config under "ae" and its weights as "ae.*"."""
    wm = tiny_world_model()
    wm.save(tmp_path / "new")
    config = load_json(tmp_path / "new" / "config.json")
    tensors = load_tensors(tmp_path / "new" / "model.safetensors")
    old_config = {k: v for k, v in config.items() if k != "codec"} | {"ae": config["codec"]["config"]}
    old_tensors = {("ae." + k.removeprefix("codec.")) if k.startswith("codec.") else k: v for k, v in tensors.items()}
    save_model_dir(tmp_path / "old", old_tensors, old_config)
    old = WorldModel.load(tmp_path / "old")
    assert old.codec.kind == "consistency-ae"
    for k, v in wm.state_dict().items():
        torch.testing.assert_close(old.state_dict()[k], v, rtol=0, atol=0)
    frames = np.random.default_rng(0).integers(0, 256, (1, 64, 64, 3), dtype=np.uint8)
    actions = np.zeros((1, 3, 4), np.float32)
    np.testing.assert_array_equal(old.rollout(frames, actions), wm.rollout(frames, actions))


@pytest.mark.parametrize("value", ["1,0", "0.5", "a,b", "-1,1", "nan,1"])
def test_decoder_finetune_refuses_a_bad_latent_noise_range(tmp_path, capsys, value):
    args = ["train", "decoder-finetune", "--world-model", str(tmp_path / "wm"), "--data", str(tmp_path / "d.zarr"),
            "--out", str(tmp_path / "out"), f"--latent-noise={value}"]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "--latent-noise takes LO,HI" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_the_codec_of_a_world_model_checkpoint_loads_as_a_stage1_codec(tmp_path):
    """``--ae`` may name a world model: training a new dynamics on its codec."""
    wm = tiny_world_model()
    wm.save(tmp_path / "wm")
    codec = load_codec(tmp_path / "wm")
    assert codec.kind == wm.codec.kind
    for k, v in wm.codec.state_dict().items():
        assert torch.equal(codec.state_dict()[k], v), k
