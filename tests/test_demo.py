import imageio.v2 as imageio

from iwsim.cli import main


def test_demo_writes_a_playable_video(tmp_path, capsys):
    out = tmp_path / "demo"
    args = ["demo", "--episodes", "2", "--steps", "6", "--image-size", "64", "--workers", "1", "--out", str(out)]
    assert main(args) == 0
    video = out / "pusht_expert.mp4"
    assert str(video.resolve()) in capsys.readouterr().out
    frames = [f for f in imageio.get_reader(video)]
    assert len(frames) == 12 and frames[0].shape == (256 + 8, 256, 3)
    assert not list(out.glob(".*tmp*"))  # written atomically, no leftovers
    assert main(args) == 0  # a second run reuses the store
