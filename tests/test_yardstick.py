"""The world model's yardstick (``bench/yardstick.py``, its measures in ``iwsim.yardstick``)
runs end to end on a tiny model; no quality is asserted, only that every measure is there
and in range."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
from PIL import Image

from iwsim.envs.collect import collect
from iwsim.yardstick.families import FAMILIES
from tests.test_dynamics import tiny_world_model
from tests.tools.scripts import load_script

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_yardstick_runs_on_a_tiny_model(tmp_path):
    data = tmp_path / "eval.zarr"
    collect("pusht", "play", 2, out=data, steps=40, image_size=64, workers=1, seed=900000, progress=False)
    ckpt = tiny_world_model().save(tmp_path / "run" / "00000002", {"data": str(data)})
    later = tiny_world_model(seed=1).save(tmp_path / "run" / "00000004", {"data": str(data)})
    out = tmp_path / "out"
    cmd = [sys.executable, str(ROOT / "bench" / "yardstick.py"), "--models", f"tiny={ckpt}", f"later={later}",
           "--parts", "core", "--curve", "tiny,later", "--data", str(data),
           "--episodes", "2", "--horizon", "36", "--steps", "6", "--candidates", "2", "--stability-steps", "20",
           "--speed-calls", "2", "--work", str(tmp_path / "work"), "--out", str(out)]
    run = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    r = json.loads((out / "results.json").read_text())
    assert next(iter(r)) == "command" and r["command"] == r["commands"][0] and r["command"].startswith(
        "python bench/yardstick.py --models tiny=")  # relative to the project, not this machine's path
    m = r["models"]["tiny"]
    for key in ("t_found", "pusher_visible", "teleop_rate", "spread", "stable_t"):
        assert 0 <= m[key] <= 1, key
    assert m["teleop_kept"].endswith("/2") and len(m["ranking"]) == 8 and m["steps_per_s"] > 0
    assert m["action_gap_5"] > 0 and m["psnr_play"] > 0 and m["psnr_play_first"] > 0
    assert m["codec_goal"] is None  # MuJoCo keeps no 6-step take: no success frames to reconstruct
    md = (out / "results.md").read_text()
    assert "| tiny |" in md and "| MuJoCo |" in md and "| target |" in md
    assert (out / "expert_strip.png").stat().st_size > 0 and (out / "scaling.png").stat().st_size > 0
    # the stability run's frames at steps 10 and 20: a row per model, MuJoCo last
    assert Image.open(out / "run_strip.png").size == (2 * 64, 3 * 64) and "`run_strip.png`" in md
    # a second run reuses the cached evaluation
    again = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert again.returncode == 0 and json.loads((out / "results.json").read_text())["models"]["tiny"] == m


@pytest.mark.slow
def test_wm_strip_shows_a_policy_in_the_model_above_mujoco(tmp_path):
    ckpt = tiny_world_model().save(tmp_path / "wm", {})
    out = tmp_path / "strip.png"
    cmd = [sys.executable, str(ROOT / "bench" / "wm_strip.py"), "--policy", "expert", "--world-model", str(ckpt),
           "--steps", "6", "--every", "2", "--threads", "1", "--out", str(out)]
    run = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "in the world model" in run.stdout and "in MuJoCo" in run.stdout
    image = Image.open(out)
    assert image.size == (3 * 64, 2 * 64)  # frames 0, 2, 4; rows: the model, MuJoCo


@pytest.mark.slow
def test_yardstick_families_and_idle_run_on_a_tiny_model(play_store, tmp_path):
    """Item 7: every operator family (the learned one from a tiny policy zoo) in MuJoCo and
    in a tiny model, the pooled agreement, and the idle measure; no quality asserted."""
    from iwsim.cli import main as iwsim

    zoo = tmp_path / "dp"
    assert iwsim(["train", "policy", "--policy", "dp", "--preset", "tiny-dp", "--data", f"{play_store}:2",
                  "--steps", "2", "--out", str(zoo), "--no-progress"]) == 0
    ckpt = tiny_world_model().save(tmp_path / "wm", {})
    partner = tiny_world_model(seed=1).save(tmp_path / "partner", {})
    out = tmp_path / "out"
    cmd = [sys.executable, str(ROOT / "bench" / "yardstick.py"), "--models", f"tiny={ckpt}", f"partner={partner}",
           "--parts", "families,idle", "--steps", "4", "--family-seeds", "3", "--idle-episodes", "2",
           "--zoo", str(zoo), "--trained-on", "tiny=play", "--trust-pairs", "tiny=partner",
           "--paired-episodes", "2,3", "--paired-holdout", "2", "--work", str(tmp_path / "work"), "--out", str(out)]
    run = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    r = json.loads((out / "results.json").read_text())
    g = r["models"]["tiny"]["generalisation"]
    assert set(g["families"]) == set(FAMILIES) and g["seen"] == ["play"]
    for name, row in g["families"].items():
        assert row["episodes"] == 3 and row["seen"] == (name == "play")
        assert 0 <= row["mujoco"] <= 1 and 0 <= row["model"] <= 1
        lo, hi = row["offset_interval"]
        assert lo <= row["offset"] <= hi
    assert set(g["pooled"]) == {"all", "unseen"} and -1 <= g["pooled"]["unseen"]["pearson"] <= 1
    idle = r["models"]["tiny"]["idle"]
    assert 0 <= idle["kept"] <= 1 and len(idle["fit_per_step"]) == 51
    assert r["mujoco"]["idle"]["fit_first"] > 0.8  # MuJoCo's own frames fit the T
    pair = r["trust_pairs"]["tiny=partner"]
    assert pair["episodes"] == 3 * len(FAMILIES) and set(pair["families"]) == set(FAMILIES)
    paired = g["paired"]  # each family's paired estimate, judged on 2 other first states (issue 66)
    assert paired["holdout_episodes"] == 2 and set(paired["by_n"]) == {"2", "3"}
    assert len(r["mujoco"]["families_holdout"]["expert"]) == 2
    for row in paired["by_n"]["3"]["policies"].values():
        lo, hi = row["interval"]
        assert lo <= row["estimate"] <= hi and row["covered"] == (lo <= row["truth"] <= hi)
    assert set(paired["trust_weighted"]) == {"command_lead", "implausibility"}
    md = (out / "results.md").read_text()
    assert "## Generalisation" in md and "| tiny |" in md and "| miss |" in md and "| tiny=partner |" in md
    assert "Paired estimates of `tiny`" in md and "distrusted where `command_lead` > 0.1" in md


def test_yardstick_refuses_bad_input_in_one_line_before_any_work(tmp_path, capsys):
    """Issue 65's smaller list: --episodes 0 and --steps -1 traced back, a name given twice
    kept one row, a pile-sweeping model was measured against T-push, a bad --trust-pairs
    was refused only after the work, and a bad --merge file was called a checkpoint file."""
    yardstick = load_script(ROOT / "bench" / "yardstick.py")

    tpush, pile = str(ROOT / "checkpoints" / "pusht-64"), str(ROOT / "checkpoints" / "pilesweep-64")
    (tmp_path / "broken.json").write_text("{")
    (tmp_path / "list.json").write_text("[1]")
    out = tmp_path / "out"
    for flags, says in ((["--episodes", "0"], "--episodes must be a positive integer, got 0."),
                        (["--steps", "-1"], "--steps must be a positive integer, got -1."),
                        ([f"a={tpush}"], "--models names 'a' twice"),
                        ([f"c={pile}"], "is a world model of task 'pilesweep', not 'pusht'"),
                        (["--trust-pairs", "a=nobody"], "--trust-pairs takes MODEL=PARTNER, two models of --models "
                                                        "or of the report, got 'a=nobody' ('nobody' unknown)."),
                        (["--merge", str(tmp_path / "broken.json")], "--merge report"),
                        (["--merge", str(tmp_path / "list.json")], "is not a report of bench/yardstick.py"),
                        (["--paired-episodes", "1,5"], "--paired-episodes must be counts in 2..24"),
                        (["--paired-episodes", "5", "--parts", "core"], "judges the families part")):
        models = ["--models", f"a={tpush}"] + ([flags.pop(0)] if "=" in flags[0] else [])
        argv = [*models, *flags, "--work", str(tmp_path / "work"), "--out", str(out)]
        code = yardstick.reporting_errors("yardstick.py", lambda argv=argv: yardstick.main(argv))
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 1 and len(err) == 1 and says in err[0], (flags, err)
    assert not out.exists() and not (tmp_path / "work").exists()


def test_contact_then_rest_on_a_tiny_model(tmp_path):
    """Issue 64's contact-then-rest measure runs on a tiny model (no quality asserted): the
    expert pushes, the pushers withdraw and hold still, the model replays MuJoCo's commands."""
    import numpy as np

    from iwsim.eval.policy import rollout
    from iwsim.yardstick import families as fam

    yardstick = load_script(ROOT / "bench" / "yardstick.py")

    run = rollout(fam.PushThenRest(push=6), "pusht", [fam.REST_SEED], 16, progress=False)
    held = run["action"][0, 6:]
    assert np.all(held == held[0]) and np.abs(held[0] - run["action"][0, 5]).max() > 0  # withdrawn, then still
    ckpt = tiny_world_model().save(tmp_path / "wm", {})
    c = fam.contact_rest(str(ckpt), tmp_path / "work", 6, push=30, rest=4)
    assert c["episodes"] == 6 and 0 <= c["moved"] <= 6
    if c["moved"]:
        assert 0 <= c["back_to_codec"] <= 1 and 0 <= c["fit_model"] <= 1 and 0 <= c["fit_codec"] <= 1
        md = yardstick.contact_rest_markdown({"models": {"tiny": {"contact_rest": c}}, "mujoco": {}})
        assert "## Contact, then rest" in "\n".join(md) and any(line.startswith("| tiny |") for line in md)
    assert fam.contact_rest(str(ckpt), tmp_path / "work", 6, push=30, rest=4) == c  # cached


