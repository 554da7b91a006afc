"""Play sessions: per-connection world-model state, stepped together at a fixed control rate.

The engine knows nothing of sockets: the server calls :meth:`Engine.open` per connection,
:meth:`Engine.handle` per parsed message and :meth:`Engine.tick` once per control step,
and sends what they return. The server makes every call from one thread, so sessions need
no locks; only saving an episode goes to a writer thread.

Each session holds its own :class:`~iwsim.world_model.StreamState`. A tick joins the
states of all sessions into one batch, takes one functional step
(:meth:`~iwsim.world_model.WorldModel.step_state`) and splits the states again.

The task (:class:`iwsim.envs.task.Task`, the world model's unless the config names one)
decides the rest. Motion: a session's action is a command; the task maps it to the
executed motion (:meth:`~iwsim.envs.task.Task.executed`; for T-push the pushers approach
it at the speed limit, :func:`iwsim.envs.tabletop.scene.limit_targets`, the function MuJoCo runs
too), and the world model is conditioned on that executed motion, as it was trained.
A command outside the task's bounds is refused with one line (T-push clips it, as MuJoCo
does); the session goes on.

A world model of several camera views shows each (and the MuJoCo twin's, rendered by the
same cameras): the frame message's ``views`` name them ``world_model`` and ``mujoco`` for
the first view, ``world_model:<camera>`` and ``mujoco:<camera>`` for the others; the task
scores the first. A take stores every view (``img`` and ``img_<camera>``, as ``iwsim
collect --cameras`` does).

Recording: step t stores the frame shown before action t, the ``agent_pos`` observed
there (T-push: the pusher positions read from it), the action, the motion it executed and
the frame's pixel score if the task has a scorer (``img``, ``state``, ``action``,
``target``, ``iou``: the layout of ``iwsim collect``). The take lives in memory
until it is saved, and a save is one atomic append, so a client that vanishes
mid-recording leaves nothing behind. A save that fails (a full disk) leaves the store as it
was and the take with its session, which the next save tries again.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

import iwsim
from iwsim.core.errors import InputError
from iwsim.core.resources import MiB, human_bytes, require_memory
from iwsim.data.store import EpisodeStore, StoreError
from iwsim.data.views import DEFAULT_CAMERA, unstack_views, view_keys
from iwsim.envs import SMALLEST_FRAME_BYTES
from iwsim.envs.task import Bindings, Start, Task
from iwsim.play import protocol as proto
from iwsim.world_model import StreamState, WorldModel
from iwsim.world_model.env import (
    STORE,
    Starts,
    Views,
    predicted_agent_pos,
    predicts_agent_pos,
    resolve_task,
    score_key,
)

log = logging.getLogger(__name__)

EPISODE_KEYS = ("img", "state", "action", "target", "iou")  # T-push's; a task without a scorer has no "iou"


def episode_keys(task: Task) -> tuple[str, ...]:
    """The arrays a recorded step stores: frame, agent_pos, command, executed motion, and the score if any."""
    return ("img", "state", "action", "target", *((score_key(task),) if task.score_name else ()))


@dataclass(frozen=True)
class PlayConfig:
    hz: float = 10.0  # control steps per second
    max_sessions: int = 4
    record_to: Path | None = None  # episode store that saved takes are appended to
    store: Path | None = None  # episode store to draw "store" resets from
    task: str | Task | None = None  # default: the world model's task
    max_record_steps: int = 6000  # 10 minutes at 10 Hz
    checkpoint: str = ""  # recorded in the store's attributes
    wait_for_lock: bool = False  # when another process writes record_to: wait for it (else refuse)
    bindings: object = None  # teleop bindings in their JSON form, instead of the task's (Bindings.from_dict checks it)

    def __post_init__(self) -> None:
        if not (isinstance(self.hz, (int, float)) and 0 < self.hz <= 60):
            raise InputError(f"the control rate must be in (0, 60] Hz, got {self.hz!r}.")
        if not (isinstance(self.max_sessions, int) and self.max_sessions >= 1):
            raise InputError(f"max sessions must be a positive integer, got {self.max_sessions!r}.")
        if not (isinstance(self.max_record_steps, int) and self.max_record_steps >= 1):
            raise InputError(f"max record steps must be a positive integer, got {self.max_record_steps!r}.")


# Resident memory of one open play session (its state, queues, buffers), measured with 60
# sessions (about 12 MiB each); a session may also hold a full recording's frames.
SESSION_MIB = 12.0


def check_sessions_memory(sessions: int, record_steps: int = PlayConfig.max_record_steps) -> None:
    """Refuse ``sessions`` play sessions that cannot all fit in memory, each holding a full
    recording of ``record_steps`` frames (a lower bound: frames of the smallest size)."""
    per = SESSION_MIB * MiB + record_steps * SMALLEST_FRAME_BYTES
    require_memory(sessions * per, f"--max-sessions {sessions} (about {human_bytes(per)} per session, "
                                   "a full recording included)")


@dataclass
class Session:
    """One connection's simulator: world-model state, the current action, a MuJoCo twin in
    side-by-side mode, and the take being recorded."""

    id: int
    target: np.ndarray  # the action applied at every step until the client sends another
    setpoint: np.ndarray  # the executed motion
    ack: int = -1  # seq of the last action message
    state: StreamState | None = None
    frame: np.ndarray | None = None  # the world model's current frame (H, W, 3; several views: stacked)
    agent_pos: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    iou: float | None = 0.0  # the task's pixel score of the frame (None: the task has no scorer)
    step: int = 0
    start: Start | None = None
    source: str = ""
    seed: int = 0
    twin: Any = None  # the ground-truth simulator (MuJoCo) in side-by-side mode
    twin_frame: np.ndarray | None = None
    twin_iou: float | None = None
    take: dict[str, list] | None = None  # the recording in progress
    unsaved: list[tuple[dict[str, np.ndarray], int]] = field(default_factory=list)  # (take, seed) whose save failed
    closed: bool = False


class Recorder:
    """Appends saved takes to an episode store, one at a time, on a writer thread."""

    def __init__(self, path: Path, attrs: dict[str, Any], wait_for_lock: bool = False,
                 keys: tuple[str, ...] = EPISODE_KEYS) -> None:
        def check(store: EpisodeStore) -> None:
            have = store.attrs
            for key in ("task", "image_size", "cameras"):
                if have.get(key, [DEFAULT_CAMERA] if key == "cameras" else None) != attrs[key]:
                    raise StoreError(f"{path} holds episodes with {key}={have.get(key)!r}, not {attrs[key]!r}; "
                                     "record into another store.")
            if store.n_episodes and set(store.keys) != set(keys):
                raise StoreError(f"{path} holds arrays {store.keys}, not the recorded {sorted(keys)} "
                                 "(a store of iwsim collect?); record into another store.")

        # Held (locked) for the whole session: another writer would invalidate what we know of the store.
        self.store = EpisodeStore.open_or_create(path, attrs, check=check, wait=wait_for_lock)
        self.path = path
        self._writer = ThreadPoolExecutor(1, thread_name_prefix="iwsim-recorder")

    def save(self, episode: dict[str, np.ndarray], seed: int) -> Future[int]:
        """Append ``episode`` in the background; the future gives its index in the store."""
        def write() -> int:
            self.store.append(episode, seed=seed)
            return self.store.n_episodes - 1

        return self._writer.submit(write)

    def close(self) -> None:
        self._writer.shutdown(wait=True)
        self.store.close()


class Engine:
    """The simulator behind ``iwsim play`` (see the module docstring)."""

    def __init__(self, model: WorldModel, cfg: PlayConfig = PlayConfig()) -> None:
        self.model, self.cfg = model, cfg
        task = resolve_task(model, cfg.task)
        if cfg.bindings is not None:
            task = replace(task, bindings=Bindings.from_dict(cfg.bindings, task.action_dim, task.view_half))
        self.task = task
        self.low = np.asarray(task.action_low, np.float32)
        self.high = np.asarray(task.action_high, np.float32)
        self.views = Views(model.cameras)
        self.starts = Starts(task, model.image_size, cfg.store, cameras=self.views.cameras)
        self.keys = episode_keys(task)
        self.recorder: Recorder | None = None
        if cfg.record_to is not None:
            attrs = {**task.store_attrs(), "image_size": model.image_size, "policy": "teleop", "steps": None,
                     "iwsim_version": iwsim.__version__, "source": "world_model", "world_model": cfg.checkpoint,
                     "keys": list(self.keys), "cameras": list(self.views.cameras)}
            stored = (*self.keys, *list(view_keys(self.views.cameras).values())[1:])
            self.recorder = Recorder(Path(cfg.record_to), attrs, cfg.wait_for_lock, stored)
        self.sessions: dict[int, Session] = {}
        self._saves: list[tuple[Session, dict[str, np.ndarray], int, Future[int]]] = []
        self._next_id = 0
        self._rng = np.random.default_rng()
        self._threads = torch.get_num_threads()
        self.last_step_ms = 0.0

    # -- sessions -------------------------------------------------------------------------
    def open(self) -> Session | None:
        """A new session, reset to a fresh start of the task's own (MuJoCo for T-push), or
        None when ``max_sessions`` are open."""
        if len(self.sessions) >= self.cfg.max_sessions:
            return None
        zeros = np.zeros(self.task.action_dim, np.float32)
        s = Session(self._next_id, target=zeros, setpoint=zeros.copy(), agent_pos=zeros.copy())
        self._next_id += 1
        self.sessions[s.id] = s
        self.reset(s, self.task.start_source, None)
        return s

    def close(self, s: Session) -> None:
        """Forget the session; an unsaved take is dropped."""
        s.closed, s.take, s.unsaved = True, None, []
        if s.twin is not None:
            s.twin.close()
            s.twin = None
        self.sessions.pop(s.id, None)

    def hello(self, s: Session) -> str:
        return proto.event(
            "hello", session=s.id, image_size=self.model.image_size, hz=self.cfg.hz,
            **{**self.task.page_info(), "action_low": self.low.tolist(), "action_high": self.high.tolist()},
            reset_sources=[self.task.start_source, *([STORE] if self.starts.has_store else [])],
            side_by_side=self.task.has_ground_truth,
            recording_to=None if self.recorder is None else self.recorder.path.name,  # a name, never a path
            max_message_bytes=proto.MAX_MESSAGE_BYTES)

    # -- messages -------------------------------------------------------------------------
    def handle(self, s: Session, msg: proto.Message) -> list[str]:
        """Apply one parsed client message; returns the events to send back (the server
        also sends :meth:`frame_message` at once after a restart)."""
        if s.closed:
            return []
        if isinstance(msg, proto.Action):
            command = np.asarray(msg.action, np.float64)
            refused = self.task.out_of_bounds(command)
            if refused is not None:
                return [proto.event("error", message=refused)]
            s.target = np.clip(command.astype(np.float32), self.low, self.high)
            s.ack = msg.seq
            return []
        if isinstance(msg, proto.Reset):
            if msg.source == STORE and not self.starts.has_store:
                return [proto.event("error", message="no store to reset from; start iwsim play with --store PATH.")]
            if msg.source not in self.starts.sources:
                return [proto.event("error", message=f"task {self.task.name!r} starts from "
                                                     f"{self.task.start_source!r} or 'store', not {msg.source!r}.")]
            dropped = self._drop_take(s)
            self.reset(s, msg.source, msg.seed)
            return dropped + [self._status(s, f"reset to a {msg.source} start (seed {s.seed})")]
        if isinstance(msg, proto.SideBySide):
            if msg.on and s.twin is None:
                twin = self.task.ground_truth_env(self.model.image_size, cameras=self.views.cameras)
                if twin is None:
                    return [proto.event("error", message=f"task {self.task.name!r} has no simulator to run "
                                                         "side by side.")]
            dropped = self._drop_take(s)
            if msg.on and s.twin is None:
                s.twin = twin
            elif not msg.on and s.twin is not None:
                s.twin.close()
                s.twin, s.twin_frame, s.twin_iou = None, None, None
            self.reset(s, s.source, s.seed)
            assert s.start is not None  # set by reset
            note = "" if s.twin is None or s.start.state is not None else " (this start has no MuJoCo state)"
            return dropped + [self._status(s, f"side by side {'on' if msg.on else 'off'}: episode restarted{note}")]
        return self._command(s, msg.name)

    def _command(self, s: Session, name: str) -> list[str]:
        if name == "record":
            if s.take is not None:
                return [proto.event("error", message="already recording; save (Shift+S) or discard (q) first.")]
            if self.recorder is None:
                return [proto.event("error", message="recording is off; start iwsim play with --record-to STORE.")]
            if s.unsaved:
                return [proto.event("error", message=f"{len(s.unsaved)} take(s) could not be saved and are kept: "
                                                     "save (Shift+S) to try again, or discard (q), first.")]
            s.take = {k: [] for k in self.keys}
            return [self._status(s, "recording")]
        if s.take is None and s.unsaved:  # a save failed (e.g. a full disk): the takes are still here
            unsaved, s.unsaved = s.unsaved, []
            if name == "discard":
                return [self._status(s, f"discarded {len(unsaved)} take(s) that could not be saved")]
            for episode, seed in unsaved:
                self._save(s, episode, seed)
            return [self._status(s, f"saving {len(unsaved)} kept take(s) again")]
        if s.take is None:
            return [proto.event("error", message=f"nothing to {name}: not recording (press c to record).")]
        if name == "discard":
            n = len(s.take["img"])
            s.take = None
            return [self._status(s, f"discarded {n} steps")]
        take, s.take = s.take, None
        if not take["img"]:
            return [self._status(s, "nothing recorded yet; take discarded")]
        episode = self._episode(take)
        self._save(s, episode, s.seed)
        return [self._status(s, f"saving {len(episode['img'])} steps")]

    def _episode(self, take: dict[str, list]) -> dict[str, np.ndarray]:
        """A take's arrays in the store's layout: each view of the frames in its own array."""
        episode = {k: np.stack(v) for k, v in take.items()}
        frames = unstack_views(episode.pop("img"), len(self.views.cameras))
        episode.update(zip(view_keys(self.views.cameras).values(), frames, strict=True))
        return episode

    def _save(self, s: Session, episode: dict[str, np.ndarray], seed: int) -> None:
        assert self.recorder is not None  # takes are recorded only with a recorder
        self._saves.append((s, episode, seed, self.recorder.save(episode, seed)))

    def finished_saves(self) -> list[tuple[Session, str]]:
        """Events for the saves written since the last call: ``saved`` with the episode's
        index in the store, or an ``error`` if the append failed (the store is unchanged, and
        the session keeps the take: its next save tries again)."""
        done = [x for x in self._saves if x[3].done()]
        self._saves = [x for x in self._saves if not x[3].done()]
        out = []
        for s, episode, seed, future in done:
            assert self.recorder is not None  # it made the save
            n = len(episode["img"])
            try:
                out.append((s, proto.event("saved", episode=future.result(), steps=n,
                                           store=self.recorder.path.name)))
            except Exception as e:  # noqa: BLE001 - the client hears why; the server goes on
                log.error("saving a take of session %d failed: %s", s.id, e)
                if not s.closed:
                    s.unsaved.append((episode, seed))
                out.append((s, proto.event("error", message=f"saving failed: {e}; the take of {n} steps is kept: "
                                                            "save (Shift+S) to try again, or discard (q).")))
        return out

    def _drop_take(self, s: Session) -> list[str]:
        if s.take is None:
            return []
        n = len(s.take["img"])
        s.take = None
        return [proto.event("status", message=f"recording of {n} steps discarded by the restart", recording=None)]

    def _status(self, s: Session, message: str) -> str:
        return proto.event("status", message=message, recording=None if s.take is None else len(s.take["img"]))

    # -- stepping -------------------------------------------------------------------------
    def reset(self, s: Session, source: str, seed: int | None) -> None:
        """Start the session's episode from the task's own start (a MuJoCo reset for
        T-push, a dataset episode's first frame otherwise) or a store frame."""
        seed = int(self._rng.integers(proto.MAX_SEED)) if seed is None else seed
        start = self.starts.draw(seed, source)
        own = start.agent_pos[None] if predicts_agent_pos(self.model, self.task) else None
        s.state = self.model.reset_state(start.frame[None], seed=seed, held=np.asarray(start.command, np.float32)[None],
                                         state=own)
        s.start, s.source, s.seed, s.step = start, source, seed, 0
        s.frame, s.agent_pos = start.frame, start.agent_pos.astype(np.float32)
        # the robot holds still: the command is where it is (T-push: MuJoCo's position
        # controllers start at the pushers)
        s.target = np.clip(start.command.astype(np.float32), self.low, self.high)
        s.setpoint = start.command.astype(np.float32)
        score = self.task.score(self.views.first(s.frame[None]))
        s.iou = None if score is None else float(score[0])
        s.twin_frame = s.twin_iou = None
        if s.twin is not None and start.state is not None:
            obs, info = s.twin.reset(seed=seed, options={"reset_to_state": start.state})
            s.twin_frame, s.twin_iou = self.views.stacked(obs["pixels"]), float(info[score_key(self.task)])

    def tick(self) -> list[Session]:
        """One control step of every session: record, then step all world models in one
        batched pass, and the MuJoCo twins. Returns the sessions stepped."""
        ready = [(s, s.state) for s in self.sessions.values() if s.state is not None]
        if not ready:
            return []
        sessions = [s for s, _ in ready]
        t0 = time.perf_counter()
        for s in sessions:
            s.setpoint = self.task.executed(s.setpoint, s.target).astype(np.float32)
            if s.take is not None and len(s.take["img"]) < self.cfg.max_record_steps:
                for key, value in zip(self.keys, (s.frame, s.agent_pos, s.target, s.setpoint, s.iou)):
                    s.take[key].append(np.asarray(value, np.uint8 if key == "img" else np.float32))
        state = ready[0][1] if len(ready) == 1 else StreamState.cat([st for _, st in ready])
        # One session's step is too small to gain from a second thread, and with the browser
        # on the same cores a second thread makes it slower; batches do gain
        # (bench/bench_play.py measures both).
        torch.set_num_threads(1 if len(sessions) == 1 else self._threads)
        try:
            state, frames = self.model.step_state(state, np.stack([s.setpoint for s in sessions]))
        finally:
            torch.set_num_threads(self._threads)
        own = predicted_agent_pos(self.model, self.task, state)
        states = [state] if len(sessions) == 1 else state.split()
        for s, state, frame in zip(sessions, states, frames):
            s.state, s.frame = state, frame
        setpoints, positions = np.stack([s.setpoint for s in sessions]), np.stack([s.agent_pos for s in sessions])
        ious, pos = self.task.observe(self.views.first(np.stack(list(frames))), setpoints, positions, own)
        for i, (s, p) in enumerate(zip(sessions, pos)):
            s.iou, s.agent_pos, s.step = None if ious is None else float(ious[i]), p, s.step + 1
            if s.twin_frame is not None:
                obs, _, _, _, info = s.twin.step(s.target)
                s.twin_frame, s.twin_iou = self.views.stacked(obs["pixels"]), float(info[score_key(self.task)])
        self.last_step_ms = 1000 * (time.perf_counter() - t0)
        return sessions

    def frame_message(self, s: Session) -> bytes:
        """The session's current frame(s) and what the page shows with them."""
        assert s.frame is not None  # set by reset
        n = len(self.views.cameras)
        sources = [("world_model", s.frame)] + ([] if s.twin_frame is None else [("mujoco", s.twin_frame)])
        views, names = [], []
        for source, frames in sources:
            for camera, frame in zip(self.views.cameras, unstack_views(frames, n), strict=True):
                views.append(frame)
                names.append(source if camera == self.views.cameras[0] else f"{source}:{camera}")
        header = {
            "type": "frame", "step": s.step, "ack": s.ack, "action": s.target.tolist(),
            "agent_pos": s.agent_pos.tolist(), "iou": s.iou, "mujoco_iou": s.twin_iou,
            "size": self.model.image_size, "views": names, "source": s.source, "seed": s.seed,
            "recording": None if s.take is None else len(s.take["img"]),
            "record_limit": self.cfg.max_record_steps, "step_ms": round(self.last_step_ms, 2),
            "sessions": len(self.sessions),
        }
        return proto.pack_frame(header, views)

    def shutdown(self) -> None:
        for s in list(self.sessions.values()):
            self.close(s)
        if self.recorder is not None:
            self.recorder.close()
        self.starts.close()

