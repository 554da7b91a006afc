"""Scripted policies for pile sweeping (:mod:`iwsim.envs.pilesweep.sim`): ``play`` (world-model
data) and ``expert`` (sweeps the pile into the tray), with the expert's degraded variants.

Every policy here reads nothing but the observation: the pieces it sees in the frame
(:func:`~iwsim.envs.pilesweep.pixels.find_pieces`) and the pushers' ``agent_pos``; so the
same policies run in MuJoCo and inside a world model. Called as ``policy(obs, info) ->
action`` after ``policy.reset(obs, info)`` (:mod:`iwsim.envs.tabletop.scripting`).

The expert sweeps with a *broom*: the two pushers side by side, closer than a piece is
wide, so no piece slips between them. A stroke starts behind a loose piece and pushes it
to the nearest point well inside the tray, and with it the pieces in its lane; of all
the loose pieces, the expert starts behind the one whose lane holds the most pieces per
step of getting there and sweeping. Then the broom backs off, and each pusher travels to
its place at the next stroke's start on a shortest route around the pieces (a grid
planner), never through them. A piece pushed by round pushers slides off their sides, so
a stroke through a pile leaves lines of pieces along its lane; later strokes sweep them.
Measured over held-out seeds in ``bench/bench_pilesweep.py``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Generator

import gymnasium as gym
import numpy as np

from iwsim.core.errors import InputError
from iwsim.data.views import first_view
from iwsim.envs import POLICIES as TASK_POLICIES
from iwsim.envs.pilesweep.pixels import find_pieces, piece_fraction
from iwsim.envs.pilesweep.sim import IMAGE_SIZE, PIECE_RADIUS, TRAY, in_tray, padded
from iwsim.envs.tabletop.scene import MAX_STEP, PUSHER_RADIUS, WORKSPACE
from iwsim.envs.tabletop.scripting import (
    Degraded,
    Hand,
    ScriptedPolicy,
    Transition,
    advance,
    check_policy,
    record,
    run_policy,
)

POLICIES = TASK_POLICIES["pilesweep"]
GAP = 0.010  # between the broom's two pushers: less than a piece is wide
HALF = PUSHER_RADIUS + GAP / 2  # each pusher's centre from the broom's centre
STANDOFF = PUSHER_RADIUS + PIECE_RADIUS + 0.012  # a stroke starts this far behind its piece
INSIDE = 0.03  # a stroke pushes its first piece to the nearest point this far inside the tray
# Pieces this far inside the tray's lower edge still count as loose (a stroke pushes them further in).
LOOSE_MARGIN = 0.012
MAX_NOISE = 0.012  # the noisy expert's tremor: std drawn per episode up to this (m), as T-push's
MAX_LATENCY = 5  # the lagged expert's latency: drawn per episode up to this many steps
LEAD = 0.03  # the expert's commands lead the pushers by at most this (m)
EIGHT = np.ones((3, 3), bool)


def see_pieces(obs: dict) -> np.ndarray:
    """The pieces seen in ``obs["pixels"]``: (n, 2) world positions."""
    return find_pieces(piece_fraction(first_view(obs["pixels"])))


def loose(pieces: np.ndarray) -> np.ndarray:
    """The pieces (n, 2) a sweep should still push: outside the tray or near its lower edge."""
    inside = in_tray(pieces) & (pieces[:, 1] > TRAY[2] + LOOSE_MARGIN)
    return pieces[~inside]


def aim_at(piece: np.ndarray) -> np.ndarray:
    """Where a stroke pushes ``piece``: the nearest point :data:`INSIDE` inside the tray."""
    x0, x1, y0, y1 = TRAY
    return np.array([np.clip(piece[0], x0 + INSIDE, x1 - INSIDE), np.clip(piece[1], y0 + INSIDE, y1 - INSIDE)])


def broom(centre: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """The two pushers' positions (2, 2) of a broom at ``centre`` moving along ``direction``
    (a unit vector), the left pusher on the left of the motion."""
    across = np.array([-direction[1], direction[0]])
    return np.clip(np.stack([centre + HALF * across, centre - HALF * across]), -WORKSPACE, WORKSPACE)


class Grid:
    """Routes for a pusher around the pieces: a grid over the workspace (``cell`` m), a
    cell blocked when a piece is within ``clearance`` of it; :meth:`next_point` heads for
    a goal along the shortest free path (8-connected; the wavefront by dilation)."""

    def __init__(self, cell: float = 0.01) -> None:
        self.cell = cell
        self.n = int(np.ceil(2 * WORKSPACE / cell)) + 1
        axis = -WORKSPACE + cell * np.arange(self.n)
        self.points = np.stack(np.meshgrid(axis, axis, indexing="ij"), axis=-1)  # (n, n, 2): [i, j] -> (x, y)

    def index(self, p: np.ndarray) -> tuple[int, int]:
        i, j = np.clip(np.rint((np.asarray(p) + WORKSPACE) / self.cell).astype(int), 0, self.n - 1)
        return int(i), int(j)

    def blocked(self, pieces: np.ndarray, clearance: float, free: tuple[np.ndarray, ...] = ()) -> np.ndarray:
        """(n, n) bool: cells within ``clearance`` of a piece, except those within it of a point of ``free``."""
        out = np.zeros((self.n, self.n), bool)
        for q in pieces:
            out |= ((self.points - q) ** 2).sum(-1) < clearance**2
        for q in free:
            out &= ((self.points - q) ** 2).sum(-1) >= clearance**2
        return out

    def next_point(self, start: np.ndarray, goal: np.ndarray, blocked: np.ndarray) -> np.ndarray:
        """Where to head from ``start`` for ``goal``: the farthest point of the shortest free
        path that is in straight sight (``goal`` itself when in sight or unreachable)."""
        if self._clear(start, goal, blocked):
            return goal
        from scipy import ndimage  # here: half a second of every iwsim process's start-up, which imports the tasks

        free = ~blocked
        dist = np.full(blocked.shape, -1)
        front = np.zeros_like(free)
        front[self.index(goal)] = True
        s = self.index(start)
        for step in range(4 * self.n):
            dist[front & (dist < 0)] = step
            if dist[s] >= 0:
                break
            front = ndimage.binary_dilation(front, structure=EIGHT) & free & (dist < 0)
            if not front.any():
                return goal  # walled in: straight for it
        if dist[s] < 0:
            return goal
        path, here = [], s
        while dist[here] > 0:
            i, j = here
            window = dist[max(i - 1, 0):i + 2, max(j - 1, 0):j + 2]
            options = np.argwhere((window >= 0) & (window < dist[here]))
            di, dj = options[np.argmin(window[tuple(options.T)])]
            here = (max(i - 1, 0) + int(di), max(j - 1, 0) + int(dj))
            path.append(self.points[here])
        sight = [q for q in path[:8] if self._clear(start, q, blocked)]
        return sight[-1] if sight else path[0]

    def _clear(self, a: np.ndarray, b: np.ndarray, blocked: np.ndarray) -> bool:
        n = max(2, int(np.linalg.norm(b - a) / (self.cell / 2)) + 1)
        return not any(blocked[self.index(a + (b - a) * t)] for t in np.linspace(0.0, 1.0, n))


class SweepExpert:
    """Sweeps the pile into the tray from pixels, with a broom (see the module docstring).

    ``speed``: how far the broom moves per step while sweeping (m); the pushers travel to
    a stroke's start at the task's speed limit, each on its own route around the pieces.
    ``info`` is never read.
    """

    def __init__(self, speed: float = MAX_STEP) -> None:
        self.speed = speed
        self.grid = Grid()
        self._last = np.zeros(4, np.float32)

    def reset(self, obs: dict, info: dict) -> None:
        self.phase = "plan"
        self.direction = np.array([0.0, 1.0])
        self.slots = np.zeros((2, 2))
        self.back = np.zeros(2)
        self.end = np.zeros(2)
        self._centre = np.zeros(2)
        self.stalled = 0
        self._last = np.asarray(obs["agent_pos"], np.float32).copy()

    def __call__(self, obs: dict, info: dict) -> np.ndarray:
        pushers = np.asarray(obs["agent_pos"], np.float64).reshape(2, 2)
        pieces = see_pieces(obs)
        centre = pushers.mean(0)
        # Commands move on from the last ones at the speed wanted (the pushers lag them a
        # little), but never lead a held-back pusher by more than LEAD.
        command = self._last.reshape(2, 2).astype(np.float64)
        behind = np.linalg.norm(command - pushers, axis=1) > LEAD
        command[behind] = pushers[behind]
        if self.phase == "retreat" and np.linalg.norm(centre - self.back) < 0.004:
            self.phase = "plan"
        if self.phase == "plan" and not self._plan(pushers, pieces):
            return self._last  # nothing left to sweep: hold still
        if self.phase == "travel":
            if np.max(np.linalg.norm(pushers - self.slots, axis=1)) < 0.004:
                self.phase, self.stalled, self._centre = "sweep", 0, centre
            else:
                clearance = PUSHER_RADIUS + PIECE_RADIUS + 0.004
                return self._command(np.stack([
                    advance(c, self.grid.next_point(p, slot, self.grid.blocked(pieces, clearance, (p, slot))),
                            MAX_STEP) for c, p, slot in zip(command, pushers, self.slots)]))
        if self.phase == "sweep":
            self.stalled = self.stalled + 1 if np.linalg.norm(centre - self._centre) < 0.002 else 0
            self._centre = centre
            if (self.end - centre) @ self.direction > 0.002 and self.stalled < 4:
                return self._command(self._broom(advance(command.mean(0), self.end, self.speed)))
            self.phase, self.back = "retreat", centre - self.direction * 0.03
        return self._command(self._broom(advance(command.mean(0), self.back, MAX_STEP)))

    def _broom(self, centre: np.ndarray) -> np.ndarray:
        """The pushers at a broom at ``centre``, each on the side it took at the stroke's start."""
        slots = broom(centre, self.direction)
        return slots[::-1] if self.swapped else slots

    def _plan(self, pushers: np.ndarray, pieces: np.ndarray) -> bool:
        """Choose the next stroke (its start: the two pushers' slots); False if nothing is loose.

        Each loose piece is a candidate stroke's first piece: the stroke starts behind it
        and heads for the tray; its worth is the loose pieces in its lane per step of
        getting there and sweeping it."""
        rest = loose(pieces)
        if not len(rest):
            return False
        centre = pushers.mean(0)
        best, worth = rest[0], -1.0
        for target in rest:
            aim = aim_at(target)
            u = (aim - target) / max(float(np.linalg.norm(aim - target)), 1e-9)
            rel = rest - target
            along, across = rel @ u, np.abs(rel @ np.array([-u[1], u[0]]))
            lane = int(np.sum((along > -PIECE_RADIUS) & (across < HALF + PIECE_RADIUS)))
            start = target - u * STANDOFF
            steps = float(np.linalg.norm(start - centre) + np.linalg.norm(aim - start)) / MAX_STEP
            if lane / (steps + 5) > worth:
                best, worth = target, lane / (steps + 5)
        aim = aim_at(best)
        self.direction = (aim - best) / max(float(np.linalg.norm(aim - best)), 1e-9)
        self.end = aim - self.direction * (PUSHER_RADIUS + PIECE_RADIUS)  # the first piece then reaches the aim
        slots = broom(best - self.direction * STANDOFF, self.direction)
        # each pusher takes the nearer slot (the pushers never cross on their way)
        self.swapped = bool(np.linalg.norm(pushers - slots[::-1], axis=1).sum()
                            < np.linalg.norm(pushers - slots, axis=1).sum())
        self.slots, self.phase = (slots[::-1] if self.swapped else slots), "travel"
        return True

    def _command(self, targets: np.ndarray) -> np.ndarray:
        self._last = np.clip(targets.reshape(4), -WORKSPACE, WORKSPACE).astype(np.float32)
        return self._last


