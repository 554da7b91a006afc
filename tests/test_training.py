import dataclasses
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from iwsim.cli import main
from iwsim.core import trainer
from iwsim.core.checkpoint import CheckpointError, last_checkpoint
from iwsim.core.config import TrainConfig, to_dict
from iwsim.core.precision import bf16_available
from iwsim.data.store import StoreError
from iwsim.envs.collect import collect
from iwsim.world_model.codecs import load_codec
from iwsim.world_model.presets import AE_PRESETS
from iwsim.world_model.train_codec import AETask, train_autoencoder

TINY = AE_PRESETS["tiny"]


def tiny(steps: int = 6, **train) -> object:
    return dataclasses.replace(TINY, train=dataclasses.replace(TINY.train, steps=steps, **train))


def state(run: Path, step: int, part: str = "model") -> dict[str, torch.Tensor]:
    return load_file(run / "checkpoints" / f"{step:08d}" / "training_state" / f"{part}.safetensors")


def assert_same(a: dict, b: dict, **tol) -> None:
    assert a.keys() == b.keys()
    for k in a:
        if tol:
            torch.testing.assert_close(a[k], b[k], **tol)
        else:
            assert torch.equal(a[k], b[k]), k


def test_run_directory_layout(play_store, tmp_path):
    run = tmp_path / "run"
    metrics = train_autoencoder(tiny(), play_store, run, device=torch.device("cpu"), progress=False)
    assert {"psnr_1jump", "ssim_1jump", "psnr_3jump"} <= set(metrics)
    assert (run / "config.json").exists() and (run / "log.txt").read_text()
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows if "loss" in r] == [1, 2, 3, 4, 5, 6]
    assert any("eval/psnr_1jump" in r for r in rows)
    assert last_checkpoint(run / "checkpoints") == (run / "checkpoints" / "00000006").resolve()
    assert sorted(p.name for p in (run / "eval").iterdir()) == ["recon_00000003.png", "recon_00000006.png"]
    split = json.loads((run / "config.json").read_text())["split"]
    assert split["heldout_episodes"] == [3] and split["train_episodes"] == [0, 1, 2]
    # The exported checkpoint loads as an Autoencoder with the EMA weights.
    ae = load_codec(run / "checkpoints" / "last")
    ema = state(run, 6, "ema")
    assert_same({k: v for k, v in ae.state_dict().items()}, {k.removeprefix("codec."): v for k, v in ema.items()})


def test_resume_equals_uninterrupted(play_store, tmp_path):
    cpu = torch.device("cpu")
    train_autoencoder(tiny(6), play_store, tmp_path / "a", device=cpu, progress=False)
    train_autoencoder(tiny(3), play_store, tmp_path / "b", device=cpu, progress=False)
    train_autoencoder(tiny(6), play_store, tmp_path / "b", device=cpu, progress=False)  # resumes at 3
    for part in ("model", "ema", "optimizer"):
        assert_same(state(tmp_path / "a", 6, part), state(tmp_path / "b", 6, part))
    # A crash after step 4 logged rows the checkpoint at 3 does not have: resuming drops them.
    b = tmp_path / "b"
    def logged() -> list[tuple]:
        rows = [json.loads(line) for line in (b / "metrics.jsonl").read_text().splitlines()]
        return [(r["step"], r.get("loss"), r.get("eval/psnr_1jump")) for r in rows]

    before = logged()
    (b / "checkpoints" / "last").unlink()
    (b / "checkpoints" / "last").symlink_to("00000003")
    train_autoencoder(tiny(6), play_store, b, device=cpu, progress=False)
    assert logged() == before


