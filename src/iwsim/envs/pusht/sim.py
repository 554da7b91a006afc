"""Bimanual planar T-pushing in MuJoCo: the ground-truth task (``iwsim/BimanualPushT-v0``).

Two cylindrical pushers under position control push a T block that slides and rotates on
a table with friction, towards a goal T drawn on the table. The table, its camera, the
pushers and their control are the tabletop every pushing task shares
(:mod:`iwsim.envs.tabletop.scene`).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from iwsim.core.errors import InputError
from iwsim.envs import IMAGE_SIZES  # noqa: F401 - the sizes this task renders
from iwsim.envs.pusht import geometry as geo
from iwsim.envs.tabletop.scene import (  # noqa: F401 - T-push's names for the tabletop's (others import them here)
    MAX_STEP,
    PUSHER_RADIUS,
    VIEW_HALF,
    WORKSPACE,
    TabletopEnv,
    TabletopSpec,
    limit_targets,
    palette,
)
from iwsim.envs.tabletop.scene import scene_xml as tabletop_xml

IMAGE_SIZE = 64  # the frames rendered unless told otherwise (the shipped model's); one of IMAGE_SIZES
BLOCK_INIT_HALF = 0.12  # initial block centroid is uniform in +-this
# Initial-state distributions (``start``): "random", the task's (block anywhere in the central
# region at any angle); "goal-turned", the block on the goal's position (within 1.5 cm) but
# turned 45-135 degrees either way from it, the state where imitation policies that learned
# the carry but not the turn end up (recovery demonstrations start there).
STARTS = ("random", "goal-turned")
TURNED_OFFSET = 0.015, (np.pi / 4, 3 * np.pi / 4)  # position spread (m), |yaw offset| range (rad)
GOAL_POSE = np.array([0.0, 0.0, np.pi / 4])
SUCCESS_IOU = 0.9

# Palette (RGB in [0, 1]): what each surface renders as, exactly (unlit materials).
PALETTE = palette(goal=(0.62, 0.86, 0.62), block=(0.86, 0.38, 0.22))

BLOCK_GEOM = 'material="block" density="600" contype="3" conaffinity="3" friction="0.5 0.005 0.0001"'


def _t_geoms(prefix: str, z: float, half_height: float, extra: str) -> str:
    """Two box geoms (bar, stem) making a T in its body frame."""
    return "\n".join(
        f'<geom name="{prefix}_{name}" type="box" pos="{c[0]:.6f} {c[1]:.6f} {z:g}" '
        f'size="{h[0]:.6f} {h[1]:.6f} {half_height:g}" {extra}/>'
        for name, (c, h) in zip(("bar", "stem"), geo.T_BOXES)
    )


def scene_xml(goal_pose: np.ndarray = GOAL_POSE) -> str:
    """The MJCF scene: the tabletop with the goal T drawn on the table and the T block.
    Collision bits: table 1, walls 1|4, block 1|2, pushers 2, so pushers touch the block and
    each other but glide above the table."""
    gx, gy, gyaw = (float(v) for v in goal_pose)
    h = geo.BLOCK_HEIGHT / 2
    bodies = f"""<body name="goal" pos="{gx:g} {gy:g} 0" euler="0 0 {gyaw:.8f}">
      {_t_geoms("goal", 0.0005, 0.0005, 'material="goal" contype="0" conaffinity="0"')}
    </body>
    <body name="block" pos="0 0 {h:g}">
      <joint name="block_x" type="slide" axis="1 0 0" damping="0.1"/>
      <joint name="block_y" type="slide" axis="0 1 0" damping="0.1"/>
      <joint name="block_z" type="slide" axis="0 0 1"/>
      <joint name="block_yaw" type="hinge" axis="0 0 1" damping="0.001"/>
      {_t_geoms("block", 0.0, h, BLOCK_GEOM)}
    </body>"""
    # noslip: without it soft contacts creep under load and a pinched block slips.
    return tabletop_xml("bimanual_pusht", PALETTE, bodies, geo.BLOCK_HEIGHT, ' noslip_iterations="5"')


@dataclass(frozen=True)
class TaskSpec(TabletopSpec):
    """What a consumer of this task's data needs to know (stored with episodes)."""

    name: str = "pusht"
    env_id: str = "iwsim/BimanualPushT-v0"
    goal_pose: tuple[float, ...] = tuple(float(v) for v in GOAL_POSE)