class PlayPolicy:
    """Interaction with the pile of the breadth that people and policies show, for
    world-model data.

    The episode is cut into segments of 30-80 steps, each with its own speed (3-16 mm a
    step) and its own hand (:class:`~iwsim.envs.tabletop.scripting.Hand`: half lag with a time
    constant of 1.5-5 steps, half start a pause at 0.5-3% of steps, half a tremor of 1-5
    mm), of one of six kinds: rest (8%: both pushers hold still for 5-30 steps), broom
    sweeps (22%: a stroke through the pile in a random direction, a third of them towards
    the tray), the expert's own strokes (15%), pokes (25%: each pusher on its own
    approaches a piece from a random side and pushes through it by 2-8 cm), strokes
    (20%: each pusher along a line through the pile's neighbourhood) and wandering (10%:
    each pusher to a random point).
    """

    KINDS = ("rest", "broom", "expert", "poke", "stroke", "wander")
    CHANCES = (0.08, 0.22, 0.15, 0.25, 0.20, 0.10)

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        self.expert = SweepExpert()

    def reset(self, obs: dict, info: dict) -> None:
        self._left = 0
        self._command = np.asarray(obs["agent_pos"], np.float64).copy()
        self.expert.reset(obs, info)

    def _segment(self, pushers: np.ndarray, pieces: np.ndarray, obs: dict) -> None:
        rng = self.rng
        self.kind = str(rng.choice(self.KINDS, p=self.CHANCES))
        self._left = int(rng.integers(30, 81))
        self.speed = float(rng.uniform(0.003, 0.016))
        self.hand = Hand(rng, self._command, lag=float(rng.uniform(1.5, 5.0)) if rng.random() < 0.5 else 0.0,
                         pause=float(rng.uniform(0.005, 0.03)) if rng.random() < 0.5 else 0.0,
                         jitter=float(rng.uniform(0.001, 0.005)) if rng.random() < 0.5 else 0.0)
        near = pieces if len(pieces) else np.zeros((1, 2))
        if self.kind == "rest":
            self._left, self._rest = int(rng.integers(5, 31)), pushers.copy()
        elif self.kind == "expert":
            self.expert.reset(obs, {})
            self.expert.speed = max(self.speed, 0.006)
        elif self.kind == "broom":
            through = near[rng.integers(len(near))]
            if rng.random() < 1 / 3:
                angle = float(np.arctan2(*(aim_at(through) - through)[::-1]))
            else:
                angle = rng.uniform(-np.pi, np.pi)
            u = np.array([np.cos(angle), np.sin(angle)])
            length = rng.uniform(0.08, 0.25)
            start = np.clip(through - u * (STANDOFF + rng.uniform(0.0, 0.05)), -WORKSPACE, WORKSPACE)
            self.tasks = [{"stage": "approach", "points": broom(start, u)[k], "ends": broom(start + u * length, u)[k]}
                          for k in range(2)]
        else:
            self.tasks = [self._solo(p, near) for p in pushers]

    def _solo(self, p: np.ndarray, near: np.ndarray) -> dict:
        rng = self.rng
        if self.kind == "wander":
            return {"stage": "stroke", "ends": rng.uniform(-WORKSPACE, WORKSPACE, 2)}
        through = near[rng.integers(len(near))] + rng.normal(0.0, 0.01, 2)
        angle = rng.uniform(-np.pi, np.pi)
        u = np.array([np.cos(angle), np.sin(angle)])
        if self.kind == "poke":
            start = through - u * (PUSHER_RADIUS + PIECE_RADIUS + 0.015)
            end = through + u * rng.uniform(0.02, 0.08)
        else:  # a stroke along a line through the pile's neighbourhood
            half = rng.uniform(0.06, 0.14)
            start, end = through - u * half, through + u * half
        return {"stage": "approach", "points": np.clip(start, -WORKSPACE, WORKSPACE),
                "ends": np.clip(end, -WORKSPACE, WORKSPACE)}

    def _move(self, p: np.ndarray, task: dict) -> np.ndarray:
        if task["stage"] == "approach":
            if np.linalg.norm(p - task["points"]) > 0.005:  # free space: travel at up to the speed limit
                return advance(p, task["points"], max(self.speed, 0.8 * MAX_STEP))
            task["stage"] = "stroke"
        return advance(p, task["ends"], self.speed)

    def __call__(self, obs: dict, info: dict) -> np.ndarray:
        pushers = np.asarray(obs["agent_pos"], np.float64).reshape(2, 2)
        if self._left <= 0:
            self._segment(pushers, see_pieces(obs), obs)
        self._left -= 1
        if self.kind == "rest":
            targets = self._rest
        elif self.kind == "expert":
            targets = np.asarray(self.expert(obs, {}), np.float64).reshape(2, 2)
        else:
            targets = np.stack([self._move(p, t) for p, t in zip(pushers, self.tasks)])
        if self.kind != "rest":  # a rest holds still; the hand's pauses do too
            targets = self.hand(targets.reshape(4)).reshape(2, 2)
        self._command = np.clip(targets.reshape(4), -WORKSPACE, WORKSPACE)
        return self._command.astype(np.float32)


