"""A run's resumable state saved where a new machine finds it (issue 64 item 4): restored
into a fresh run directory, the run resumes bit-identically to one that never stopped."""

import shutil

import pytest
import torch

from iwsim.cli import main
from iwsim.core.errors import InputError
from iwsim.core.wip import restore_wip, save_wip
from iwsim.world_model.train_codec import train_autoencoder
from tests.test_training import assert_same, state, tiny


def test_a_saved_state_resumes_on_a_new_machine_as_if_it_never_stopped(play_store, tmp_path, capsys):
    cpu = torch.device("cpu")
    train_autoencoder(tiny(6), play_store, tmp_path / "whole", device=cpu, progress=False)
    run = tmp_path / "machine1" / "run"
    train_autoencoder(tiny(3), play_store, run, device=cpu, progress=False)
    wip = tmp_path / "repo" / "checkpoints" / "wip" / "run"
    assert main(["wip", "save", "--run", str(run), "--out", str(wip)]) == 0
    assert "at step 3" in capsys.readouterr().out
    assert sorted(p.name for p in wip.iterdir()) == ["00000003", "config.json", "log.txt", "metrics.jsonl",
                                                      "wip.json"]
    assert not any(p.is_symlink() for p in wip.rglob("*"))  # committed as plain files
    shutil.rmtree(tmp_path / "machine1")  # the machine is gone
    fresh = tmp_path / "machine2" / "run"
    assert main(["wip", "restore", "--wip", str(wip), "--out", str(fresh)]) == 0
    train_autoencoder(tiny(6), play_store, fresh, device=cpu, progress=False)  # the run's command, rerun
    for part in ("model", "ema", "optimizer"):
        assert_same(state(tmp_path / "whole", 6, part), state(fresh, 6, part))
    # a later save replaces the state (one state per run, not an accumulation)
    save_wip(fresh, wip)
    assert sorted(p.name for p in wip.iterdir() if p.name.isdigit()) == ["00000006"]
    assert not [p for p in wip.parent.iterdir() if p.name.startswith(".")]
    # never restored over newer work, nor saved over something else
    with pytest.raises(InputError, match="already holds the run at step 6"):
        restore_wip(wip, fresh)
    with pytest.raises(InputError, match="is not a saved run state"):
        save_wip(fresh, play_store)
    with pytest.raises(InputError, match="is not a training run"):
        save_wip(tmp_path / "nothing", tmp_path / "w2")


def test_a_dynamics_run_resumes_from_latents_encoded_on_another_cpu(play_store, tmp_path, one_thread):
    """A new machine encodes the store again, and its CPU's bf16 latents differ from the
    first machine's in their last bits, so their statistics differ too: the resumed run
    keeps the latent standardisation it started with (before, it refused the run as one of
    a different config)."""
    from safetensors import safe_open

    from iwsim.core.checkpoint import save_tensors
    from iwsim.world_model import WorldModel

    ae, run, cache = tmp_path / "ae", tmp_path / "dyn", tmp_path / "latents.safetensors"
    common = ["--data", str(play_store), "--preset", "tiny", "--no-progress", "--latent-cache", str(cache)]
    assert main(["train", "ae", "--data", str(play_store), "--preset", "tiny", "--out", str(ae), "--no-progress"]) == 0
    assert main(["train", "dynamics", "--ae", str(ae), "--out", str(run), "--steps", "3", *common]) == 0
    before = WorldModel.load(run / "checkpoints" / "00000003")
    with safe_open(cache, "pt") as f:  # the other machine's latents: the same up to a last bit
        meta, latents = f.metadata(), f.get_tensor("latents")
    save_tensors({"latents": (latents.float() * 1.002 + 0.001).half()}, cache, metadata=meta)
    assert main(["train", "dynamics", "--ae", str(ae), "--out", str(run), "--steps", "6", *common]) == 0
    after = WorldModel.load(run / "checkpoints" / "00000006")
    assert after.latent_scale == before.latent_scale
    assert torch.equal(after.latent_mean, before.latent_mean)