def check_start(start: str) -> str:
    """``start`` if it names an initial-state distribution (:data:`STARTS`), else a clear error."""
    if start not in STARTS:
        raise InputError(f"start must be one of {', '.join(STARTS)}, got {start!r}.")
    return start


class BimanualPushTEnv(TabletopEnv):
    """Push the T block onto the goal with two pushers.

    Action: ``[lx, ly, rx, ry]``, absolute pusher targets (m), clipped to the workspace
    and approached at bounded speed (:func:`limit_targets`, ``max_step`` m per step).
    Observation: ``{"pixels": (H, W, 3) uint8, "agent_pos": (4,) float32}``; with several
    ``cameras`` (``("top", "side")``), ``pixels`` is ``{camera: (H, W, 3) uint8}``.
    Reward: the geometric IoU of block and goal. ``info``: ``iou``, ``block_pose``,
    ``goal_pose``, ``is_success`` (iou >= 0.9), ``n_contacts`` (pusher-block contacts) and
    ``target`` (the rate-limited setpoints the last step executed; the pushers' positions
    after a reset).
    ``start``: the distribution of :meth:`reset`'s initial states (:data:`STARTS`).
    State for ``reset(options={"reset_to_state": s})``: ``[lx, ly, rx, ry, bx, by, byaw]``.
    """

    reward_key = "iou"

    def __init__(
        self,
        image_size: int = IMAGE_SIZE,
        render_mode: str | None = "rgb_array",
        terminate_on_success: bool = False,
        max_step: float = MAX_STEP,
        start: str = "random",
        cameras: tuple[str, ...] = ("top",),
    ) -> None:
        self.start = check_start(start)
        self.spec_info = TaskSpec()
        self.goal_pose = GOAL_POSE.copy()
        super().__init__(scene_xml(self.goal_pose), image_size, render_mode, max_step, terminate_on_success,
                         cameras)
        m = self.model
        self._block_qpos = np.array([m.joint(f"block_{a}").qposadr[0] for a in ("x", "y", "z", "yaw")])
        self._block_geoms = {m.geom("block_bar").id, m.geom("block_stem").id}
        self._block_z0 = 0.0  # slide joints are offsets from the body position

    # --- state -------------------------------------------------------------------------
    @property
    def block_pose(self) -> np.ndarray:
        x, y, _, yaw = self.data.qpos[self._block_qpos]
        return np.array([x, y, geo.wrap_angle(yaw)])

    def get_state(self) -> np.ndarray:
        """``[lx, ly, rx, ry, bx, by, byaw]`` (float64), accepted by ``reset_to_state``."""
        return np.concatenate([self.data.qpos[self._pusher_qpos], self.block_pose])

    def _set_state(self, state: np.ndarray) -> None:
        state = np.asarray(state, dtype=np.float64)
        if state.shape != (7,) or not np.all(np.isfinite(state)):
            raise InputError(
                f"reset_to_state must be 7 finite floats [lx, ly, rx, ry, bx, by, byaw], got {state!r}."
            )
        mujoco.mj_resetData(self.model, self.data)
        self._set_pushers(state[:4])
        self.data.qpos[self._block_qpos] = [state[4], state[5], self._block_z0, state[6]]
        mujoco.mj_forward(self.model, self.data)

    def sample_state(self, rng: np.random.Generator) -> np.ndarray:
        """A random initial state from :attr:`start`'s distribution (the task's: block
        anywhere in the central region at any angle), the pushers in the workspace clear of
        the block and of each other."""
        if self.start == "random":
            block = np.array([*rng.uniform(-BLOCK_INIT_HALF, BLOCK_INIT_HALF, 2), rng.uniform(-np.pi, np.pi)])
        else:
            spread, (lo, hi) = TURNED_OFFSET
            turn = rng.choice([-1.0, 1.0]) * rng.uniform(lo, hi)
            block = np.array([*(self.goal_pose[:2] + rng.uniform(-spread, spread, 2)),
                              geo.wrap_angle(self.goal_pose[2] + turn)])
        pushers = self.sample_pushers(rng, lambda p: bool(geo.distance_to_t(p, block) > PUSHER_RADIUS + 0.01))
        return np.concatenate([pushers, block])

    def _info(self) -> dict:
        pose = self.block_pose
        iou = geo.t_iou(pose, self.goal_pose)
        return {
            "iou": iou,
            "block_pose": pose,
            "goal_pose": self.goal_pose.copy(),
            "is_success": iou >= SUCCESS_IOU,
            "n_contacts": self._n_contacts(self._block_geoms),
            "target": self.data.ctrl.astype(np.float32),
        }