def degraded_expert(seed: int, noise: float = 0.0, latency: int = 0, lag: float = 0.0, pause: float = 0.0,
                    jitter: float = 0.0, overshoot: float = 0.0) -> Degraded:
    """The expert of graded skill, for the ranking study: its commands through a hand
    (``lag``, ``pause``, ``jitter``, ``overshoot``), Gaussian ``noise`` (m) and ``latency``
    (steps), as T-push's ``ScriptedConfig`` degrades its expert
    (:class:`~iwsim.envs.tabletop.scripting.Degraded`); the draws come from ``seed``."""
    return Degraded(SweepExpert(), np.random.default_rng([seed, 0]), np.random.default_rng([seed, 1]),
                    noise=noise, latency=latency, lag=lag, pause=pause, jitter=jitter, overshoot=overshoot)


def make_policy(name: str, seed: int) -> ScriptedPolicy:
    """A scripted policy by name (:data:`POLICIES`): ``play`` (randomised by ``seed``),
    ``expert`` (deterministic), ``expert-noisy`` (the expert through a tremor of 0-12 mm
    drawn from ``seed``) or ``expert-lagged`` (that, executed 0-5 steps late)."""
    check_policy(name, POLICIES)
    if name == "expert":
        return SweepExpert()
    if name == "play":
        return PlayPolicy(seed)
    rng = np.random.default_rng(seed)
    jitter = float(rng.uniform(0.0, MAX_NOISE))
    latency = int(rng.integers(0, MAX_LATENCY + 1)) if name == "expert-lagged" else 0
    return degraded_expert(seed, jitter=jitter, latency=latency)


