"""What the imitation policies share: observation/action normalisation, the batch they
train on, a small image encoder, and the execution interface.

Observations, as the policies take them (LeRobot's names)::

    obs["image"]      (B, To, H, W, 3V) uint8 or (B, To, 3V, H, W) float in [-1, 1]
    obs["agent_pos"]  (B, To, S) float, in the data's units

V is the number of camera views the policy sees (``policy.cameras``, as its training store
named them, :mod:`iwsim.data.views`), stacked along the channels in that order
(:func:`iwsim.data.views.stack_views`): view v in channels 3v..3v+2; one view is the
frame itself.

``predict_action(obs) -> (B, Ta, A)`` returns the actions to execute next, in the data's
units; the caller executes them in order and asks again. A policy trained with
``relative_actions`` predicts offsets from the current agent_pos and adds it back, so its
callers see absolute actions all the same. ``reset()`` forgets what the
policy remembers between calls (an action queue, the ensembling buffer).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from iwsim.core.errors import InputError
from iwsim.core.normalize import Normalizer
from iwsim.data.views import DEFAULT_CAMERA
from iwsim.envs.task import Task
from iwsim.policies.registry import policy_name


@dataclass
class PolicyBatch:
    """Training windows. image (B, To, 3V, H, W) in [-1, 1] (V views stacked along the
    channels); agent_pos (B, To, S) and
    action (B, Tp, A) normalised to [-1, 1]; action_is_pad (B, Tp) marks actions past the
    episode's end (repeats of the last one)."""

    image: torch.Tensor
    agent_pos: torch.Tensor
    action: torch.Tensor
    action_is_pad: torch.Tensor

    def to(self, device: torch.device | str) -> PolicyBatch:
        return PolicyBatch(*(t.to(device) for t in (self.image, self.agent_pos, self.action, self.action_is_pad)))


class PolicyLike(Protocol):
    """The execution interface (see the module docstring) of a learned or a scripted policy."""

    @property
    def obs_horizon(self) -> int: ...

    def reset(self) -> None: ...

    def predict_action(self, obs: dict) -> np.ndarray: ...


class Policy(nn.Module):
    """What every policy keeps: its config, the normalisers (buffers, so saved with the
    weights), the action and state sizes, and the window it trains on: ``obs_horizon``
    observed steps and ``horizon`` actions from the first of them."""

    image_size: int  # the frames it was trained on; set by iwsim.policies.factory.load_policy
    task: Task | None = None  # the task of its training episodes (load_policy: as its checkpoint records it)
    name = "the policy"  # what errors call it (load_policy: "policy PATH")

    def __init__(self, cfg, action_norm: Normalizer, state_norm: Normalizer) -> None:
        super().__init__()
        self.cfg, self.action_norm, self.state_norm = cfg, action_norm, state_norm
        self.action_dim = int(action_norm.low.shape[0])
        self.state_dim = int(state_norm.low.shape[0])

    @property
    def kind(self) -> str:
        """The policy's registered name (what its checkpoints store)."""
        return policy_name(self.cfg)

    @property
    def obs_horizon(self) -> int:
        return self.cfg.obs_horizon

    @property
    def horizon(self) -> int:
        return self.cfg.horizon

    @property
    def cameras(self) -> tuple[str, ...]:
        """The camera views it sees, in the order they are stacked along the channels (a
        policy whose config has no ``cameras`` sees one view)."""
        return tuple(getattr(self.cfg, "cameras", (DEFAULT_CAMERA,)))

    @property
    def views(self) -> int:
        return len(self.cameras)

    @property
    def relative(self) -> bool:
        """Whether the network predicts actions as offsets from the current agent_pos."""
        return self.cfg.relative_actions

    def to_absolute(self, action: torch.Tensor, obs: dict) -> torch.Tensor:
        """Unnormalised predicted actions (B, T, A) -> actions in the data's units: with
        relative actions, plus the agent_pos of the current (last observed) step."""
        if not self.relative:
            return action
        pos = torch.as_tensor(obs["agent_pos"], dtype=action.dtype, device=action.device)
        return action + pos[:, -1:, :]

    def reset(self) -> None:
        """Forget what the policy remembers between calls (see the module docstring)."""
        raise NotImplementedError

    def predict_action(self, obs: dict) -> np.ndarray:
        """The actions (B, Ta, A) to execute next, in the data's units (see the module docstring)."""
        raise NotImplementedError


