"""Pile sweeping's yardstick (``bench/pile_yardstick.py``) runs end to end on a tiny model;
no quality is asserted, only that every measure is there and in range, and that a model of
another task or a store too short for the horizon is refused in one line."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from iwsim.envs.collect import collect
from tests.test_dynamics import tiny_world_model

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_pile_yardstick_runs_on_a_tiny_model(pile_model, tmp_path):
    play, expert = tmp_path / "play.zarr", tmp_path / "expert.zarr"
    collect("pilesweep", "play", 2, out=play, steps=8, image_size=64, workers=1, seed=900000, progress=False)
    collect("pilesweep", "expert", 2, out=expert, steps=8, image_size=64, workers=1, seed=910000, progress=False)
    out = tmp_path / "out"

    def run(*models: str, horizon: int = 6) -> subprocess.CompletedProcess:
        cmd = [sys.executable, str(ROOT / "bench" / "pile_yardstick.py"), "--models", *models, "--data", str(play),
               "--expert-data", str(expert), "--horizon", str(horizon), "--episodes", "2", "--rank-episodes", "2",
               "--teleop-episodes", "2", "--speed-calls", "2", "--work", str(tmp_path / "work"), "--out", str(out)]
        return subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=600)

    done = run(f"tiny={pile_model['checkpoint']}")
    assert done.returncode == 0, done.stderr[-2000:]
    r = json.loads((out / "results.json").read_text())
    assert next(iter(r)) == "command" and r["command"].startswith("python bench/pile_yardstick.py --models tiny=")
    m, mj, first = r["models"]["tiny"], r["mujoco"], r["repeat_first"]
    for row in (m, mj):
        assert 0 <= row["pieces_kept"] <= 1 and row["tray_err"] >= 0 and 0 <= row["expert_score"] <= 1
        assert len(row["ranking"]) >= 8 and all(0 <= v <= 1 for v in row["ranking"].values())
    assert first["pieces_kept"] == 1.0 and first["psnr_play"] > 0  # the first frame keeps every piece
    assert m["psnr_play"] > 0 and m["steps_per_s"] > 0 and m["expert_offset"] == pytest.approx(
        m["expert_score"] - mj["expert_score"])
    assert all(m[k] is None or -1 <= m[k] <= 1 for k in ("pearson", "spearman")) and (m["mmrv"] is None
                                                                                       or m["mmrv"] >= 0)
    assert len(mj["n_in_tray"]) == 2 and min(mj["n_in_tray"]) >= 0
    md = (out / "results.md").read_text()
    assert "| target |" in md and "| MuJoCo |" in md and "| repeat first frame | 100% |" in md and "| tiny |" in md
    again = run(f"tiny={pile_model['checkpoint']}")  # the model's row comes from the cache
    assert again.returncode == 0 and json.loads((out / "results.json").read_text())["models"]["tiny"] == m

    pusht = tiny_world_model().save(tmp_path / "pusht", {})  # 4-D actions, no task recorded: T-push
    for refused, needle in ((run(f"t={pusht}"), "world model of task 'pusht'"),
                            (run(f"tiny={pile_model['checkpoint']}", horizon=9), "use --horizon 7"),
                            (run(f"tiny={pile_model['checkpoint']}", horizon=0), "--horizon must be a positive")):
        lines = refused.stderr.strip().splitlines()
        assert refused.returncode != 0 and len(lines) == 1 and needle in lines[0], refused.stderr[-2000:]


@pytest.mark.slow
def test_pile_families_runs_on_a_tiny_model(pile_model, tmp_path):
    """bench/pile_families.py: every family, the pile at rest and a long rollout, each
    measure in range; seen and unseen families split by --trained-on; a bad one refused."""
    out = tmp_path / "out"

    def run(*extra: str) -> subprocess.CompletedProcess:
        cmd = [sys.executable, str(ROOT / "bench" / "pile_families.py"), "--models",
               f"tiny={pile_model['checkpoint']}", "--seeds", "2", "--steps", "4", "--idle-episodes", "1",
               "--long-episodes", "1", "--long-steps", "6", "--work", str(tmp_path / "work"), "--out", str(out), *extra]
        return subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=600)

    done = run()
    assert done.returncode == 0, done.stderr[-2000:]
    r = json.loads((out / "results.json").read_text())
    assert next(iter(r)) == "command"
    m = r["models"]["tiny"]
    rows = m["families"]["families"]
    assert "learned" not in rows and "miss" not in rows and {"expert", "person", "still", "play"} <= set(rows)
    assert {f for f, row in rows.items() if row["seen"]} == {"expert", "jitter", "play"}
    for row in rows.values():
        assert 0 <= row["mujoco"] <= 1 and 0 <= row["model"] <= 1 and row["episodes"] == 2
        assert row["offset"] == pytest.approx(row["model"] - row["mujoco"])
    assert set(m["families"]["pooled"]) == {"all", "unseen"}
    idle, long = m["idle"], m["long"]
    assert 0 <= idle["kept"] <= idle["count_kept"] <= 1 and 0 <= idle["mask_iou"] <= 1 and idle["psnr"] > 0
    assert len(idle["kept_per_step"]) == 50 and set(idle["psnr_at"]) == {"1", "10", "50"}
    assert 0 <= long["kept"] <= 1 and len(long["kept_per_stretch"]) == 1
    md = (out / "results.md").read_text()
    assert "| person | no |" in md and "At rest" in md and "Long rollouts" in md
    refused = run("--trained-on", "nobody")
    lines = refused.stderr.strip().splitlines()
    assert refused.returncode != 0 and len(lines) == 1 and "unknown training policies" in lines[0], refused.stderr
