"""Scripted policies for the T-pushing task: ``play`` (world-model data), ``expert`` and ``expert-wide``.

A policy is called as ``policy(obs, info) -> action`` after ``policy.reset(obs, info)``;
actions are absolute pusher targets ``[lx, ly, rx, ry]``. :func:`run_scripted` drives
MuJoCo with one; :func:`record_episode` records one (what every tabletop task's scripted
policies share: :mod:`iwsim.envs.tabletop.scripting`).

(Not to be confused with :mod:`iwsim.policies`, the learned policies, which are called as
``policy.predict_action(obs)``.)

All are built on one manoeuvre, the *pinch*: the pushers slide into the notches under
the T's bar, one on each side of the stem, squeeze the stem and then carry the block as a
rigid grasp. Paths around the block come from a visibility graph over the corners of the
T grown by the pusher radius, computed in the block's frame. The expert's pinch is precise
(paths 5 mm from the block, a close once both pushers are within 4 mm of their pre-grip
points); ``expert-wide``'s (:func:`wide_pinch`) tolerates centimetre errors, for
demonstrations that imitation can follow: paths 2 cm from the block, a close and
a carry relative to where the pushers are, commands that change smoothly.
"""

from __future__ import annotations

import functools
import heapq
import math
from collections import deque
from collections.abc import Callable, Generator
from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from iwsim.core.errors import InputError
from iwsim.data.views import first_view
from iwsim.envs import POLICIES as TASK_POLICIES
from iwsim.envs.pusht import geometry as geo
from iwsim.envs.pusht.geometry import to_block, to_world
from iwsim.envs.pusht.pixels import estimate_block_pose
from iwsim.envs.pusht.sim import GOAL_POSE, IMAGE_SIZE, MAX_STEP, PUSHER_RADIUS, WORKSPACE
from iwsim.envs.tabletop.scripting import (
    PAUSE_STEPS,  # noqa: F401 - T-push's name for it
    Hand,
    ScriptedPolicy,
    Transition,
    advance,
    check_policy,
    record,
    run_policy,
)

POLICIES = TASK_POLICIES["pusht"]  # T-push's scripted policies, by name

# The pinch, in the block frame: grip level just under the bar, on both sides of the stem.
_BAR_BOTTOM = geo.BAR_CENTER[1] - geo.BAR_WIDTH / 2
GRIP_Y = _BAR_BOTTOM - PUSHER_RADIUS - 0.008
CONTACT_X = geo.STEM_WIDTH / 2 + PUSHER_RADIUS  # pusher centre touching the stem
PRE_GRIP_X = CONTACT_X + 0.02  # where the pushers wait before closing
SQUEEZE = 0.02  # targets this far inside the stem: ~8 N of grip at kp = 400
CLEARANCE = 0.005  # paths keep this much free space around the block
WAYPOINT_MARGIN = 0.007  # graph nodes sit a little further out than paths need


