import json

import imageio.v2 as imageio

from iwsim.cli import main
from iwsim.envs.pilesweep.task import PileSweepTask
from tests.test_shipped_checkpoint import SHIPPED


def test_demo_writes_a_side_by_side_video_and_scores(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--checkpoint", str(SHIPPED), "--steps", "6", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    video = out / "world_model_vs_mujoco.mp4"
    assert str(video.resolve()) in printed and "iwsim play --checkpoint" in printed
    frames = [f for f in imageio.get_reader(video)]
    assert len(frames) == 6 and frames[0].shape == (256 + 8, 2 * 256 + 4, 3)  # truth | gap | prediction, PSNR bar
    scores = json.loads(video.with_suffix(".json").read_text())
    assert len(scores["psnr_per_step"]) == 6 and scores["psnr"] > 15
    assert not list(out.glob(".*tmp*"))  # written atomically, no leftovers
    assert main(["demo", "--checkpoint", str(tmp_path / "missing"), "--out", str(out)]) == 1
    assert "not a checkpoint directory" in capsys.readouterr().err


def test_demo_of_another_task_pairs_its_model_with_its_simulator(pile_model, tmp_path, capsys, monkeypatch):
    """Issue 45: `iwsim demo --task pilesweep` runs the pile's scripted expert in its MuJoCo
    task beside the model, scored by the pile's pixel scorer; a model of another task, or a
    task without a shipped model and no --checkpoint, is one line."""
    out = tmp_path / "pile"
    ckpt = str(pile_model["checkpoint"])
    assert main(["demo", "--task", "pilesweep", "--checkpoint", ckpt, "--steps", "4", "--out", str(out)]) == 0
    summary = json.loads(capsys.readouterr().out.splitlines()[1])
    assert summary["task"] == "pilesweep" and summary["checkpoint"] == ckpt
    scores = json.loads((out / "world_model_vs_mujoco.json").read_text())
    truth = scores["iou_true"]  # the pile's score: the share of the pieces in the tray
    assert len(truth) == 4 and all(0.0 <= v <= 1.0 for v in truth) and len(scores["iou_pred"]) == 4
    monkeypatch.setattr(PileSweepTask, "checkpoint", None)  # a task without a shipped model
    assert main(["demo", "--task", "pilesweep", "--out", str(out)]) == 1
    assert "task 'pilesweep' has no shipped world model yet; give one with --checkpoint" in capsys.readouterr().err
    assert main(["demo", "--checkpoint", ckpt, "--out", str(out)]) == 1  # the default task is T-push
    assert f"{ckpt} is a world model of task 'pilesweep', not 'pusht'" in capsys.readouterr().err