@pytest.mark.ddp
@pytest.mark.slow
def test_two_process_ddp_matches_single_process(play_store, tmp_path):
    out = tmp_path / "ranks"
    out.mkdir()
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
           str(Path(__file__).parent / "ddp_train.py"), str(play_store), str(tmp_path / "ddp"), str(out), "3"]
    subprocess.run(cmd, check=True, capture_output=True, timeout=300)
    r0, r1 = load_file(out / "rank0.safetensors"), load_file(out / "rank1.safetensors")
    assert_same(r0, r1)  # DDP keeps the ranks identical
    train_autoencoder(tiny(3), play_store, tmp_path / "single", device=torch.device("cpu"), progress=False)
    single = state(tmp_path / "single", 3)
    # Same global batch, samples and noise: only the order of floating-point sums differs.
    # Adam turns a near-zero gradient into a step of up to lr whatever its size, so single
    # elements may differ by a few lr; on average they agree to float precision.
    init = AETask(TINY, play_store).module.state_dict()  # the seeded initial weights
    diffs = torch.cat([(r0[k] - single[k]).abs().flatten() for k in single])
    moved = torch.cat([(single[k] - init[k]).abs().flatten() for k in single])
    assert diffs.max() <= 6 * TINY.train.lr and diffs.mean() < 1e-6, (diffs.max(), diffs.mean())
    assert moved.mean() > 100 * diffs.mean()  # training did move the weights


class _NaNAt(torch.nn.Module):
    def __init__(self, bad_step: int) -> None:
        super().__init__()
        self.w = torch.nn.Parameter(torch.ones(3))
        self.bad_step = bad_step

    def forward(self, step: int):
        loss = (self.w**2).sum() * (float("nan") if step == self.bad_step else 1.0)
        return loss, {}


class _NaNTask:
    def __init__(self, bad_step: int) -> None:
        self.module = _NaNAt(bad_step)

    def batch(self, step, generator, part, device):
        return step

    def evaluate(self, module, step, out_dir):
        return {}

    def export(self, module):
        return module.state_dict()


def test_non_finite_loss_stops_and_keeps_last_good_checkpoint(tmp_path):
    cfg = TrainConfig(steps=8, batch_size=1, checkpoint_every=2, eval_every=100, log_every=1)
    with pytest.raises(trainer.TrainingError, match=r"non-finite.*step 5.*00000004"):
        trainer.train(_NaNTask(5), cfg, tmp_path, {"x": 1}, progress=False)
    assert last_checkpoint(tmp_path / "checkpoints").name == "00000004"
    assert not (tmp_path / "checkpoints" / "00000006").exists()
    assert torch.isfinite(load_file(tmp_path / "checkpoints" / "last" / "model.safetensors")["w"]).all()


def test_cli_dry_run_and_overrides(capsys):
    assert main(["train", "ae", "--data", "x", "--out", "y", "--preset", "pusht-64", "--steps", "7",
                 "--batch-size", "8", "--dry-run"]) == 0
    cfg = json.loads(capsys.readouterr().out)
    assert cfg["preset"] == "pusht-64" and cfg["train"]["steps"] == 7 and cfg["train"]["batch_size"] == 8
    assert cfg["encoder"] == json.loads(json.dumps(to_dict(AE_PRESETS["pusht-64"].encoder)))


def _error(capsys, argv) -> str:
    assert main(argv) != 0
    err = capsys.readouterr().err.strip()
    assert err.startswith("iwsim: error:") and "\n" not in err
    return err


