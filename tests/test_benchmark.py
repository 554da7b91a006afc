"""The benchmark: metric correctness on known inputs, the LPIPS/FID/FVD paths with random
weights and without weights, the report, and a tiny end-to-end ``iwsim bench``."""

import json
import math
import shlex

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from iwsim.cli import main
from iwsim.core.metrics import mse, psnr, ssim, uiqi
from iwsim.eval import features as ft
from iwsim.eval import report
from iwsim.eval import scores as sc
from tests.test_dynamics import tiny_world_model
from tests.test_features import _random_state


def video(seed: int, e: int = 2, s: int = 16) -> np.ndarray:
    return np.random.default_rng(seed).integers(40, 200, (e, s, 64, 64, 3), dtype=np.uint8)


def test_identical_videos_score_perfectly():
    v = video(0)
    scores = sc.frame_metrics(v, v)
    assert scores["mse"].shape == (2, 16)
    assert np.all(scores["mse"] == 0) and np.allclose(scores["ssim"], 1) and np.allclose(scores["uiqi"], 1)
    assert np.all(scores["psnr"] >= 100)


def test_a_known_shift_gives_the_known_psnr():
    a = torch.rand(3, 3, 32, 32) * 0.5
    assert torch.allclose(mse(a + 0.1, a), torch.full((3,), 0.01), atol=1e-6)
    assert torch.allclose(psnr(a + 0.1, a), torch.full((3,), 20.0), atol=1e-3)
    v = video(1)
    shifted = v + np.uint8(26)
    expected = 20 * math.log10(255 / 26)
    assert np.allclose(sc.frame_metrics(v, shifted)["psnr"], expected, atol=1e-3)


def test_ssim_and_uiqi_fall_with_noise_and_handle_flat_images():
    flat = torch.full((2, 3, 32, 32), 0.5)
    assert torch.allclose(uiqi(flat, flat), torch.ones(2)) and torch.allclose(ssim(flat, flat), torch.ones(2))
    a = torch.rand(2, 3, 32, 32)
    noisy = (a + 0.2 * torch.randn_like(a)).clamp(0, 1)
    assert torch.all(ssim(noisy, a) < 0.9) and torch.all(uiqi(noisy, a) < 0.9)
    # UIQI of a scaled image has a closed form on constant-ratio patches: 2k / (1 + k^2) x ...
    assert torch.all(uiqi(a * 0.75, a) < uiqi(a * 0.95, a))
    with pytest.raises(ValueError, match="one shape"):
        mse(a, a[:1])


@pytest.mark.parametrize("shape", [(3, 3, 64, 64), (2, 1, 32, 48), (1, 6, 16, 16)])
def test_ssim_is_torchmetrics_ssim(shape):
    from torchmetrics.functional.image import structural_similarity_index_measure as reference

    g = torch.Generator().manual_seed(shape[1])
    a = torch.rand(shape, generator=g)
    for b in (a, (a + 0.1 * torch.randn(shape, generator=g)).clamp(0, 1), torch.rand(shape, generator=g), a * 0.5):
        expected = reference(b, a, data_range=1.0, reduction="none")
        assert torch.allclose(ssim(b, a), expected, atol=1e-5), (ssim(b, a), expected)


def test_missing_weights_are_reported_not_scored(tmp_path):
    nets = sc.FeatureNets.load(tmp_path)
    assert nets.lpips is None and nets.inception is None and nets.i3d is None
    assert nets.missing == {"lpips": f"unavailable: {ft.LPIPS_FILE} not found",
                            "fid": f"unavailable: {ft.INCEPTION_FILE} not found",
                            "fvd": f"unavailable: {ft.I3D_FILE} not found"}
    v = video(0)
    assert "lpips" not in sc.frame_metrics(v, v, nets) and sc.set_metrics({}, v, nets) == {}


@pytest.mark.slow
def test_lpips_fid_fvd_with_random_weights(tmp_path):
    for cls, name, seed in ((ft.LPIPS, ft.LPIPS_FILE, 0), (ft.InceptionFID, ft.INCEPTION_FILE, 1),
                            (ft.I3D, ft.I3D_FILE, 2)):
        save_file(_random_state(cls, seed), tmp_path / name)
    nets = sc.FeatureNets.load(tmp_path)
    assert not nets.missing
    truth, other = video(0, 1, 4), video(1, 1, 4)
    same = sc.frame_metrics(truth, truth, nets)
    diff = sc.frame_metrics(truth, other, nets)
    assert np.allclose(same["lpips"], 0, atol=1e-6) and np.all(diff["lpips"] > 0)
    # One network at a time keeps the big ones on small inputs: FID on 4 frames, FVD on 2 clips.
    fid_only = sc.FeatureNets(inception=nets.inception)
    feats = {"fid": sc.inception_features(nets.inception, truth)}
    assert feats["fid"].shape == (4, 2048)
    assert ft.frechet_distance(feats["fid"], feats["fid"]) == pytest.approx(0.0, abs=1e-3)
    assert sc.set_metrics(feats, other, fid_only)["fid"] > 0
    fvd_only = sc.FeatureNets(i3d=nets.i3d)
    clips, clips_other = video(0, 2, 16), video(1, 2, 16)
    feats = {"fvd": sc.i3d_features(nets.i3d, clips)}
    assert feats["fvd"].shape == (2, 400)
    assert ft.frechet_distance(feats["fvd"], feats["fvd"]) == pytest.approx(0.0, abs=1e-3)
    assert sc.set_metrics(feats, clips_other, fvd_only)["fvd"] > 0


