import json

import imageio.v2 as imageio

from iwsim.cli import main
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