def _boxes(grow: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """The T's two rectangles in the block frame, grown by ``grow``: (lo, hi) corners."""
    return [(c - h - grow, c + h + grow) for c, h in geo.T_BOXES]


@functools.cache
def _obstacles(clearance: float) -> tuple[list[tuple[np.ndarray, np.ndarray]], np.ndarray]:
    """What paths keeping ``clearance`` around the block avoid, in the block frame: the
    T's rectangles grown by the pusher radius and the clearance (boxes no path may cross),
    and the convex corners of the T grown a little further (the graph's nodes; the two
    notch corners are concave, never on a shortest path)."""
    bar, stem = _boxes(PUSHER_RADIUS + clearance + WAYPOINT_MARGIN)
    corners = np.array([
        [bar[0][0], bar[1][1]], [bar[1][0], bar[1][1]],  # bar top
        [bar[0][0], bar[0][1]], [bar[1][0], bar[0][1]],  # bar bottom ends
        [stem[0][0], stem[0][1]], [stem[1][0], stem[0][1]],  # stem bottom
    ])
    return _boxes(PUSHER_RADIUS + clearance), corners


def _segment_hits_box(a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Whether segment a-b passes through the open box (lo, hi) (Liang-Barsky clipping)."""
    t0, t1 = 0.0, 1.0
    d = b - a
    for k in range(2):
        if abs(d[k]) < 1e-12:
            if a[k] <= lo[k] or a[k] >= hi[k]:
                return False
            continue
        ta, tb = (lo[k] - a[k]) / d[k], (hi[k] - a[k]) / d[k]
        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
        if t0 >= t1:
            return False
    return True


def plan_step(p: np.ndarray, target: np.ndarray, pose: np.ndarray, max_step: float,
              clearance: float = CLEARANCE) -> np.ndarray:
    """Next pusher target (world) on a shortest path from ``p`` to ``target`` around the
    block at ``pose`` that keeps ``clearance`` of free space from it, at most ``max_step``
    along the path. Closer than that to the block, it backs straight out first. Where no
    path that wide fits in the workspace (the block near a wall), it keeps :data:`CLEARANCE`."""
    q, goal = to_block(p, pose), to_block(target, pose)
    collide, _ = _obstacles(clearance)
    out = q
    for lo, hi in collide:
        if np.all(q > lo) and np.all(q < hi):  # too close to the block: back straight out
            gaps = np.concatenate([q - lo, hi - q])
            k = int(np.argmin(gaps))
            out = q.copy()
            out[k % 2] = lo[k] - 0.003 if k < 2 else hi[k - 2] + 0.003
            break
    wide = clearance > CLEARANCE
    if out is not q:  # backing out, unless no path this wide leads on from there
        if wide and _shortest_path(out, goal, pose, clearance) is None:
            return plan_step(p, target, pose, max_step)
        return advance(p, to_world(out, pose), max_step)
    path = _shortest_path(q, goal, pose, clearance)
    if path is None and wide:
        return plan_step(p, target, pose, max_step)
    if path is None:  # no path (e.g. walled in): head straight for the target
        return advance(p, target, max_step)
    return _along(p, [to_world(n, pose) for n in path], max_step)


def _shortest_path(q: np.ndarray, goal: np.ndarray, pose: np.ndarray, clearance: float) -> list[np.ndarray] | None:
    """The nodes after ``q`` of a shortest path from ``q`` to ``goal`` (block frame) that
    keeps ``clearance`` around the block at ``pose`` through corners within the workspace,
    or None if there is none."""
    collide, corners = _obstacles(clearance)
    in_ws = np.all(np.abs(to_world(corners, pose)) <= WORKSPACE, axis=1)
    nodes = [q, goal] + [c for c, ok in zip(corners, in_ws) if ok]

    def visible(a: np.ndarray, b: np.ndarray) -> bool:
        return not any(_segment_hits_box(a, b, lo, hi) for lo, hi in collide)

    # Dijkstra from the goal so that each node knows its next hop towards it.
    dist = {1: 0.0}
    nxt: dict[int, int] = {}
    heap = [(0.0, 1)]
    done: set[int] = set()
    while heap:
        d, i = heapq.heappop(heap)
        if i in done:
            continue
        done.add(i)
        if i == 0:
            break
        for j in range(len(nodes)):
            if j in done or j == i or not visible(nodes[i], nodes[j]):
                continue
            nd = d + float(np.linalg.norm(nodes[i] - nodes[j]))
            if nd < dist.get(j, np.inf):
                dist[j], nxt[j] = nd, i
                heapq.heappush(heap, (nd, j))
    if 0 not in nxt:
        return None
    path, i = [], 0
    while i != 1:
        i = nxt[i]
        path.append(nodes[i])
    return path


def _along(p: np.ndarray, path: list[np.ndarray], max_step: float) -> np.ndarray:
    """The point ``max_step`` along the polyline p -> path[0] -> ... (or its end)."""
    left = max_step
    for w in path:
        n = float(np.linalg.norm(w - p))
        if n >= left:
            return p + (w - p) * (left / n)
        left -= n
        p = w
    return p


@dataclass(frozen=True)
class Grasp:
    """Where and how a :class:`Pinch` takes the stem (block frame, metres): the expert's
    precise defaults, or :data:`WIDE_GRASP`."""

    grip_y: float = GRIP_Y  # the grip's height on the stem
    pre_grip_x: float = PRE_GRIP_X  # |x| of the points where the pushers wait before closing
    squeeze: float = SQUEEZE  # the grip's targets lie this far inside the stem
    clearance: float = CLEARANCE  # approach paths keep this much free space around the block
    close_within: float = 0.004  # the close starts once both pushers are this near their pre-grip points
    close_speed: float = math.inf  # the close moves its targets inwards at most this far a step
    close_steps: int = 5  # the pinch restarts when it has not closed after this many steps
    touch: float = 0.003  # closed: both pushers within the pusher radius and this of the (believed) T
    hold: float = 0.012  # the carry restarts once a pusher is this far from its contact point (see relative)
    # Close and carry relative to the pushers rather than to grip points on the believed
    # block: they close towards each other (for as many steps as the ramp from ``pre_grip_x``
    # would take), the carry moves them with the grasp and squeezes along the line between
    # them, and the grip holds (and has closed, whatever ``touch``) while they are the
    # stem's width apart, give or take ``hold`` (let go, they would close on each other).
    # Where along and across the stem they hold it, and how wrong the believed pose is,
    # then does not matter.
    relative: bool = False


class Pinch:
    """The pinch-and-carry manoeuvre towards a target block pose.

    ``__call__(pushers, block_pose, target_pose)`` returns the two pusher targets (2, 2).
    Phases: approach (each pusher to its pre-grip point, on paths around the block, its
    target ``speed`` ahead along the path), close (squeeze the stem), carry (move the
    grasp; translation and rotation rate-limited). Losing the grip restarts it. Where it
    grips and how it closes: ``grasp``. Each pusher's target moves at most ``max_jump``
    from its previous one a step (from the pusher at the first).
    """

    def __init__(self, speed: float = MAX_STEP, carry_speed: float = 0.012, turn_speed: float = 0.3,
                 gain: float = 2.0, grasp: Grasp = Grasp(), max_jump: float = math.inf) -> None:
        self.speed, self.carry_speed, self.turn_speed, self.gain = speed, carry_speed, turn_speed, gain
        self.grasp, self.max_jump = grasp, max_jump
        self.reset()

    def reset(self) -> None:
        """Start afresh (a new episode)."""
        self.sides: np.ndarray | None = None  # +-1 per pusher: which side of the stem
        self._sent: np.ndarray | None = None  # the last targets returned
        self._begin()

    def _begin(self) -> None:
        """(Re)start from the approach; a restart keeps ``_sent``, so the targets stay smooth."""
        self.phase = "approach"
        self.closing_steps = 0
        self.stalled_steps = 0
        self._prev: np.ndarray | None = None

    def _assign(self, pushers: np.ndarray, pose: np.ndarray) -> np.ndarray:
        g = self.grasp
        grips = to_world(np.array([[-g.pre_grip_x, g.grip_y], [g.pre_grip_x, g.grip_y]]), pose)
        straight = np.linalg.norm(pushers - grips, axis=1).sum()
        crossed = np.linalg.norm(pushers - grips[::-1], axis=1).sum()
        return np.array([-1.0, 1.0]) if straight <= crossed else np.array([1.0, -1.0])

    def _restart(self, pushers: np.ndarray, pose: np.ndarray) -> None:
        self._begin()
        self.sides = self._assign(pushers, pose)

    def _points(self, x: float) -> np.ndarray:
        assert self.sides is not None  # __call__ assigns the sides first
        return np.stack([self.sides * x, np.full(2, self.grasp.grip_y)], axis=1)

    def _closing(self, pushers: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """The close's targets (world, (2, 2)) at its step ``closing_steps + 1``: from the
        pre-grip points inwards at ``close_speed`` a step until ``squeeze`` inside the stem
        (relative: each pusher ``close_speed`` towards the other)."""
        g = self.grasp
        if g.relative:
            return pushers + g.close_speed * _towards_each_other(pushers)
        return to_world(self._points(max(g.pre_grip_x - (self.closing_steps + 1) * g.close_speed,
                                         CONTACT_X - g.squeeze)), pose)

    def _touching(self, pushers: np.ndarray, pose: np.ndarray) -> bool:
        """Whether the close has brought both pushers onto the block at ``pose``."""
        if self.grasp.relative:
            return self._holding(pushers, pose)
        dist = np.array([geo.distance_to_t(p, pose) for p in pushers])
        return bool(np.all(dist <= PUSHER_RADIUS + self.grasp.touch))

    def _holding(self, pushers: np.ndarray, pose: np.ndarray) -> bool:
        """Whether the pushers still hold the block at ``pose`` (see :class:`Grasp`)."""
        g = self.grasp
        if g.relative:
            return bool(abs(np.linalg.norm(pushers[1] - pushers[0]) - 2 * CONTACT_X) <= g.hold)
        contacts = to_world(self._points(CONTACT_X), pose)
        return bool(np.max(np.linalg.norm(pushers - contacts, axis=1)) <= g.hold)

    def _carrying(self, pushers: np.ndarray, pose: np.ndarray, commanded: np.ndarray) -> np.ndarray:
        """The carry's targets (world, (2, 2)) moving the grasp of the block at ``pose`` to ``commanded``."""
        g = self.grasp
        if not g.relative:
            return to_world(self._points(CONTACT_X - g.squeeze), commanded)
        c, s = np.cos(commanded[2] - pose[2]), np.sin(commanded[2] - pose[2])
        squeezed = pushers - pose[:2] + g.squeeze * _towards_each_other(pushers)
        return squeezed @ np.array([[c, s], [-s, c]]) + commanded[:2]

    def carry_step(self, pose: np.ndarray, target: np.ndarray) -> np.ndarray:
        """How far the carry commands the grasp past ``pose`` (x, y, angle) towards ``target``."""
        err = np.array([*(target[:2] - pose[:2]), geo.wrap_angle(target[2] - pose[2])])
        # Command past the target (gain > 1): the grasp lags the command by what friction
        # costs, so a plain proportional command would stall short of it.
        step = self.gain * err
        n = np.linalg.norm(step[:2])
        if n > self.carry_speed:
            step[:2] *= self.carry_speed / n
        step[2] = np.clip(step[2], -self.turn_speed, self.turn_speed)
        return step

    def __call__(self, pushers: np.ndarray, pose: np.ndarray, target: np.ndarray) -> np.ndarray:
        targets = self._targets(pushers, pose, target)
        if self.max_jump < math.inf:
            start = pushers if self._sent is None else self._sent
            targets = np.stack([advance(a, b, self.max_jump) for a, b in zip(start, targets)])
            self._sent = targets
        return targets

    def _targets(self, pushers: np.ndarray, pose: np.ndarray, target: np.ndarray) -> np.ndarray:
        g = self.grasp
        if self.sides is None:
            self.sides = self._assign(pushers, pose)
        if self.phase == "carry":
            if self._holding(pushers, pose):
                return self._carrying(pushers, pose, pose + self.carry_step(pose, target))
            self._restart(pushers, pose)
        if self.phase == "close":
            self.closing_steps += 1
            closed = g.pre_grip_x - self.closing_steps * g.close_speed <= CONTACT_X - g.squeeze
            if closed and self._touching(pushers, pose):
                self.phase = "carry"
            elif self.closing_steps > g.close_steps:
                self._restart(pushers, pose)
            return self._closing(pushers, pose)
        pre = to_world(self._points(g.pre_grip_x), pose)
        if np.max(np.linalg.norm(pushers - pre, axis=1)) < g.close_within:
            self.phase, self.closing_steps = "close", 0
            return self._closing(pushers, pose)
        moved = np.inf if self._prev is None else np.max(np.linalg.norm(pushers - self._prev, axis=1))
        self._prev = pushers.copy()
        self.stalled_steps = self.stalled_steps + 1 if moved < 0.001 else 0
        if self.stalled_steps >= 5:  # the pushers block each other's way: swap sides
            self.sides, self.stalled_steps = -self.sides, 0
        return np.stack([plan_step(p, t, pose, self.speed, g.clearance) for p, t in zip(pushers, pre)])


def _towards_each_other(pushers: np.ndarray) -> np.ndarray:
    """(2, 2) unit vectors from each pusher towards the other."""
    d = pushers[::-1] - pushers
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)


# The forgiving grasp of ``expert-wide``: approach paths 2 cm from the block to points
# 3.5 cm from the stem, 3 cm under the bar (a centimetre along the stem either way stays
# on it); the close starts once both pushers are within 2 cm of them, moves them towards
# each other at 12 mm a step, and the carry squeezes them 1 cm into the stem from where
# they are (a light squeeze: a firm one stops the grasp from turning the block).
WIDE_GRASP = Grasp(grip_y=_BAR_BOTTOM - PUSHER_RADIUS - 0.03, pre_grip_x=CONTACT_X + 0.035, squeeze=0.01,
                   clearance=0.02, close_within=0.02, close_speed=0.012, close_steps=12, hold=0.025, relative=True)


def wide_pinch() -> Pinch:
    """The pinch of ``expert-wide``: :data:`WIDE_GRASP`, its approach targets 4 cm ahead
    along the path (the environment moves the setpoint at its speed limit towards them),
    turns of at most 0.2 rad a step, and targets that move at most the speed limit a step."""
    return Pinch(speed=0.04, turn_speed=0.2, grasp=WIDE_GRASP, max_jump=MAX_STEP)


# The T-push experts by name: the pinch each one carries the block with.
EXPERTS: dict[str, Callable[[], Pinch]] = {"expert": Pinch, "expert-wide": wide_pinch}


class ExpertPolicy:
    """Goal-directed pushing: pinch the stem, carry the block onto the goal pose.

    ``pose_source="state"`` reads the block pose from ``info["block_pose"]``;
    ``"pixels"`` estimates it from ``obs["pixels"]`` alone (the teleoperator stand-in).
    ``pinch``: the manoeuvre (default the expert's precise :class:`Pinch`; ``expert-wide``'s
    is :func:`wide_pinch`).
    """

    def __init__(self, pose_source: str = "state", goal_pose: np.ndarray = GOAL_POSE,
                 pinch: Pinch | None = None) -> None:
        if pose_source not in ("state", "pixels"):
            raise InputError(f"pose_source must be 'state' or 'pixels', got {pose_source!r}.")
        self.pose_source = pose_source
        self.goal_pose = np.asarray(goal_pose, dtype=np.float64)
        self.pinch = Pinch() if pinch is None else pinch
        self._last = np.zeros(4, np.float32)

    def reset(self, obs: dict, info: dict) -> None:
        self.pinch.reset()
        self._last = obs["agent_pos"].astype(np.float32)

    def block_pose(self, obs: dict, info: dict) -> np.ndarray | None:
        if self.pose_source == "state":
            return np.asarray(info["block_pose"], dtype=np.float64)
        est = estimate_block_pose(first_view(obs["pixels"]))
        return est.pose if est.found else None

    def __call__(self, obs: dict, info: dict) -> np.ndarray:
        pose = self.block_pose(obs, info)
        if pose is None:  # block not visible: hold still
            return self._last
        pushers = np.asarray(obs["agent_pos"], dtype=np.float64).reshape(2, 2)
        targets = self.pinch(pushers, pose, self.goal_pose)
        self._last = np.clip(targets.reshape(4), -WORKSPACE, WORKSPACE).astype(np.float32)
        return self._last


def _outline() -> tuple[np.ndarray, np.ndarray]:
    """The T's outline in the block frame: counter-clockwise corners and edge lengths."""
    b0, b1 = _BAR_BOTTOM, _BAR_BOTTOM + geo.BAR_WIDTH
    s0, hb, hs = b0 - geo.STEM_LENGTH, geo.BAR_LENGTH / 2, geo.STEM_WIDTH / 2
    corners = np.array([[-hs, s0], [hs, s0], [hs, b0], [hb, b0], [hb, b1], [-hb, b1], [-hb, b0], [-hs, b0]])
    return corners, np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)