def _result() -> dict:
    def acc(psnr_mean: float) -> dict:
        return {"mse": {"mean": 0.01, "std": 0.001, "last": 0.02, "last_std": 0.002},
                "psnr": {"mean": psnr_mean, "std": 1.0, "last": psnr_mean - 2, "last_std": 1.5},
                "ssim": {"mean": 0.8, "std": 0.05, "last": 0.7, "last_std": 0.06},
                "uiqi": {"mean": 0.7, "std": 0.05, "last": 0.6, "last_std": 0.05},
                "iou_err": {"mean": 0.1, "std": 0.02, "last": 0.2, "last_std": 0.05}}

    speed = {"step_ms": 30.0, "steps_per_s": 33.3, "dynamics_step_ms": 17.0, "step_ms_batch64": 1000.0,
             "frames_per_s_batch64": 64.0}
    return {"machine": "x", "data": "d.zarr", "episodes": [19, 39], "steps": 192, "seed": 0, "ours": "ours",
            "unavailable": {"lpips": "unavailable: lpips_alex.safetensors not found",
                            "fid": "unavailable: inception_fid.safetensors not found",
                            "fvd": "unavailable: i3d_kinetics400.safetensors not found"},
            "models": {"ours": {"objective": "consistency", "accuracy": acc(20.0), "speed": speed},
                       "diffusion": {"objective": "edm", "train_steps": 500, "train_minutes": 20.0,
                                     "accuracy": acc(21.0), "speed": {**speed, "step_ms": 90.0}}}}


def test_the_frames_figure_spans_the_rollout():
    from iwsim.eval.figures import figure_steps

    assert figure_steps(192) == [0, 48, 96, 144, 192]
    assert figure_steps(24) == [0, 6, 12, 18, 24]
    assert figure_steps(2) == [0, 1, 2]  # no step twice
    assert figure_steps(0) == [0]


def test_markdown_table():
    md = report.markdown(_result())
    assert "| MSE ↓ | PSNR ↑ | SSIM ↑ | UIQI ↑ | LPIPS ↓ | FID ↓ | FVD ↓ | IOU_ERR ↓ |" in md
    assert "| ours | 0.0100 +- 0.0010 | 20.00 +- 1.00 | 0.8000 +- 0.0500 | 0.7000 +- 0.0500 | unavailable: " \
           "lpips_alex.safetensors not found | unavailable: inception_fid.safetensors not found |" in md
    assert "| diffusion | edm | 500 steps, 20.0 min | 90.0 |" in md
    assert "loses on PSNR 20 vs 21, PSNR at step 192 18 vs 19" in md
    assert "ours is 3.00x as fast" in md


@pytest.mark.slow
def test_bench_cli_end_to_end(play_store, tmp_path, capsys):
    paths = {}
    for name in ("ours", "deterministic", "diffusion"):
        paths[name] = tiny_world_model(name=name).save(tmp_path / name, {"data": str(play_store)})
    out = tmp_path / "bench"
    args = ["bench", "--checkpoint", str(paths["ours"]),
            "--baselines", f"deterministic={paths['deterministic']},diffusion={paths['diffusion']}",
            "--out", str(out), "--episodes", "1", "--steps", "8", "--stability-steps", "6",
            "--stability-every", "2", "--speed-batch", "2", "--speed-calls", "2", "--weights", str(tmp_path / "none"),
            "--no-progress"]
    assert main(args) == 0
    assert str(out / "results.md") in capsys.readouterr().out
    r = json.loads((out / "results.json").read_text())
    assert list(r["models"]) == ["ours", "deterministic", "diffusion"] and r["steps"] == 8
    assert next(iter(r)) == "command" and r["command"] == shlex.join(["iwsim", *args])
    assert (out / "results.md").read_text().split("\n")[2] == f"`{r['command']}`"
    for name, entry in r["models"].items():
        acc = entry["accuracy"]
        assert set(acc) == {"mse", "psnr", "ssim", "uiqi", "iou_err"}, name
        assert 0 < acc["psnr"]["mean"] < 100 and -1 <= acc["ssim"]["mean"] <= 1
        assert entry["speed"]["steps_per_s"] > 0 and entry["speed"]["frames_per_s_batch2"] > 0
        assert 0 <= entry["stability"]["block_detected"] <= 1
    assert r["models"]["diffusion"]["objective"] == "edm"
    assert set(r["reference"][report.COPY]["accuracy"]) == {"mse", "psnr", "ssim", "uiqi", "iou_err"}
    assert r["mujoco"]["stability"]["block_detected"] == 1.0  # MuJoCo's own frames: the T is always there
    md = (out / "results.md").read_text()
    assert f"unavailable: {ft.LPIPS_FILE} not found" in md and "## Stability" in md and f"| *{report.COPY}* |" in md
    for png in ("curves.png", "frames.png", "stability.png"):
        assert (out / png).stat().st_size > 1000
    assert not list(out.glob(".*tmp*"))
    bad = ["bench", "--checkpoint", str(paths["ours"]), "--baselines", "nameless", "--out", str(out)]
    assert main(bad) == 1
    assert "NAME=CHECKPOINT" in capsys.readouterr().err