def random_shift(image: torch.Tensor, pad: int, offsets: torch.Tensor | None = None, views: int = 1
                 ) -> torch.Tensor:
    """Shift augmentation (DrQ, Kostrikov et al. 2021; Diffusion Policy's random crop):
    each window of (B, To, C, H, W) images moves by up to ``pad`` pixels in x and y, the
    same for its To frames (motion between them stays true), the border repeated.
    ``offsets`` (2, B) in [0, 2 * pad] are drawn from torch's generator when not given.
    With ``views`` > 1 (views stacked along the channels) each view of a window moves by
    its own offsets, as Diffusion Policy crops each camera's image on its own: ``offsets``
    (2, B * views), window b's views at b * views .. b * views + views - 1."""
    if pad <= 0:
        return image
    if views > 1:
        b, to, c, h, w = image.shape
        one = image.reshape(b, to, views, c // views, h, w).transpose(1, 2).reshape(b * views, to, c // views, h, w)
        out = random_shift(one, pad, offsets)
        return out.reshape(b, views, to, c // views, h, w).transpose(1, 2).reshape(b, to, c, h, w)
    b, to, c, h, w = image.shape
    padded = F.pad(image.reshape(b, to * c, h, w), (pad, pad, pad, pad), mode="replicate")
    dy, dx = torch.randint(0, 2 * pad + 1, (2, b)) if offsets is None else offsets
    rows = (dy[:, None] + torch.arange(h))[:, :, None]  # (B, H, 1)
    cols = (dx[:, None] + torch.arange(w))[:, None, :]  # (B, 1, W)
    out = padded[torch.arange(b)[:, None, None], :, rows, cols]  # (B, H, W, To*C)
    return out.permute(0, 3, 1, 2).reshape(b, to, c, h, w)


class SpatialSoftmax(nn.Module):
    """Expected (x, y) image coordinates of each feature map (Levine et al. 2016), as
    Diffusion Policy's and robomimic's image encoders pool."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(N, C, H, W) -> (N, 2C)."""
        n, c, h, w = x.shape
        attn = F.softmax(x.flatten(2), dim=-1).view(n, c, h, w)
        ys = torch.linspace(-1, 1, h, device=x.device, dtype=x.dtype)
        xs = torch.linspace(-1, 1, w, device=x.device, dtype=x.dtype)
        return torch.cat([(attn.sum(2) * xs).sum(-1), (attn.sum(3) * ys).sum(-1)], 1)


class ImageEncoder(nn.Module):
    """A small CNN trained from scratch (no downloads): GroupNorm instead of BatchNorm (as
    Diffusion Policy replaces it), spatial-softmax keypoints, a linear projection."""

    def __init__(self, out_dim: int = 64, channels: tuple[int, ...] = (32, 64, 64), keypoints: int = 32,
                 first_stride: int = 1) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        c_in = 3
        for i, c in enumerate(channels):  # every layer after the first halves H and W
            stride = first_stride if i == 0 else 2
            layers += [nn.Conv2d(c_in, c, 3, stride=stride, padding=1), nn.GroupNorm(8, c), nn.ReLU()]
            c_in = c
        layers.append(nn.Conv2d(c_in, keypoints, 1))
        self.net = nn.Sequential(*layers)
        self.pool = SpatialSoftmax()
        self.proj = nn.Linear(2 * keypoints, out_dim)
        self.out_dim = out_dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 3, H, W) in [-1, 1] -> (N, out_dim)."""
        return self.proj(self.pool(self.net(x)))


def prepare_obs(obs: dict, state_norm: Normalizer, obs_horizon: int, cameras: tuple[str, ...] = (DEFAULT_CAMERA,)
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """obs dict (see the module docstring) -> image (B, To, 3V, H, W) in [-1, 1] and the
    normalised agent_pos (B, To, S), on the normaliser's device; checks the horizon and
    that the images hold the V views of ``cameras``."""
    device = state_norm.low.device
    image = torch.as_tensor(np.asarray(obs["image"]) if not torch.is_tensor(obs["image"]) else obs["image"])
    pos = torch.as_tensor(np.asarray(obs["agent_pos"]), dtype=torch.float32)
    c = 3 * len(cameras)
    if image.ndim != 5 or pos.ndim != 3 or image.shape[:2] != pos.shape[:2]:
        raise InputError(f"expected image (B, To, H, W, {c}) and agent_pos (B, To, S), got {tuple(image.shape)} "
                         f"and {tuple(pos.shape)}.")
    if image.shape[1] != obs_horizon:
        raise InputError(f"this policy observes {obs_horizon} steps, got {image.shape[1]}.")
    uint8 = image.dtype == torch.uint8
    have = image.shape[-1] if uint8 else image.shape[2]
    if have != c:
        layout = f"(B, To, H, W, {c}) uint8" if uint8 else f"(B, To, {c}, H, W) float"
        got = f"{have // 3} view(s)" if have % 3 == 0 else f"{have} channels"
        raise InputError(f"this policy sees {len(cameras)} camera view(s) ({', '.join(cameras)}) stacked along the "
                         f"channels, images {layout}; got {tuple(image.shape)}: {got}.")
    if uint8:
        image = image.permute(0, 1, 4, 2, 3).float() / 127.5 - 1
    if pos.shape[-1] != state_norm.low.shape[0]:
        raise InputError(f"this policy takes a {state_norm.low.shape[0]}-D agent_pos, got {pos.shape[-1]}.")
    return image.float().to(device), state_norm.normalize(pos.to(device))