def test_bad_inputs(play_store, tmp_path, capsys):
    base = ["train", "ae", "--preset", "tiny", "--no-progress"]
    missing = ["--data", str(tmp_path / "none.zarr"), "--out", str(tmp_path / "r")]
    assert "does not exist" in _error(capsys, base + missing)
    junk = tmp_path / "junk.zarr"
    junk.mkdir()
    (junk / "x").write_text("not zarr")
    assert "not an episode store" in _error(capsys, base + ["--data", str(junk), "--out", str(tmp_path / "r")])
    assert "unknown preset" in _error(capsys, ["train", "ae", "--data", "x", "--out", "y", "--preset", "huge"])
    assert "positive" in _error(capsys, ["train", "ae", "--data", "x", "--out", "y", "--steps", "0"])
    # A 96 px store for a 64 px preset.
    big = tmp_path / "big.zarr"
    collect("pusht", "play", 2, out=big, steps=3, image_size=96, workers=1, seed=0, progress=False)
    assert "96x96" in _error(capsys, base + ["--data", str(big), "--out", str(tmp_path / "r")])
    # A run directory holding another config is refused, unless --force.
    run = tmp_path / "run"
    assert main(base + ["--data", str(play_store), "--out", str(run), "--steps", "1"]) == 0
    before = (run / "config.json").read_text()
    assert "different config" in _error(capsys, base + ["--data", str(play_store), "--out", str(run), "--seed", "5"])
    assert (run / "config.json").read_text() == before
    assert main(base + ["--data", str(play_store), "--out", str(run), "--seed", "5", "--force", "--steps", "2"]) == 0


