"""Training windows for the policies, from a mixture of episode stores.

``--data sim.zarr:30,mujoco.zarr:70`` takes exactly the first 30 episodes of the first
store and the first 70 of the second (``store`` alone takes all of its episodes). A
window at step t of an episode holds the observations of steps t-To+1 .. t and the
actions of steps t-To+1 .. t-To+Tp, as Diffusion Policy's sampler: steps before the
episode's start repeat its first step, actions past its end repeat the last one and are
marked as padding.

A store of several camera views (:mod:`iwsim.data.views`) gives frames of every view
stacked along the channels, (H, W, 3V) a step (:func:`iwsim.data.views.stack_views`); the
stores of a mixture must hold the same views.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from iwsim.core.errors import InputError
from iwsim.data.store import EpisodeStore
from iwsim.data.views import check_cameras, stack_views, store_cameras, view_key
from iwsim.policies.common import Normalizer, PolicyBatch


@dataclass(frozen=True)
class Source:
    path: Path
    episodes: int | None  # None: all of them


def parse_mixture(spec: str) -> list[Source]:
    """``"a.zarr:30,b.zarr:70"`` (or ``"a.zarr"``) -> sources; a clear error otherwise."""
    sources = []
    for part in (p.strip() for p in spec.split(",")):
        if not part:
            continue
        path, sep, count = part.rpartition(":")
        if not sep or not count.isdigit():
            path, count = part, ""
        if count and int(count) < 1:
            raise InputError(f"episode count of {path} must be >= 1, got {count}.")
        sources.append(Source(Path(path), int(count) if count else None))
    seen: dict[str, str] = {}
    for src in sources:  # the same store twice would repeat its episodes without a word
        key = os.path.realpath(src.path)
        if key in seen:
            raise InputError(f"--data names the store {seen[key]} twice ({spec!r}); give each store once, "
                             "with the number of episodes to take from it.")
        seen[key] = str(src.path)
    if not sources:
        raise InputError(f"--data {spec!r} names no episode store; expected STORE[:N][,STORE:N...].")
    return sources


class PolicyData:
    """The chosen episodes of every source, in memory, and random windows of them."""

    def __init__(self, sources: list[Source], obs_horizon: int, horizon: int, actions: str = "action",
                 cameras: tuple[str, ...] | None = None, first_only: bool = False) -> None:
        """``actions``: the array the policy learns to output (``action`` or ``target``).
        ``cameras``: the views to read from every store, in this order (None: every view of
        the first store, which every other store must hold alike; stores of one view each
        may name it differently). ``first_only``: each store's first view alone."""
        if not sources:
            raise InputError("the data mixture is empty; give at least one STORE[:N].")
        self.obs_horizon, self.horizon = obs_horizon, horizon
        chosen = cameras is not None
        self.cameras: tuple[str, ...] = () if cameras is None else check_cameras(cameras, "the policy's cameras")
        imgs, states, labels, lengths, self.counts, self.hashes = [], [], [], [], {}, {}
        for src in sources:
            store = EpisodeStore.open(src.path, "r")
            for key in ("img", "state", actions):
                if key not in store.keys:
                    raise InputError(f"{src.path} has no data/{key}; policies need img, state and {actions}.")
            views = store_cameras(store.attrs, store.keys)
            self.cameras = self.cameras or (views[:1] if first_only else views)  # by default, the first store's
            keys = ["img"] if first_only else self._view_keys(src.path, views, chosen, sources[0].path)
            n = store.n_episodes if src.episodes is None else src.episodes
            if n > store.n_episodes or n < 1:
                raise InputError(f"{src.path} holds {store.n_episodes} episodes; {n} were asked for.")
            end = int(store.episode_ends[n - 1])
            imgs.append(stack_views([np.asarray(store.array(k)[:end]) for k in keys]))
            states.append(np.asarray(store.array("state")[:end], np.float32))
            labels.append(np.asarray(store.array(actions)[:end], np.float32))
            ends = store.episode_ends[:n]
            lengths += np.diff(ends, prepend=0).tolist()
            self.counts[os.fspath(src.path)] = n
            self.hashes[os.fspath(src.path)] = store.content_hash(n)  # the data's identity, wherever it lies
            for name, arrays in (("frames", imgs), ("state", states), (actions, labels)):
                if arrays[-1].shape[1:] != arrays[0].shape[1:]:
                    raise InputError(f"{src.path} has {name} of shape {arrays[-1].shape[1:]} per step, "
                                     f"{sources[0].path} {arrays[0].shape[1:]}; a mixture must agree.")
        self.img = torch.from_numpy(np.concatenate(imgs))
        self.state = torch.from_numpy(np.concatenate(states))
        self.action = torch.from_numpy(np.concatenate(labels))
        ends = np.cumsum(lengths)
        self.starts = torch.from_numpy(ends - np.asarray(lengths))
        self.ends = torch.from_numpy(ends)
        self.episode_of = torch.repeat_interleave(torch.arange(len(lengths)), torch.as_tensor(lengths))

    def _view_keys(self, path: Path, views: tuple[str, ...], chosen: bool, first: Path) -> list[str]:
        """The data arrays of the policy's views (:attr:`cameras`) in the store at ``path``,
        which holds ``views``: with the views not ``chosen``, the same as the first store's."""
        if not chosen and len(views) == len(self.cameras) == 1:
            return ["img"]  # one view each, whatever the stores call it
        if not set(self.cameras) <= set(views) or (not chosen and set(views) != set(self.cameras)):
            whose = "" if chosen else f" (the views of {first})"
            raise InputError(f"{path} holds the camera views {', '.join(views)}; the policy sees "
                             f"{', '.join(self.cameras)}{whose}: a mixture's stores must hold the same views.")
        return [view_key(views, name) for name in self.cameras]

    @property
    def views(self) -> int:
        return len(self.cameras)

    @property
    def n_episodes(self) -> int:
        return len(self.starts)

    @property
    def n_frames(self) -> int:
        return len(self.action)

    @property
    def image_size(self) -> int:
        return int(self.img.shape[1])

    def check_relative(self) -> None:
        """Relative actions are offsets from agent_pos: both must be the same quantity."""
        if self.action.shape[1] != self.state.shape[1]:
            raise InputError(f"relative actions need actions and agent_pos of one size (offsets from the current "
                             f"position); the data has {self.action.shape[1]}-D actions and {self.state.shape[1]}-D "
                             "agent_pos. Train with absolute actions (relative_actions false).")

    def actions(self, obs: torch.Tensor, act: torch.Tensor, relative: bool) -> torch.Tensor:
        """The windows' actions (B, Tp, A) in the data's units, or with ``relative`` their
        offsets from the agent_pos of each window's current (last observed) step."""
        if not relative:
            return self.action[act]
        self.check_relative()
        return self.action[act] - self.state[obs[:, -1]][:, None]

    def normalizers(self, relative: bool = False) -> tuple[Normalizer, Normalizer]:
        """Min-max bounds of the actions (with ``relative``, of their offsets over every
        window) and of the agent positions of the training data."""
        action = self.action
        if relative:
            obs, act, _ = self.windows(torch.arange(self.n_frames))
            action = self.actions(obs, act, True).flatten(0, 1)
        return (Normalizer(action.min(0).values, action.max(0).values),
                Normalizer(self.state.min(0).values, self.state.max(0).values))

    def windows(self, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Global step indices t (B,) -> observation indices (B, To), action indices
        (B, Tp) and the action padding mask (B, Tp)."""
        e = self.episode_of[t]
        lo, hi = self.starts[e][:, None], self.ends[e][:, None] - 1
        first = t[:, None] - (self.obs_horizon - 1)
        obs = (first + torch.arange(self.obs_horizon)).clamp(lo, hi)
        act = first + torch.arange(self.horizon)
        return obs, act.clamp(lo, hi), act > hi

    def batch(self, t: torch.Tensor, action_norm: Normalizer, state_norm: Normalizer,
              relative: bool = False) -> PolicyBatch:
        """The windows at global steps t (B,), normalised (see :meth:`actions`)."""
        obs, act, pad = self.windows(t)
        image = self.img[obs].permute(0, 1, 4, 2, 3).float() / 127.5 - 1
        with torch.no_grad():
            return PolicyBatch(image, state_norm.normalize(self.state[obs]),
                               action_norm.normalize(self.actions(obs, act, relative)), pad)