_OUTLINE, _EDGE_LENGTHS = _outline()


class PlayPolicy:
    """Smooth random interaction for world-model data, biased towards touching the block.

    The episode is cut into segments of 30-80 steps, each with its own speed for pushing
    (4-14 mm per step; travel in free space goes at 13 mm per step; all within the task's
    speed limit, so commanded and executed motion agree). In
    each segment both pushers pinch and carry the block to a random pose (30%), or each
    pusher on its own either pokes the block (90%: approach a random point of its outline
    from outside, preferring edges near it, then push in by a random depth) or wanders to
    a random target (10%).
    A slowly drifting offset (about 1.5 mm, correlated over ~10 steps) covers nearby
    actions without making the motion jittery.
    """

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        self.pinch = Pinch(turn_speed=0.15)  # gentler turns than the expert's
        self._drift = np.zeros(4)

    def reset(self, obs: dict, info: dict) -> None:
        self._segment_left = 0
        self._drift = np.zeros(4)

    def _new_segment(self, pushers: np.ndarray, pose: np.ndarray) -> None:
        rng = self.rng
        self._segment_left = int(rng.integers(30, 81))
        self.speed = float(rng.uniform(0.004, 0.014))
        self.mode = "pinch" if rng.random() < 0.3 else "solo"
        if self.mode == "pinch":
            self.pinch.reset()
            self.pinch.speed = self.speed
            self.target_pose = np.array([*rng.uniform(-0.1, 0.1, 2), rng.uniform(-np.pi, np.pi)])
            return
        self.tasks = self._solo_tasks(pushers, pose)

    def _solo_tasks(self, pushers: np.ndarray, pose: np.ndarray) -> list[dict]:
        """Each pusher's task of a solo segment: poke the block (90%) or wander (10%)."""
        rng, tasks = self.rng, []
        mids = (_OUTLINE + np.roll(_OUTLINE, -1, axis=0)) / 2
        for p in pushers:
            if rng.random() < 0.9:
                # Edges near the pusher are likelier (less time travelling, more in contact).
                near = np.exp(-np.linalg.norm(mids - to_block(p, pose), axis=1) / 0.03)
                w = _EDGE_LENGTHS * (0.05 + near)
                e = int(rng.choice(len(_OUTLINE), p=w / w.sum()))
                a, b = _OUTLINE[e], _OUTLINE[(e + 1) % len(_OUTLINE)]
                normal = np.array([b[1] - a[1], a[0] - b[0]]) / _EDGE_LENGTHS[e]
                contact = a + rng.uniform(0.1, 0.9) * (b - a)
                tasks.append({
                    "kind": "poke", "stage": "approach",
                    "pre": contact + normal * (PUSHER_RADIUS + 0.015),
                    "through": contact - normal * rng.uniform(0.02, 0.08),
                })
            else:
                tasks.append({"kind": "wander", "target": rng.uniform(-WORKSPACE, WORKSPACE, 2)})
        return tasks

    def _solo(self, p: np.ndarray, pose: np.ndarray, task: dict) -> np.ndarray:
        if task["kind"] == "wander":
            return advance(p, task["target"], self.speed)
        if task["stage"] == "approach":
            pre = to_world(task["pre"], pose)
            if np.linalg.norm(p - pre) > 0.005:  # free space: travel at up to the speed limit
                return plan_step(p, pre, pose, max(self.speed, 0.8 * MAX_STEP))
            task["stage"] = "push"
        return advance(p, to_world(task["through"], pose), self.speed)

    def __call__(self, obs: dict, info: dict) -> np.ndarray:
        pose = np.asarray(info["block_pose"], dtype=np.float64)
        pushers = np.asarray(obs["agent_pos"], dtype=np.float64).reshape(2, 2)
        if self._segment_left <= 0:
            self._new_segment(pushers, pose)
        self._segment_left -= 1
        return self._command(self._targets(pushers, pose))

    def _targets(self, pushers: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """The segment's pusher targets (2, 2) this step."""
        if self.mode == "pinch":
            return self.pinch(pushers, pose, self.target_pose)
        return np.stack([self._solo(p, pose, t) for p, t in zip(pushers, self.tasks)])

    def _command(self, targets: np.ndarray) -> np.ndarray:
        """The command (4,) float32 for ``targets``: with the drift, in the workspace."""
        self._drift = 0.9 * self._drift + self.rng.normal(0.0, 0.0007, 4)
        return np.clip(targets.reshape(4) + self._drift, -WORKSPACE, WORKSPACE).astype(np.float32)


class BroadPlayPolicy(PlayPolicy):
    """Play of the breadth that people and policies show, for world-model data.

    Segments of 30-80 steps, each with its own speed (3-16 mm a step) and its own hand
    (:class:`Hand`: half lag with a time constant of 1.5-5 steps, half start a pause at
    0.5-3% of steps,
    half a tremor of 1-5 mm), of one of four kinds: rest (8%: both pushers hold still for
    5-30 steps), pinch-and-carry (30%: to a random pose, a third of them near the goal;
    a quarter of the pinches let go of the block part-way), sweeps (12%: each pusher
    strokes along a line through the block's neighbourhood), or, as :class:`PlayPolicy`,
    each pusher on its own poking the block or wandering (50%). A hand that overshoots
    and commands that execute late are left out on purpose: the yardstick holds those
    families out of training (:mod:`iwsim.yardstick.families`).
    """

    def reset(self, obs: dict, info: dict) -> None:
        super().reset(obs, info)
        self._last_command = np.asarray(obs["agent_pos"], dtype=np.float64).copy()
        self.hand = Hand(self.rng, self._last_command)

    def _new_segment(self, pushers: np.ndarray, pose: np.ndarray) -> None:
        rng = self.rng
        kind = rng.choice(["rest", "pinch", "sweep", "solo"], p=[0.08, 0.30, 0.12, 0.50])
        self._segment_left = int(rng.integers(30, 81))
        self.speed = float(rng.uniform(0.003, 0.016))
        self.pinch.speed = self.speed
        self.hand = Hand(rng, self._last_command, lag=float(rng.uniform(1.5, 5.0)) if rng.random() < 0.5 else 0.0,
                         pause=float(rng.uniform(0.005, 0.03)) if rng.random() < 0.5 else 0.0,
                         jitter=float(rng.uniform(0.001, 0.005)) if rng.random() < 0.5 else 0.0)
        self._release = None
        if kind == "rest":
            self.mode, self._segment_left, self._rest = "rest", int(rng.integers(5, 31)), pushers.copy()
        elif kind == "pinch":
            self.mode = "pinch"
            self.pinch.reset()
            if rng.random() < 1 / 3:  # near the goal: carries that arrive, overshoot or arrive turned
                self.target_pose = GOAL_POSE + np.array([*rng.normal(0.0, 0.03, 2), rng.normal(0.0, 0.5)])
            else:
                self.target_pose = np.array([*rng.uniform(-0.1, 0.1, 2), rng.uniform(-np.pi, np.pi)])
            if rng.random() < 0.25:
                self._release = int(rng.integers(5, max(6, self._segment_left)))
        elif kind == "sweep":
            self.mode = "solo"
            self.tasks = []
            for _ in pushers:
                through = pose[:2] + rng.normal(0.0, 0.03, 2)
                angle = rng.uniform(-np.pi, np.pi)
                half = rng.uniform(0.06, 0.12) * np.array([np.cos(angle), np.sin(angle)])
                self.tasks.append({"kind": "sweep", "stage": "approach",
                                   "start": np.clip(through - half, -WORKSPACE, WORKSPACE),
                                   "end": np.clip(through + half, -WORKSPACE, WORKSPACE)})
        else:
            self.mode, self.tasks = "solo", self._solo_tasks(pushers, pose)

    def _solo(self, p: np.ndarray, pose: np.ndarray, task: dict) -> np.ndarray:
        if task["kind"] != "sweep":
            return super()._solo(p, pose, task)
        if task["stage"] == "approach":
            if np.linalg.norm(p - task["start"]) > 0.005:
                return plan_step(p, task["start"], pose, max(self.speed, 0.8 * MAX_STEP))
            task["stage"] = "stroke"
        return advance(p, task["end"], self.speed)

    def _targets(self, pushers: np.ndarray, pose: np.ndarray) -> np.ndarray:
        if self.mode == "rest":
            return self._rest
        targets = super()._targets(pushers, pose)
        if self.mode == "pinch" and self._release is not None:
            self._release -= 1
            if self._release < 0:  # let go: open the grip outwards, away from the block
                away = pushers - pose[:2]
                away /= np.maximum(np.linalg.norm(away, axis=1, keepdims=True), 1e-9)
                return pushers + 0.03 * away
        return targets

    def _command(self, targets: np.ndarray) -> np.ndarray:
        targets = targets.reshape(4)
        if self.mode != "rest":  # the drift goes through the hand: a rest or a pause holds still
            self._drift = 0.9 * self._drift + self.rng.normal(0.0, 0.0007, 4)
            targets = targets + self._drift
        self._last_command = np.clip(self.hand(targets), -WORKSPACE, WORKSPACE)
        return self._last_command.astype(np.float32)


class PressingPlayPolicy(BroadPlayPolicy):
    """:class:`BroadPlayPolicy` whose commands run ahead of the pushers, as learned policies'
    do, far beyond what the other collected policies reach (``bench/probes/setpoint_gap.py``
    measures both).
    In 60% of the segments that move, each command lies 10-40 mm (drawn per segment) beyond
    the step it asks for, along its direction: a pusher the block stops presses into it
    with its setpoint well ahead, the contact the world model must learn from."""

    def _new_segment(self, pushers: np.ndarray, pose: np.ndarray) -> None:
        super()._new_segment(pushers, pose)
        self.lead = float(self.rng.uniform(0.01, 0.04)) if self.mode != "rest" and self.rng.random() < 0.6 else 0.0

    def _targets(self, pushers: np.ndarray, pose: np.ndarray) -> np.ndarray:
        targets = super()._targets(pushers, pose)
        if not self.lead:
            return targets
        step = targets - pushers
        norm = np.linalg.norm(step, axis=1, keepdims=True)
        return targets + np.where(norm > 1e-4, self.lead * step / np.maximum(norm, 1e-9), 0.0)


class SeededExpertPolicy(ExpertPolicy):
    """The expert (block pose from state) with a random generator seeded per policy, the
    base of its randomised variants."""

    def __init__(self, seed: int) -> None:
        super().__init__()
        self.rng = np.random.default_rng(seed)


class HandExpertPolicy(SeededExpertPolicy):
    """The noisy expert (:class:`NoisyExpertPolicy`'s smooth command noise of 0-12 mm)
    through a person's hand drawn per episode (:class:`Hand`: half of them slow, time
    constant 1.5-4 steps; half starting a pause at 0.5-3% of steps), for world-model data of goal-directed
    contact as people perform it. No overshoot and no latency (held out, see
    :class:`BroadPlayPolicy`)."""

    def reset(self, obs: dict, info: dict) -> None:
        super().reset(obs, info)
        rng = self.rng
        self.hand = Hand(rng, obs["agent_pos"], lag=float(rng.uniform(1.5, 4.0)) if rng.random() < 0.5 else 0.0,
                         pause=float(rng.uniform(0.005, 0.03)) if rng.random() < 0.5 else 0.0,
                         jitter=float(rng.uniform(0.0, NoisyExpertPolicy.MAX_NOISE)))

    def __call__(self, obs: dict, info: dict) -> np.ndarray:
        return np.clip(self.hand(super().__call__(obs, info)), -WORKSPACE, WORKSPACE).astype(np.float32)


class ImpreciseExpertPolicy(SeededExpertPolicy):
    """The expert with a learned policy's imprecision, for world-model data of contact that
    goes wrong: each episode draws a persistent error in where the policy believes the
    block is (a few mm and degrees, plus a slow wobble), a squeeze of 0.5-8 cm, a carry
    speed of 6-20 mm a step, and, half the time, a blind carry: once it has pinched, it
    carries by dead reckoning (it assumes the block follows its commands and never checks),
    as a policy replaying the expert's motion does. Grips land off the grip points, blocks
    slip, turn or are left behind, and the motions still look like the expert's."""

    POSE_BIAS = (0.008, 0.008, 0.25)  # std of the per-episode belief error: m, m, rad
    # How far past the stem the grip's targets lie (m): up to through the other pusher, so
    # the pushers press the block and stay centimetres from their setpoints, as learned
    # policies' do (bench/probes/setpoint_gap.py measures their gap and the data's)
    SQUEEZE = (0.005, 0.08)
    WOBBLE = (0.003, 0.003, 0.08)  # stationary std of its slow AR(1) drift

    def reset(self, obs: dict, info: dict) -> None:
        super().reset(obs, info)
        rng = self.rng
        self.bias = rng.normal(0.0, self.POSE_BIAS)
        self.wobble = rng.normal(0.0, self.WOBBLE)
        self.pinch = Pinch(carry_speed=float(rng.uniform(0.006, 0.02)),
                           grasp=Grasp(squeeze=float(rng.uniform(*self.SQUEEZE))))
        self.blind = bool(rng.random() < 0.5)
        self.belief: np.ndarray | None = None  # the blind carry's dead-reckoned pose

    def block_pose(self, obs: dict, info: dict) -> np.ndarray:
        if self.blind and self.pinch.phase == "carry" and self.belief is not None:
            return self.belief
        self.wobble = 0.9 * self.wobble + self.rng.normal(0.0, np.asarray(self.WOBBLE) * np.sqrt(1 - 0.81))
        pose = super().block_pose(obs, info)
        assert pose is not None  # a seeded expert reads the pose from the state, never from pixels
        return pose + self.bias + self.wobble

    def __call__(self, obs: dict, info: dict) -> np.ndarray:
        pose = self.block_pose(obs, info)
        pushers = np.asarray(obs["agent_pos"], dtype=np.float64).reshape(2, 2)
        targets = self.pinch(pushers, pose, self.goal_pose)
        # the command leads the grasp by the gain: the block is believed to follow it
        in_carry = self.pinch.phase == "carry"
        self.belief = pose + self.pinch.carry_step(pose, self.goal_pose) / self.pinch.gain if in_carry else None
        self._last = np.clip(targets.reshape(4), -WORKSPACE, WORKSPACE).astype(np.float32)
        return self._last


class NoisyExpertPolicy(SeededExpertPolicy):
    """The expert (block pose from state) with smooth command noise, for world-model data
    around goal-directed contact: each episode draws a noise level of 0-12 mm and adds
    an AR(1) drift of that std (correlated over ~5 steps) to every command. The expert
    corrects its own errors, so episodes stay in the pinch-and-carry regime while covering
    nearby actions."""

    MAX_NOISE = 0.012

    def reset(self, obs: dict, info: dict) -> None:
        super().reset(obs, info)
        self.level = float(self.rng.uniform(0.0, self.MAX_NOISE))
        self._drift = self.rng.normal(0.0, self.level, 4)

    def __call__(self, obs: dict, info: dict) -> np.ndarray:
        targets = super().__call__(obs, info)
        self._drift = 0.8 * self._drift + self.rng.normal(0.0, 0.6 * self.level, 4)  # stationary std: level
        return np.clip(targets + self._drift, -WORKSPACE, WORKSPACE).astype(np.float32)


class LaggedExpertPolicy(NoisyExpertPolicy):
    """The noisy expert whose commands also execute late: each episode draws a latency
    of 0-``MAX_LATENCY`` steps (the pushers hold their first positions until the first
    command arrives), for world-model data holding the overshoots and corrections of a
    slow controller, which a noisy expert that corrects at once never shows."""

    MAX_LATENCY = 5

    def reset(self, obs: dict, info: dict) -> None:
        super().reset(obs, info)
        latency = int(self.rng.integers(0, self.MAX_LATENCY + 1))
        self._queue = deque([obs["agent_pos"].astype(np.float32)] * latency, maxlen=latency + 1)

    def __call__(self, obs: dict, info: dict) -> np.ndarray:
        self._queue.append(super().__call__(obs, info))
        return self._queue.popleft()


def make_policy(name: str, seed: int) -> ExpertPolicy | PlayPolicy:
    """A scripted policy by name: ``play`` (randomised by ``seed``), ``play-broad`` (play
    of a person's and a policy's breadth), ``expert`` (deterministic, block pose from
    state), ``expert-wide`` (the same, with the forgiving :func:`wide_pinch`),
    ``expert-noisy`` (the expert with command noise drawn from ``seed``),
    ``expert-lagged`` (that, executed 0-5 steps late) or ``expert-hands`` (that, through a
    person's slow or pausing hand) or ``expert-imprecise`` (the expert with a learned
    policy's imprecise grip and blind carry) or ``play-press`` (broad play whose setpoints
    run ahead of the pushers, as learned policies' do)."""
    check_policy(name, POLICIES)
    if name in EXPERTS:
        return ExpertPolicy(pinch=EXPERTS[name]())
    if name == "expert-lagged":
        return LaggedExpertPolicy(seed)
    if name == "expert-hands":
        return HandExpertPolicy(seed)
    if name == "expert-imprecise":
        return ImpreciseExpertPolicy(seed)
    if name == "play-broad":
        return BroadPlayPolicy(seed)
    if name == "play-press":
        return PressingPlayPolicy(seed)
    return NoisyExpertPolicy(seed) if name == "expert-noisy" else PlayPolicy(seed)


class _MissingExpert(ExpertPolicy):
    """A pixel expert (its ``pinch``) aiming at a block displaced by ``offset`` (x, y, yaw)
    from where it sees it: the expert's kind of motion, not aimed at where the block is."""

    def __init__(self, pinch: Pinch, offset: np.ndarray) -> None:
        super().__init__(pose_source="pixels", pinch=pinch)
        self.offset = offset

    def block_pose(self, obs: dict, info: dict) -> np.ndarray | None:
        pose = super().block_pose(obs, info)
        return None if pose is None else pose + self.offset


class _PixelPose:
    """A scripted policy that takes its block pose from the frame (for the play policy,
    which otherwise reads ``info["block_pose"]`` from the simulator)."""

    def __init__(self, policy: ScriptedPolicy) -> None:
        self.policy = policy
        self._pose = np.zeros(3)

    def _info(self, obs: dict) -> dict:
        est = estimate_block_pose(first_view(obs["pixels"]))
        if est.found:  # when the block is hidden, keep the last pose seen
            self._pose = est.pose
        return {"block_pose": self._pose}

    def reset(self, obs: dict, info: dict) -> None:
        self.policy.reset(obs, self._info(obs))

    def __call__(self, obs: dict, info: dict) -> np.ndarray:
        return self.policy(obs, self._info(obs))


# The policies that read the block pose from the frame (PushTTask.pixel_policy): the experts and play.
PIXEL_POLICIES = (*EXPERTS, "play")


def pixel_policy(kind: str, seed: int, rng: np.random.Generator, miss: float = 0.0) -> ScriptedPolicy:
    """A policy of :data:`PIXEL_POLICIES` that estimates the block pose from the frame: an
    expert of :data:`EXPERTS` (with ``miss`` > 0 aimed at a block displaced by ``miss`` m in
    a direction, and turned by an angle, drawn from ``rng``) or play (randomised by ``seed``)."""
    check_policy(kind, PIXEL_POLICIES)
    if kind not in EXPERTS:
        if miss:
            raise InputError(f"miss displaces an expert's aim; the {kind!r} policy has none.")
        return _PixelPose(PlayPolicy(seed))
    pinch = EXPERTS[kind]()
    if miss:
        angle = rng.uniform(-np.pi, np.pi)
        return _MissingExpert(pinch, np.array([miss * np.cos(angle), miss * np.sin(angle),
                                               rng.uniform(-np.pi / 2, np.pi / 2)]))
    return ExpertPolicy(pose_source="pixels", pinch=pinch)


def run_scripted(policy: str | ScriptedPolicy, seed: int, steps: int, task: str = "pusht",
                 image_size: int = IMAGE_SIZE, env: gym.Env | None = None,
                 cameras: tuple[str, ...] = ("top",)) -> Generator[Transition, None, None]:
    """Drive ``task`` (or ``env``) with a scripted policy (a name of :data:`POLICIES`,
    seeded by ``seed``, or a policy object) for ``steps`` steps from the reset with
    ``seed``, yielding each :class:`Transition`. An environment made here (its frames from
    ``cameras``) is closed when the loop ends or is abandoned."""
    pol = make_policy(policy, seed) if isinstance(policy, str) else policy
    return run_policy(pol, task if env is None else env, seed, steps, image_size, cameras)


def record_episode(task: str, policy: str, seed: int, steps: int,
                   image_size: int = IMAGE_SIZE, cameras: tuple[str, ...] = ("top",)) -> dict[str, np.ndarray]:
    """Run one seeded episode and return its arrays, in the episode store's layout
    (:func:`~iwsim.envs.tabletop.scripting.record`): ``img`` (and ``img_<camera>`` for each
    camera after the first), ``state``, ``action``, ``target``, then ``block_pose`` (T, 3)
    float32, ``iou`` (T,) float32 and ``n_contacts`` (T,) int32, with T = ``steps``. The
    same arguments give the same arrays.
    """
    return record(run_scripted(policy, seed, steps, task, image_size, cameras=cameras),
                  {"block_pose": np.float32, "iou": np.float32, "n_contacts": np.int32})