def test_seen_families_and_the_learned_familys_checkpoints(tmp_path):
    from iwsim.yardstick.families import TRAINING_FAMILIES, seen_families, zoo_sources

    assert seen_families(["play", "expert-noisy"]) == ["expert", "jitter", "play"]
    assert seen_families(["learned-zoo"]) == [] and set(TRAINING_FAMILIES) >= {"play", "expert-hands"}
    with pytest.raises(ValueError, match="unknown training policies \\['nope'\\]"):
        seen_families(["play", "nope"])
    for step in ("00000010", "00000002", "last"):  # a run: its numbered checkpoints, in training order
        (tmp_path / "run" / "checkpoints" / step).mkdir(parents=True)
    single = tmp_path / "ckpt"
    assert zoo_sources([str(tmp_path / "run"), str(single)]) == [
        str(tmp_path / "run" / "checkpoints" / "00000002"), str(tmp_path / "run" / "checkpoints" / "00000010"),
        str(single)]


def test_compare_pools_the_families_and_ranks_episodes_by_each_trust_signal():
    import numpy as np

    from iwsim.yardstick.families import compare, ensemble_trust

    mujoco = {"play": [0.2, 0.4, 0.6], "expert": [0.9, 0.8, 1.0]}
    model = {"play": [0.3, 0.5, 0.7], "expert": [0.5, 0.9, 0.6]}
    novelty = {"play": [0.0, 0.1, 0.2], "expert": [0.9, 0.3, 0.8]}  # high where the model is wrong
    backwards = {"play": [0.9, 0.8, 0.7], "expert": [0.0, 0.5, 0.1]}  # high where it is right
    r = compare(mujoco, model, ["play"], {"novelty": novelty, "implausibility": backwards,
                                          "partial": {"play": [0.0, 0.0, 0.0]}})  # not every family: left out
    play, expert = r["families"]["play"], r["families"]["expert"]
    assert play["offset"] == pytest.approx(0.1) and play["seen"] and not expert["seen"] and play["episodes"] == 3
    lo, hi = expert["offset_interval"]
    assert expert["offset"] == pytest.approx(-0.7 / 3) and lo <= expert["offset"] <= hi
    assert r["pooled"]["unseen"]["families"] == ["expert"] and r["pooled"]["all"]["families"] == ["play", "expert"]
    assert r["pooled"]["unseen"]["max_abs_offset"] == pytest.approx(0.7 / 3)
    trust = r["trust"]
    assert trust["episodes"] == {"seen": 3, "unseen": 3, "all": 6} and set(trust["spearman"]) == {
        "novelty", "implausibility"}
    assert trust["spearman"]["novelty"]["all"] > 0.5 and trust["spearman"]["implausibility"]["all"] < -0.5
    # errors 0.4, 0.1, 0.4 against 0.9, 0.3, 0.8: in order, but for the tie (rho sqrt(3) / 2)
    assert trust["spearman"]["novelty"]["unseen"] == pytest.approx(np.sqrt(3) / 2)
    assert trust["error_unseen"] == pytest.approx([0.4, 0.1, 0.4])
    flagged = trust["calibration"]["novelty"]  # the most novel third first: an error of 0.4
    assert flagged[0]["share"] == 0.1 and flagged[0]["flagged_error"] == pytest.approx(0.4)
    assert "predictor" not in trust  # 3 seen episodes are too few to fit one on
    assert play["novelty"] == pytest.approx(0.1) and "partial" not in play
    t = ensemble_trust(mujoco, model, {"play": [0.3, 0.5, 0.7], "expert": [0.9, 0.8, 1.0]})
    assert t["episodes"] == 6 and t["spearman_error"] > 0.5 and t["families"]["play"] == 0
    assert np.isclose(t["families"]["expert"], np.mean([0.4, 0.1, 0.4]))