# The policies behind PileSweepTask.pixel_policy (every policy here reads only the observation;
# the studies degrade the expert themselves, as ScriptedConfig does any task's).
PIXEL_POLICIES = ("expert", "play")


def pixel_policy(kind: str, seed: int, rng: np.random.Generator, miss: float = 0.0) -> ScriptedPolicy:
    """The expert or the play policy (randomised by ``seed``) of :data:`PIXEL_POLICIES`;
    nothing is drawn per episode from ``rng``. ``miss`` (T-push's experts aim off the block)
    has no meaning here: pile sweeping's expert aims at whichever piece it sees."""
    del rng
    check_policy(kind, PIXEL_POLICIES)
    if miss:
        raise InputError(f"miss displaces an expert's aim at its one object; pile sweeping has many, got miss={miss}.")
    return SweepExpert() if kind == "expert" else PlayPolicy(seed)


def run_scripted(policy: str | ScriptedPolicy, seed: int, steps: int, image_size: int = IMAGE_SIZE,
                 env: gym.Env | None = None, cameras: tuple[str, ...] = ("top",)) -> Generator[Transition, None, None]:
    """Drive ``iwsim/PileSweep-v0`` (or ``env``) with a scripted policy (a name of
    :data:`POLICIES`, seeded by ``seed``, or a policy object) for ``steps`` steps from the
    reset with ``seed``, yielding each :class:`~iwsim.envs.tabletop.scripting.Transition`. An
    environment made here is closed when the loop ends or is abandoned."""
    pol = make_policy(policy, seed) if isinstance(policy, str) else policy
    return run_policy(pol, "pilesweep" if env is None else env, seed, steps, image_size, cameras)


# The per-step arrays of a recorded episode besides frames, state, action and target.
RECORD_INFO = {"pieces": np.float32, "score": np.float32, "n_in_tray": np.int32, "n_pieces": np.int32,
               "n_contacts": np.int32}


def record_episode(policy: str, seed: int, steps: int, image_size: int = IMAGE_SIZE,
                   cameras: tuple[str, ...] = ("top",)) -> dict[str, np.ndarray]:
    """Run one seeded episode and return its arrays in the episode store's layout
    (:func:`~iwsim.envs.tabletop.scripting.record`): ``img`` (and ``img_<camera>`` for each
    camera after the first), ``state``, ``action``, ``target``, then
    ``pieces`` (T, 30, 2) float32 (NaN past the episode's pieces), ``score`` (T,) float32,
    ``n_in_tray``, ``n_pieces`` and ``n_contacts`` (T,) int32. The same arguments give the
    same arrays."""
    run = (dataclasses.replace(tr, info={**tr.info, "pieces": padded(tr.info["pieces"])})
           for tr in run_scripted(policy, seed, steps, image_size, cameras=cameras))
    return record(run, RECORD_INFO)
