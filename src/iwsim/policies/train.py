"""Training a policy (``iwsim train policy``) with the generic loop: random windows of a
mixture of stores, checkpoints every ``checkpoint_every`` steps (all kept: choosing among
them is what evaluation is for), resumption, EMA weights exported."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from iwsim.core import trainer
from iwsim.core.config import from_dict, to_dict
from iwsim.core.errors import InputError
from iwsim.envs.registry import REGISTRY, task_from_store
from iwsim.envs.task import Task
from iwsim.policies import PolicyStageConfig, config_class
from iwsim.policies.common import Policy, random_shift
from iwsim.policies.data import PolicyData, Source
from iwsim.policies.factory import complete_config, describe, make_policy

EVAL_WINDOWS = 64  # fixed windows scored at every evaluation


class PolicyTask:
    """Batches of windows from the mixture; evaluation scores sampled action chunks."""

    def __init__(self, cfg: PolicyStageConfig, sources: list[Source]) -> None:
        model: Any = from_dict(config_class(cfg.policy), cfg.model)  # the registered policy's config dataclass
        # The camera views come from the data (every view of its stores) unless the config names
        # some; a policy whose config has no cameras sees each store's first view.
        has_views = hasattr(model, "cameras")
        self.data = PolicyData(sources, model.obs_horizon, model.horizon, cfg.actions,
                               cameras=model.cameras if "cameras" in cfg.model else None, first_only=not has_views)
        self.relative = model.relative_actions
        self.action_norm, self.state_norm = self.data.normalizers(self.relative)
        fields = {**cfg.model, "cameras": self.data.cameras} if has_views else cfg.model
        with torch.random.fork_rng():  # initial weights from the run's seed, global RNG untouched
            torch.manual_seed(cfg.train.seed)
            self.module = make_policy(cfg.policy, fields, self.action_norm, self.state_norm)
        self.cfg, self.sources = cfg, sources
        self.task = mixture_task(sources)
        g = torch.Generator().manual_seed(12345)
        self.eval_steps = torch.randint(0, self.data.n_frames, (min(EVAL_WINDOWS, self.data.n_frames),), generator=g)

    def batch(self, step: int, generator: torch.Generator, part: slice, device: torch.device):
        t = torch.randint(0, self.data.n_frames, (self.cfg.train.batch_size,), generator=generator)
        views = self.data.views  # each view of a window shifts by its own offsets (random_shift)
        shifts = torch.randint(0, 2 * self.cfg.shift + 1, (2, len(t) * views), generator=generator)
        # The policies draw their noise (diffusion steps, CVAE samples, dropout) from torch's
        # global generator; seeding it from the step's generator keeps resumption exact.
        torch.manual_seed(int(torch.randint(2**62, (1,), generator=generator)))
        batch = self.data.batch(t[part], self.action_norm, self.state_norm, self.relative)
        batch.image = random_shift(batch.image, self.cfg.shift, shifts.view(2, len(t), views)[:, part].flatten(1),
                                   views)
        return batch.to(device)

    @torch.no_grad()
    def evaluate(self, module: Policy, step: int, out_dir: Path) -> dict[str, float]:
        """The training loss and the error of the chunk the policy would sample, on fixed
        windows of the training data (closed-loop success is ``iwsim eval policy``'s job)."""
        batch = self.data.batch(self.eval_steps, self.action_norm, self.state_norm,
                                self.relative).to(module.action_norm.low.device)
        torch.manual_seed(step)
        loss, _ = module(batch)
        obs = {"image": batch.image, "agent_pos": module.state_norm.unnormalize(batch.agent_pos)}
        pred = torch.as_tensor(module.predict_action(obs))
        module.reset()
        start = module.obs_horizon - 1
        truth = module.to_absolute(module.action_norm.unnormalize(batch.action[:, start:start + pred.shape[1]]),
                                   obs).cpu()
        return {"loss": loss.item(), "action_mae": (pred - truth).abs().mean().item()}

    def export(self, module: Policy) -> dict[str, torch.Tensor]:
        return dict(module.state_dict())

    def config(self) -> dict[str, Any]:
        return {**describe(self.module), "task": self.task.describe(), "train": to_dict(self.cfg.train),
                "shift": self.cfg.shift,
                "data": [{"path": str(s.path), "episodes": s.episodes, "sha256": self.data.hashes[os.fspath(s.path)]}
                         for s in self.sources],
                "episodes_used": self.data.counts, "image_size": self.data.image_size}


def mixture_task(sources: list[Source]) -> Task:
    """The task whose episodes a mixture holds (what the policy's config records): the
    built-in task its stores name, else the first store's; stores of two built-in tasks are
    one line of error."""
    tasks = [task_from_store(s.path) for s in sources]
    built_in = {t.name: s.path for t, s in zip(tasks, sources) if t.kind in REGISTRY}
    if len(built_in) > 1:
        (a, path_a), (b, path_b) = list(built_in.items())[:2]
        raise InputError(f"--data mixes episodes of task {a!r} ({path_a}) and task {b!r} ({path_b}); a policy "
                         "learns one task.")
    return next((t for t in tasks if t.kind in REGISTRY), tasks[0])


def train_policy(cfg: PolicyStageConfig, sources: list[Source], out: str | Path, *, device: torch.device,
                 force: bool = False, progress: bool = True) -> dict[str, float]:
    """Train (or resume) a policy into the run directory ``out``."""
    task = PolicyTask(cfg, sources)
    return trainer.train(task, cfg.train, Path(out), task.config(), device=device, force=force, progress=progress,
                         complete=complete_config)
