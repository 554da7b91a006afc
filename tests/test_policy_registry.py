"""The policy registry: a policy is its registered config class. One defined in this test
alone trains, saves, loads and evaluates through the command line with no other file
changed; the registered names are the ones checkpoints store."""

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from torch import nn
from torch.nn import functional as F

from iwsim.cli import build_parser, main
from iwsim.core.config import TrainConfig
from iwsim.policies import POLICIES, PRESETS, PolicyStageConfig, config_class, register_policy
from iwsim.policies.common import Policy, PolicyBatch, prepare_obs
from iwsim.policies.factory import load_policy

pytestmark = pytest.mark.usefixtures("one_thread")


@dataclasses.dataclass(frozen=True)
class LinearConfig:
    """A third policy: a linear map from the current agent_pos to a chunk of actions."""

    obs_horizon: int = 1
    horizon: int = 4
    n_action_steps: int = 2
    relative_actions: bool = False


class LinearPolicy(Policy):
    def __init__(self, cfg: LinearConfig, action_norm, state_norm) -> None:
        super().__init__(cfg, action_norm, state_norm)
        self.net = nn.Linear(self.state_dim, cfg.horizon * self.action_dim)

    def chunk(self, pos: torch.Tensor) -> torch.Tensor:
        """Normalised agent_pos (B, To, S) -> normalised chunk (B, Tp, A)."""
        return self.net(pos[:, -1]).view(len(pos), self.cfg.horizon, self.action_dim)

    def forward(self, batch: PolicyBatch) -> tuple[torch.Tensor, dict[str, float]]:
        return F.mse_loss(self.chunk(batch.agent_pos), batch.action), {}

    def reset(self) -> None:
        pass

    @torch.no_grad()
    def predict_action(self, obs: dict, generator: torch.Generator | None = None) -> np.ndarray:
        _, pos = prepare_obs(obs, self.state_norm, self.cfg.obs_horizon)
        act = self.action_norm.unnormalize(self.chunk(pos)[:, :self.cfg.n_action_steps])
        return self.to_absolute(act, obs).cpu().numpy()


@pytest.fixture
def linear_policy():
    """``linear`` registered for the test only (the registry is left as it was)."""
    before, presets = dict(POLICIES), dict(PRESETS)
    train = TrainConfig(steps=4, batch_size=4, lr=1e-3, warmup_steps=1, eval_every=2, checkpoint_every=2, log_every=2)
    register_policy("linear", model=f"{__name__}:LinearPolicy", execution=("n_action_steps",),
                    presets={"linear": PolicyStageConfig("linear", {}, train, shift=0)})(LinearConfig)
    yield
    POLICIES.clear(), POLICIES.update(before)
    PRESETS.clear(), PRESETS.update(presets)


def test_the_shipped_policies_keep_the_names_their_checkpoints_store():
    assert {"dp", "act"} <= set(POLICIES)
    assert {name: p.policy for name, p in PRESETS.items() if name in ("dp", "act", "tiny-dp", "tiny-act")} == {
        "dp": "dp", "act": "act", "tiny-dp": "dp", "tiny-act": "act"}
    assert config_class("dp").__name__ == "DiffusionConfig" and POLICIES["act"].policy_class().__name__ == "ACTPolicy"
    with pytest.raises(ValueError, match="unknown policy 'nope'; expected one of"):
        config_class("nope")


def test_a_registered_name_cannot_be_taken_twice(linear_policy):
    with pytest.raises(ValueError, match="already registered"):
        register_policy("linear", model=f"{__name__}:LinearPolicy")(dataclasses.make_dataclass("Other", []))


def test_a_policy_registered_in_a_test_trains_loads_and_evaluates_through_the_cli(linear_policy, play_store,
                                                                                     tmp_path, capsys):
    parser = build_parser()  # the command line reads its choices from the registry
    assert parser.parse_args(["train", "policy", "--policy", "linear", "--data", "x", "--out", "y"]).policy == "linear"
    out = tmp_path / "linear"
    assert main(["train", "policy", "--policy", "linear", "--data", f"{play_store}:2", "--out", str(out),
                 "--no-progress"]) == 0
    assert json.loads((out / "checkpoints" / "last" / "config.json").read_text())["policy"] == "linear"
    policy = load_policy(out, n_action_steps=1)
    assert isinstance(policy, LinearPolicy) and policy.kind == "linear" and policy.cfg.n_action_steps == 1
    assert main(["eval", "policy", "--checkpoint", str(out), "--episodes", "1", "--steps", "4", "--videos", "0",
                 "--out", str(tmp_path / "eval"), "--no-progress"]) == 0
    assert len(json.loads((tmp_path / "eval" / "results.json").read_text())["episodes"]) == 1


def test_the_command_line_reads_the_registry_without_importing_torch():
    code = "import sys, iwsim.cli; iwsim.cli.build_parser(); assert 'torch' not in sys.modules, 'torch imported'"
    subprocess.run([sys.executable, "-c", code], check=True)