def test_truncated_or_incomplete_checkpoint(play_store, tmp_path):
    run = tmp_path / "run"
    train_autoencoder(tiny(3), play_store, run, device=torch.device("cpu"), progress=False)
    ckpt = run / "checkpoints" / "00000003"
    weights = ckpt / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[: weights.stat().st_size // 2])
    with pytest.raises(CheckpointError, match="truncated or corrupt"):
        load_codec(ckpt)
    (ckpt / "config.json").unlink()
    with pytest.raises(CheckpointError, match="config.json is missing"):
        load_codec(ckpt)
    with pytest.raises(CheckpointError, match="not a checkpoint directory"):
        load_codec(tmp_path / "nowhere")


def test_store_without_frames_is_refused(tmp_path):
    from iwsim.data.store import EpisodeStore

    s = EpisodeStore.create(tmp_path / "s.zarr", {"task": "pusht"})
    s.append({"action": torch.zeros(3, 4).numpy()}, seed=0)
    s.append({"action": torch.zeros(3, 4).numpy()}, seed=1)
    with pytest.raises(StoreError, match="no data/img"):
        AETask(TINY, tmp_path / "s.zarr")


def test_resume_falls_back_past_a_truncated_newest_checkpoint(play_store, tmp_path, caplog):
    """A truncated optimizer.safetensors in the newest checkpoint: resumption warns, naming
    it, and goes on from the checkpoint before it, bit-identically to an uninterrupted run."""
    cpu = torch.device("cpu")
    train_autoencoder(tiny(6), play_store, tmp_path / "a", device=cpu, progress=False)
    b = tmp_path / "b"
    train_autoencoder(tiny(6), play_store, b, device=cpu, progress=False)
    damaged = b / "checkpoints" / "00000006" / "training_state" / "optimizer.safetensors"
    damaged.write_bytes(damaged.read_bytes()[:100])
    with caplog.at_level("INFO"):
        train_autoencoder(tiny(6), play_store, b, device=cpu, progress=False)  # redoes steps 4-6
    assert f"{damaged} is unreadable" in caplog.text and "resuming from the checkpoint before it" in caplog.text
    assert "resuming from" in caplog.text and "(step 3)" in caplog.text
    for part in ("model", "ema", "optimizer"):
        assert_same(state(tmp_path / "a", 6, part), state(b, 6, part))
    # nothing whole left: one clear error, nothing trained from scratch over it
    for step in (3, 6):
        (b / "checkpoints" / f"{step:08d}" / "model.safetensors").write_bytes(b"")
    with pytest.raises(CheckpointError, match="no checkpoint in .* is whole \\(damaged: 00000006, 00000003\\)"):
        train_autoencoder(tiny(6), play_store, b, device=cpu, progress=False)


def test_a_finished_run_returns_without_building_an_optimizer(play_store, tmp_path, monkeypatch, caplog):
    """A rerun of a finished training (a recipe run again) stops before the optimizer, whose
    first construction costs seconds; its checkpoint must still fit the network."""
    run = tmp_path / "run"
    train_autoencoder(tiny(3), play_store, run, device=torch.device("cpu"), progress=False)

    def no_optimizer(*a, **k):
        raise AssertionError("an optimizer was built for a finished run")

    with monkeypatch.context() as m, caplog.at_level("INFO"):
        m.setattr(torch.optim, "AdamW", no_optimizer)
        assert train_autoencoder(tiny(3), play_store, run, device=torch.device("cpu"), progress=False) == {}
    assert "is already trained to step 3" in caplog.text
    other = dataclasses.replace(tiny(3), encoder=dataclasses.replace(TINY.encoder, channels=(8, 16, 16)))
    train_autoencoder(other, play_store, tmp_path / "other", device=torch.device("cpu"), progress=False)
    shutil.rmtree(run / "checkpoints")
    shutil.copytree(tmp_path / "other" / "checkpoints", run / "checkpoints", symlinks=True)
    with pytest.raises(CheckpointError, match="does not fit this model"):
        train_autoencoder(tiny(3), play_store, run, device=torch.device("cpu"), progress=False)

def test_dynamics_fine_tune_keeps_the_models_normalisation_and_starts_from_its_weights(play_store, tmp_path, capsys,
                                                                                     one_thread):
    """``train dynamics --init``: the world model's autoencoder, action and latent
    normalisation and network are kept (even on data with other action ranges), training
    starts from its weights and at its longest unroll."""
    from iwsim.data.formats import merge
    from iwsim.world_model import WorldModel

    flags = ["--preset", "tiny", "--no-progress"]
    assert main(["train", "ae", "--data", str(play_store), "--out", str(tmp_path / "ae"), *flags]) == 0
    assert main(["train", "dynamics", "--data", str(play_store), "--ae", str(tmp_path / "ae"),
                 "--out", str(tmp_path / "dyn"), *flags]) == 0
    expert = tmp_path / "expert.zarr"
    collect("pusht", "expert-noisy", 2, out=expert, steps=12, image_size=64, workers=1, seed=5, progress=False)
    mixed = merge([play_store, expert], tmp_path / "mixed.zarr", progress=False)
    last = tmp_path / "dyn" / "checkpoints" / "last"
    init = WorldModel.load(last)
    tuned = tmp_path / "tuned"
    assert main(["train", "dynamics", "--data", str(mixed.path), "--init", str(last),
                 "--out", str(tuned), "--steps", "1", "--lr", "1e-12", *flags]) == 0
    wm = WorldModel.load(tuned / "checkpoints" / "last")
    for name in ("action_low", "action_high", "latent_mean"):
        assert torch.equal(getattr(wm, name), getattr(init, name)), name
    assert wm.latent_scale == init.latent_scale
    assert_same(wm.codec.state_dict(), init.codec.state_dict())
    assert_same(wm.dynamics.state_dict(), init.dynamics.state_dict(), atol=1e-6, rtol=0)
    config = json.loads((tuned / "config.json").read_text())
    assert config["init"].endswith("last") and config["stage2"]["unroll"] == [[0, 2]]
    # --dry-run prints what the run trains: the model's own config, its window widened by --context.
    capsys.readouterr()
    assert main(["train", "dynamics", "--data", str(mixed.path), "--init", str(last), "--context", "4",
                 "--out", str(tmp_path / "wide"), "--steps", "3", "--dry-run", *flags]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["dynamics"]["context"] == 4 and printed["unroll"] == [[0, 2]] and printed["train"]["steps"] == 3
    assert printed["dynamics"]["channels"] == init.cfg.dynamics.channels
    assert not (tmp_path / "wide").exists()
    # --unroll: a fine-tune unrolls every sequence that long.
    assert main(["train", "dynamics", "--data", str(mixed.path), "--init", str(last), "--unroll", "5",
                 "--out", str(tmp_path / "wide"), "--dry-run", *flags]) == 0
    assert json.loads(capsys.readouterr().out)["unroll"] == [[0, 5]]
    # --variant sampled: the model trained on jumps from every level and sampled in 3.
    assert main(["train", "dynamics", "--data", str(mixed.path), "--init", str(last), "--variant", "sampled",
                 "--out", str(tmp_path / "wide"), "--dry-run", *flags]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert (printed["jumps"], printed["top_fraction"], printed["zero_fraction"]) == (3, 0.5, 0.5)
    assert printed["dynamics"] == json.loads(json.dumps(dataclasses.asdict(init.cfg.dynamics)))
    assert printed["unroll_grad"] is init.cfg.unroll_grad is True
    assert main(["train", "dynamics", "--data", str(mixed.path), "--init", str(last), "--variant", "detached-unroll",
                 "--out", str(tmp_path / "wide"), "--dry-run", *flags]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["unroll_grad"] is False and printed["jumps"] == init.cfg.jumps == 1
    assert main(["train", "dynamics", "--data", str(mixed.path), "--init", str(last), "--variant", "context-wide",
                 "--out", str(tmp_path / "wide"), "--dry-run", *flags]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed["context_sigma"] == [0.0, 0.6] and printed["context_label"] == init.cfg.context_label
    # --context widens the window: the older latents start unheard, the rest as it was.
    assert main(["train", "dynamics", "--data", str(mixed.path), "--init", str(last), "--context", "4",
                 "--out", str(tmp_path / "wide"), "--steps", "1", "--lr", "1e-12", *flags]) == 0
    wide = WorldModel.load(tmp_path / "wide" / "checkpoints" / "last")
    assert (init.cfg.dynamics.context, wide.cfg.dynamics.context) == (2, 4)
    w, c = wide.dynamics.conv_in.weight, init.cfg.dynamics.latent_channels
    assert w[:, c:3 * c].abs().max() < 1e-6
    torch.testing.assert_close(torch.cat([w[:, :c], w[:, 3 * c:]], 1), init.dynamics.conv_in.weight, atol=1e-6,
                               rtol=0)


def test_longest_unroll_keeps_the_curriculum_below_it():
    from iwsim.world_model.train_dynamics import longest_unroll

    curriculum = ((0, 2), (200, 4), (500, 8))
    assert longest_unroll(curriculum, 16) == ((0, 2), (200, 4), (500, 8), (800, 16))
    assert longest_unroll(curriculum, 6) == ((0, 2), (200, 4), (500, 6))
    assert longest_unroll(curriculum, 4) == ((0, 2), (200, 4))
    assert longest_unroll(curriculum, 1) == ((0, 1),)


def test_dynamics_takes_either_an_autoencoder_or_a_model_to_fine_tune(play_store, tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["train", "dynamics", "--data", str(play_store), "--out", str(tmp_path / "x"), "--preset", "tiny"])
    assert "one of the arguments --ae --init is required" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["train", "dynamics", "--data", str(play_store), "--ae", "a", "--init", "b", "--out", str(tmp_path)])
    assert "not allowed with argument" in capsys.readouterr().err
    assert main(["train", "dynamics", "--data", str(play_store), "--ae", "a", "--out", str(tmp_path),
                 "--lr", "0", "--preset", "tiny"]) != 0
    assert "--lr must be a positive number" in capsys.readouterr().err
    assert main(["train", "dynamics", "--data", str(play_store), "--init", "a", "--out", str(tmp_path),
                 "--variant", "diffusion"]) != 0
    assert "--variant applies to training from scratch" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.skipif(not bf16_available(torch.device("cpu")), reason="this CPU has neither AMX nor AVX-512-BF16")
def test_bf16_autocast_on_the_cpu_trains_reproducibly(play_store, tmp_path, one_thread):
    """``--bf16``: the config records it, every training row names the path, the loss stays
    finite, the same command gives the same weights, and they differ from the float32 run's
    (the autocast is in effect); the checkpoint loads in the plain (float32) path."""
    flags = ["--preset", "tiny", "--no-progress"]
    assert main(["train", "ae", "--data", str(play_store), "--out", str(tmp_path / "ae"), *flags]) == 0
    for out, bf16 in (("a", ["--bf16"]), ("b", ["--bf16"]), ("fp32", [])):
        assert main(["train", "dynamics", "--data", str(play_store), "--ae", str(tmp_path / "ae"), *bf16,
                     "--out", str(tmp_path / out), *flags]) == 0
    config = json.loads((tmp_path / "a" / "config.json").read_text())
    assert config["stage2"]["train"]["cpu_bf16"] is True
    rows = [json.loads(line) for line in (tmp_path / "a" / "metrics.jsonl").read_text().splitlines()]
    assert all(math.isfinite(r["loss"]) and r["path"] == "bf16" for r in rows if "loss" in r)
    fp32_rows = [json.loads(line) for line in (tmp_path / "fp32" / "metrics.jsonl").read_text().splitlines()]
    assert {r["path"] for r in fp32_rows if "loss" in r} == {"fp32"}
    from iwsim.world_model import WorldModel

    WorldModel.load(tmp_path / "a" / "checkpoints" / "last")
    a = load_file(tmp_path / "a" / "checkpoints" / "last" / "model.safetensors")
    b = load_file(tmp_path / "b" / "checkpoints" / "last" / "model.safetensors")
    assert_same(a, b)
    fp32 = load_file(tmp_path / "fp32" / "checkpoints" / "last" / "model.safetensors")
    assert any(not torch.equal(a[k], fp32[k]) for k in a if k.startswith("dynamics."))


def test_a_run_from_before_the_task_entry_resumes(tmp_path):
    """Configs gained a "task" entry (issue 24); runs started before it resume, and a
    real difference is still refused."""
    from iwsim.core.checkpoint import load_json, write_json_atomic
    from iwsim.core.errors import InputError
    from iwsim.core.trainer import prepare_run_dir

    old = {"kind": "world_model", "train": {"steps": 10, "lr": 1e-3}}
    write_json_atomic(tmp_path / "config.json", old)
    prepare_run_dir(tmp_path, {**old, "task": {"kind": "pusht"}})
    assert load_json(tmp_path / "config.json")["task"] == {"kind": "pusht"}
    with pytest.raises(InputError, match="differs in task"):
        prepare_run_dir(tmp_path, {**old, "task": {"kind": "generic"}})
    with pytest.raises(InputError, match="differs in train.lr"):
        prepare_run_dir(tmp_path, {**old, "train": {"steps": 10, "lr": 1.0}, "task": {"kind": "pusht"}})


def counting_codec():
    """A tiny codec of seeded random weights (the bf16 gap below must not depend on the tests
    run before), its own encode, and the list of batch sizes its encode is called with."""
    from iwsim.world_model.codecs import build_codec

    torch.manual_seed(0)
    codec = build_codec("conv-ae", to_dict(AE_PRESETS["tiny-conv"])).eval()
    calls: list[int] = []
    encode = codec.encode
    codec.encode = lambda x: calls.append(len(x)) or encode(x)
    return codec, encode, calls


def test_the_latent_cache_serves_a_store_that_extends_its_own(play_store, tmp_path, one_thread):
    from safetensors.torch import save_file

    from iwsim.data.frames import to_model
    from iwsim.data.store import EpisodeStore
    from iwsim.world_model.dynamics_data import encode_store, encoder_key

    codec, encode, calls = counting_codec()
    cache, cpu = tmp_path / "latents.safetensors", torch.device("cpu")
    base = encode_store(codec, EpisodeStore.open(play_store), cpu, False, cache, chunk=16)
    assert sum(calls) == len(base) == 48
    more, merged = tmp_path / "more.zarr", tmp_path / "merged.zarr"
    collect("pusht", "play", 1, out=more, steps=12, image_size=64, workers=1, seed=9, progress=False)
    assert main(["data", "merge", str(play_store), str(more), "--out", str(merged), "--no-progress"]) == 0
    calls.clear()
    both = encode_store(codec, EpisodeStore.open(merged), cpu, False, cache, chunk=16)
    assert sum(calls) == 12 and torch.equal(both[:48], base)  # only the new episode's frames are encoded
    assert both.dtype == torch.float16  # stored in half precision
    torch.testing.assert_close(both[48:].float(), encode(to_model(EpisodeStore.open(more).array("img")[:])),
                               atol=5e-3, rtol=5e-3)
    calls.clear()
    encode_store(codec, EpisodeStore.open(merged), cpu, False, cache, chunk=16)
    assert not calls
    # latents encoded in bf16 are another cache's: they neither serve nor are served by float32's
    fast = encode_store(codec, EpisodeStore.open(merged), cpu, False, cache, chunk=16, bf16=True)
    assert sum(calls) == 60 and (fast.float() - both.float()).abs().max() < 0.2
    calls.clear()
    encode_store(codec, EpisodeStore.open(merged), cpu, False, cache, chunk=16)
    assert sum(calls) == 60
    calls.clear()
    old_key = f"{EpisodeStore.open(play_store).path}|48|{encoder_key(codec)}"
    save_file({"latents": base.contiguous()}, cache, metadata={"key": old_key})
    assert torch.equal(encode_store(codec, EpisodeStore.open(play_store), cpu, False, cache, chunk=16), base)
    assert not calls  # a cache from before the chunk hashes still serves its own store


def test_the_latent_cache_of_two_views_serves_each_view_imported_alone(two_view_store, tmp_path, one_thread):
    """bench/two_views.sh's single-view models read the two-view model's cache: each view's
    latents come from the cached view of the same frames, none is encoded again."""
    from iwsim.data.store import EpisodeStore
    from iwsim.world_model.dynamics_data import encode_store

    codec, _, calls = counting_codec()
    cache, cpu = tmp_path / "latents.safetensors", torch.device("cpu")
    both = encode_store(codec, EpisodeStore.open(two_view_store), cpu, False, cache, chunk=4)
    assert sum(calls) == 2 * len(both) == 22
    c = both.shape[1] // 2
    for k, view in enumerate(["top", "side"]):
        alone = tmp_path / f"{view}.zarr"
        assert main(["data", "import", "--format", "zarr", "--in", str(two_view_store), "--camera", view,
                     "--image-size", "32", "--out", str(alone), "--no-progress"]) == 0
        calls.clear()
        z = encode_store(codec, EpisodeStore.open(alone), cpu, False, cache, chunk=4)
        assert not calls and torch.equal(z, both[:, k * c:(k + 1) * c])
    calls.clear()
    assert torch.equal(encode_store(codec, EpisodeStore.open(two_view_store), cpu, False, cache, chunk=4), both)
    assert not calls  # the views' reads left the cache as it was


def test_an_encoding_stopped_part_way_resumes_from_the_frames_it_saved(play_store, tmp_path, one_thread):
    from iwsim.data.store import EpisodeStore
    from iwsim.world_model.dynamics_data import encode_store

    codec, encode, calls = counting_codec()
    cpu, store = torch.device("cpu"), EpisodeStore.open(play_store)
    whole = encode_store(codec, store, cpu, False, None, chunk=16)
    calls.clear()

    def stop_at_the_third_chunk(x):
        if len(calls) == 2:
            raise KeyboardInterrupt
        calls.append(len(x))
        return encode(x)
    codec.encode = stop_at_the_third_chunk
    cache = tmp_path / "latents.safetensors"
    with pytest.raises(KeyboardInterrupt):
        encode_store(codec, store, cpu, False, cache, chunk=16, save_every_s=0)
    assert calls == [16, 16] and cache.is_file()  # the first two chunks' latents were saved
    calls.clear()
    codec.encode = lambda x: calls.append(len(x)) or encode(x)
    assert torch.equal(encode_store(codec, store, cpu, False, cache, chunk=16), whole)
    assert calls == [16]  # only the third chunk is encoded


def test_a_bf16_run_on_a_cpu_without_the_instructions_encodes_its_latents_in_float32(play_store, tmp_path,
                                                                                   monkeypatch, one_thread):
    """The trainer falls back to float32 where bf16 would be emulated; the latent cache
    follows it (before, the store was encoded under emulated bf16 autocast: 2-3x slower)."""
    from safetensors import safe_open

    from iwsim.core import trainer
    from iwsim.world_model import dynamics_data

    monkeypatch.setattr(trainer, "bf16_available", lambda device: False)
    monkeypatch.setattr(dynamics_data, "bf16_available", lambda device: False)
    ae, cache = tmp_path / "ae", tmp_path / "latents.safetensors"
    assert main(["train", "ae", "--data", str(play_store), "--preset", "tiny", "--steps", "2", "--out", str(ae),
                 "--no-progress"]) == 0
    assert main(["train", "dynamics", "--ae", str(ae), "--data", str(play_store), "--preset", "tiny", "--steps", "2",
                 "--bf16", "--out", str(tmp_path / "dyn"), "--latent-cache", str(cache), "--no-progress"]) == 0
    with safe_open(cache, "pt") as f:
        assert not f.metadata()["weights"].endswith("|bf16")


def test_a_world_model_run_started_before_a_new_config_field_resumes(play_store, tmp_path, one_thread):
    """A stage's config that gains a field resumes the runs started before it (their
    defaults are what they trained with); a field that really changed is still refused."""
    from iwsim.core.checkpoint import load_json, write_json_atomic
    from iwsim.core.errors import InputError
    from iwsim.world_model.model import complete_run_config
    from iwsim.world_model.presets import DYNAMICS_PRESETS

    run = tmp_path / "codec"
    cfg = dataclasses.replace(AE_PRESETS["tiny-conv"], train=dataclasses.replace(AE_PRESETS["tiny-conv"].train,
                                                                                 steps=3, checkpoint_every=3))
    train_autoencoder(cfg, play_store, run, device=torch.device("cpu"), progress=False)
    config = load_json(run / "config.json")
    del config["model"]["latent_noise_scale"], config["model"]["train"]["lr_decay"]  # as before they existed
    write_json_atomic(run / "config.json", config)
    longer = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, steps=6))
    train_autoencoder(longer, play_store, run, device=torch.device("cpu"), progress=False)
    assert last_checkpoint(run / "checkpoints").name == "00000006"
    config["model"]["latent_channels"] = 8  # a real difference
    write_json_atomic(run / "config.json", config)
    with pytest.raises(InputError, match="differs in model.latent_channels"):
        train_autoencoder(longer, play_store, run, device=torch.device("cpu"), progress=False)
    # A dynamics or decoder fine-tune run's config: its stage-2 and codec parts are completed.
    stored = {"kind": "world_model", "codec": {"kind": "conv-ae", "config": to_dict(cfg)},
              "stage2": to_dict(DYNAMICS_PRESETS["tiny"]), "data": "x"}
    old = json.loads(json.dumps(stored))
    del old["stage2"]["rest_threshold"], old["codec"]["config"]["foreground_weight"]
    assert json.loads(json.dumps(complete_run_config(old))) == json.loads(json.dumps(stored))
    assert complete_run_config({"stage2": {"no_such_field": 1}}) == {"stage2": {"no_such_field": 1}}