@pytest.mark.filterwarnings("ignore:All-NaN slice")  # a tiny model draws no T to fit
def test_open_loop_fidelity_and_the_codec_ceiling_on_a_tiny_model(tmp_path, one_thread):
    """The yardstick's held-out play measure (the ablation table's) and the codec's ceiling
    run on a tiny model; no quality asserted, only that each measure is there and in range."""
    import numpy as np

    from iwsim.core.errors import InputError
    from iwsim.yardstick.codec import codec_ceiling, goal_frames, reconstruction_scores
    from iwsim.yardstick.fidelity import STEPS, Episodes, score

    data = tmp_path / "eval.zarr"
    collect("pusht", "play", 2, out=data, steps=34, image_size=64, workers=1, seed=900000, progress=False)
    wm = tiny_world_model()
    ep = Episodes(str(data), 2)
    assert ep.n == 2 and ep.img.shape[:2] == (2, ep.length) and ep.actions.shape[:2] == (2, ep.length)
    with pytest.raises(InputError, match=f"at least {max(STEPS)} steps"):
        score(wm, ep, max(STEPS) - 1)
    r, (curve, first), frames = score(wm, ep, 32)
    assert frames.shape == (2, 32, 64, 64, 3) and frames.dtype == np.uint8 and curve.shape == first.shape == (32,)
    for key in ("t_found", "pusher_visible"):
        assert 0 <= r[key] <= 1, key
    assert r["action_gap_5"] > 0 and r["psnr_1_32"] > 0 and r["one_step"] >= 0 and r["copy_prev"] >= 0
    assert {f"latent_err_{s}" for s in STEPS} <= set(r)
    rec = reconstruction_scores(wm, ep.img[0, :3])
    assert rec.shape == (3,) and ((0 <= rec) & (rec <= 1)).all()
    assert goal_frames(data) is None or len(goal_frames(data))  # play rarely succeeds: None, or its success frames
    assert codec_ceiling(wm, None) is None and 0 <= codec_ceiling(wm, ep.img[0, :2]) <= 1
