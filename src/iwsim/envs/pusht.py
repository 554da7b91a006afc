"""Bimanual planar T-pushing in MuJoCo: the ground-truth task (``iwsim/BimanualPushT-v0``).

Two cylindrical pushers under position control push a T block that slides and rotates on
a table with friction, towards a goal T drawn on the table. A fixed orthographic camera
looks straight down. Materials are unlit (emissive, under a black headlight, which stops
MuJoCo from adding its default light), so every surface renders in exactly its palette
colour: the pixel scorer stays exact and the frames stay easy to model.
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is imported: headless rendering

from dataclasses import dataclass  # noqa: E402

import gymnasium as gym  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from iwsim.envs import IMAGE_SIZES  # noqa: E402, F401 - the sizes this task renders
from iwsim.envs import geometry as geo  # noqa: E402
from iwsim.errors import InputError

IMAGE_SIZE = 64  # the frames rendered unless told otherwise (the shipped model's); one of IMAGE_SIZES
CONTROL_HZ = 10
TIMESTEP = 0.002  # physics step (s); 50 substeps per control step
SUBSTEPS = round(1 / (CONTROL_HZ * TIMESTEP))

VIEW_HALF = 0.26  # the camera sees [-0.26, 0.26]^2 m
WALL_INNER = 0.24  # walls keep the block on the table
PUSHER_RADIUS = 0.015
WORKSPACE = WALL_INNER - PUSHER_RADIUS - 0.005  # pusher targets are clipped to +-WORKSPACE
# Pusher speed limit: the position setpoint of each pusher moves at most this far per
# control step (0.16 m/s), about 2 px per step at 64 px. A far target is approached over
# several steps, like a robot under a velocity limit, instead of being reached within one
# step with a jump a camera-based model cannot predict.
MAX_STEP = 0.016
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
PALETTE = {
    "table": (0.93, 0.93, 0.90),
    "wall": (0.35, 0.35, 0.38),
    "goal": (0.62, 0.86, 0.62),
    "block": (0.86, 0.38, 0.22),
    "left": (0.18, 0.42, 0.92),
    "right": (0.62, 0.22, 0.78),
}


def _rgba(name: str) -> str:
    return " ".join(f"{c:g}" for c in PALETTE[name]) + " 1"


BLOCK_GEOM = 'material="block" density="600" contype="3" conaffinity="3" friction="0.5 0.005 0.0001"'


def _t_geoms(prefix: str, z: float, half_height: float, extra: str) -> str:
    """Two box geoms (bar, stem) making a T in its body frame."""
    return "\n".join(
        f'<geom name="{prefix}_{name}" type="box" pos="{c[0]:.6f} {c[1]:.6f} {z:g}" '
        f'size="{h[0]:.6f} {h[1]:.6f} {half_height:g}" {extra}/>'
        for name, (c, h) in zip(("bar", "stem"), geo.T_BOXES)
    )


def scene_xml(goal_pose: np.ndarray = GOAL_POSE) -> str:
    """The MJCF scene. Collision bits: table/walls 1, block 1|2, pushers 2, so pushers
    touch the block and each other but glide above the table."""
    gx, gy, gyaw = (float(v) for v in goal_pose)
    h = geo.BLOCK_HEIGHT / 2
    w = WALL_INNER + (VIEW_HALF - WALL_INNER) / 2
    wt = (VIEW_HALF - WALL_INNER) / 2
    walls = "\n".join(
        f'<geom name="wall_{i}" type="box" pos="{x:g} {y:g} {h:g}" size="{sx:g} {sy:g} {h:g}" '
        f'material="wall"/>'
        for i, (x, y, sx, sy) in enumerate(
            [(w, 0, wt, VIEW_HALF), (-w, 0, wt, VIEW_HALF), (0, w, VIEW_HALF, wt), (0, -w, VIEW_HALF, wt)]
        )
    )
    pushers = "\n".join(
        f"""<body name="{side}" pos="0 0 {h:g}">
      <joint name="{side}_x" type="slide" axis="1 0 0" range="{-WORKSPACE:g} {WORKSPACE:g}" damping="1"/>
      <joint name="{side}_y" type="slide" axis="0 1 0" range="{-WORKSPACE:g} {WORKSPACE:g}" damping="1"/>
      <geom name="{side}" type="cylinder" size="{PUSHER_RADIUS:g} {h + 0.005:g}" mass="0.5"
            material="{side}" contype="2" conaffinity="2" friction="1.0 0.005 0.0001"/>
    </body>"""
        for side in ("left", "right")
    )
    actuators = "\n".join(
        f'<position name="{side}_{ax}" joint="{side}_{ax}" kp="400" kv="28" '
        f'ctrlrange="{-WORKSPACE:g} {WORKSPACE:g}" forcerange="-30 30"/>'
        for side in ("left", "right")
        for ax in "xy"
    )
    materials = "\n".join(
        f'<material name="{n}" rgba="{_rgba(n)}" emission="1" specular="0" shininess="0" reflectance="0"/>'
        for n in PALETTE
    )
    return f"""<mujoco model="bimanual_pusht">
  <compiler angle="radian"/>
  <!-- noslip: without it soft contacts creep under load and a pinched block slips. -->
  <option timestep="{TIMESTEP}" gravity="0 0 -9.81" integrator="implicitfast" noslip_iterations="5"/>
  <visual>
    <headlight active="1" ambient="0 0 0" diffuse="0 0 0" specular="0 0 0"/>
    <quality shadowsize="0" offsamples="4"/>
  </visual>
  <asset>{materials}</asset>
  <worldbody>
    <camera name="top" pos="0 0 1" projection="orthographic" fovy="{2 * VIEW_HALF:g}"/>
    <geom name="table" type="plane" size="1 1 0.01" material="table" contype="1" conaffinity="1"
          friction="0.5 0.005 0.0001"/>
    {walls}
    <body name="goal" pos="{gx:g} {gy:g} 0" euler="0 0 {gyaw:.8f}">
      {_t_geoms("goal", 0.0005, 0.0005, 'material="goal" contype="0" conaffinity="0"')}
    </body>
    <body name="block" pos="0 0 {h:g}">
      <joint name="block_x" type="slide" axis="1 0 0" damping="0.1"/>
      <joint name="block_y" type="slide" axis="0 1 0" damping="0.1"/>
      <joint name="block_z" type="slide" axis="0 0 1"/>
      <joint name="block_yaw" type="hinge" axis="0 0 1" damping="0.001"/>
      {_t_geoms("block", 0.0, h, BLOCK_GEOM)}
    </body>
    {pushers}
  </worldbody>
  <actuator>{actuators}</actuator>
</mujoco>"""


@dataclass(frozen=True)
class TaskSpec:
    """What a consumer of this task's data needs to know (stored with episodes)."""

    name: str = "pusht"
    env_id: str = "iwsim/BimanualPushT-v0"
    fps: int = CONTROL_HZ
    action_low: tuple[float, ...] = (-WORKSPACE,) * 4
    action_high: tuple[float, ...] = (WORKSPACE,) * 4
    action_names: tuple[str, ...] = ("left_x", "left_y", "right_x", "right_y")
    goal_pose: tuple[float, ...] = tuple(float(v) for v in GOAL_POSE)
    view_half: float = VIEW_HALF
    max_step: float = MAX_STEP  # pusher speed limit (m per control step), see limit_targets
    # Which action entries are (x, y) positions in the top-down orthographic camera's
    # world frame (metres, x right, y up, image centre at 0): the left and right pushers.
    action_points: tuple[tuple[int, int], ...] = ((0, 1), (2, 3))


def limit_targets(setpoint: np.ndarray, command: np.ndarray, max_step: float = MAX_STEP) -> np.ndarray:
    """The setpoints the pushers' position controllers receive: each pusher's setpoint
    moves from its previous value towards the commanded target (clipped to the
    workspace) by at most ``max_step`` metres (Euclidean, per pusher).

    ``setpoint`` and ``command`` are (..., 4) ``[lx, ly, rx, ry]``; returns (..., 4)
    float64. The one definition of the motion MuJoCo executes: the environment, the
    stage-2 data (``data/target``), ``iwsim/WorldModel-v0`` and ``iwsim play`` all call it.
    """
    s = np.asarray(setpoint, dtype=np.float64)
    c = np.clip(np.asarray(command, dtype=np.float64), -WORKSPACE, WORKSPACE)
    d = (c - s).reshape(*c.shape[:-1], 2, 2)
    n = np.linalg.norm(d, axis=-1, keepdims=True)
    scale = np.minimum(1.0, max_step / np.maximum(n, 1e-12))
    return s + (d * scale).reshape(c.shape)


def check_actions(actions: object, shape: tuple[int, ...]) -> np.ndarray:
    """Commanded targets ``[lx, ly, rx, ry]`` as float64 of ``shape``, or an InputError
    (raised before any state changes); the MuJoCo env and the world-model envs check alike."""
    a = np.asarray(actions, dtype=np.float64)
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise InputError(f"expected finite actions of shape {shape} [lx, ly, rx, ry] in metres, got "
                         f"{a.shape if a.shape != shape else a.tolist()}.")
    return a


def spaces(image_size: int) -> tuple[gym.spaces.Box, gym.spaces.Dict]:
    """The task's action and observation spaces (shared with ``iwsim/WorldModel-v0``)."""
    low = np.full(4, -WORKSPACE, np.float32)
    action = gym.spaces.Box(low, -low, dtype=np.float32)
    obs = gym.spaces.Dict({"pixels": gym.spaces.Box(0, 255, (image_size, image_size, 3), np.uint8),
                           "agent_pos": gym.spaces.Box(low, -low, dtype=np.float32)})
    return action, obs


def check_start(start: str) -> str:
    """``start`` if it names an initial-state distribution (:data:`STARTS`), else a clear error."""
    if start not in STARTS:
        raise InputError(f"start must be one of {', '.join(STARTS)}, got {start!r}.")
    return start


class BimanualPushTEnv(gym.Env):
    """Push the T block onto the goal with two pushers.

    Action: ``[lx, ly, rx, ry]``, absolute pusher targets (m), clipped to the workspace
    and approached at bounded speed (:func:`limit_targets`, ``max_step`` m per step).
    Observation: ``{"pixels": (H, W, 3) uint8, "agent_pos": (4,) float32}``.
    Reward: the geometric IoU of block and goal. ``info``: ``iou``, ``block_pose``,
    ``goal_pose``, ``is_success`` (iou >= 0.9), ``n_contacts`` (pusher-block contacts) and
    ``target`` (the rate-limited setpoints the last step executed; the pushers' positions
    after a reset).
    ``start``: the distribution of :meth:`reset`'s initial states (:data:`STARTS`).
    State for ``reset(options={"reset_to_state": s})``: ``[lx, ly, rx, ry, bx, by, byaw]``.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_HZ}

    def __init__(
        self,
        image_size: int = IMAGE_SIZE,
        render_mode: str | None = "rgb_array",
        terminate_on_success: bool = False,
        max_step: float = MAX_STEP,
        start: str = "random",
    ) -> None:
        if image_size not in IMAGE_SIZES:
            raise InputError(f"image_size must be one of {IMAGE_SIZES}, got {image_size!r}.")
        if render_mode not in (None, "rgb_array"):
            raise InputError(f"render_mode must be 'rgb_array' or None, got {render_mode!r}.")
        self.image_size = image_size
        self.render_mode = render_mode
        self.terminate_on_success = terminate_on_success
        if not max_step > 0:
            raise InputError(f"max_step must be a positive distance in metres, got {max_step!r}.")
        self.max_step = float(max_step)
        self.start = check_start(start)
        self.spec_info = TaskSpec()
        self.goal_pose = GOAL_POSE.copy()

        self.model = mujoco.MjModel.from_xml_string(scene_xml(self.goal_pose))
        self.data = mujoco.MjData(self.model)
        self._renderer: mujoco.Renderer | None = None
        m = self.model
        self._pusher_qpos = np.array([m.joint(f"{s}_{a}").qposadr[0] for s in ("left", "right") for a in "xy"])
        self._pusher_qvel = np.array([m.joint(f"{s}_{a}").dofadr[0] for s in ("left", "right") for a in "xy"])
        self._block_qpos = np.array([m.joint(f"block_{a}").qposadr[0] for a in ("x", "y", "z", "yaw")])
        self._block_geoms = {m.geom("block_bar").id, m.geom("block_stem").id}
        self._pusher_geoms = {m.geom("left").id, m.geom("right").id}
        self._block_z0 = 0.0  # slide joints are offsets from the body position

        self.action_space, self.observation_space = spaces(image_size)

    # --- state -------------------------------------------------------------------------
    @property
    def agent_pos(self) -> np.ndarray:
        return self.data.qpos[self._pusher_qpos].astype(np.float32)

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
        self.data.qpos[self._pusher_qpos] = np.clip(state[:4], -WORKSPACE, WORKSPACE)
        self.data.qpos[self._block_qpos] = [state[4], state[5], self._block_z0, state[6]]
        self.data.ctrl[:] = self.data.qpos[self._pusher_qpos]  # the setpoints start at the pushers
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
        pushers: list[np.ndarray] = []
        while len(pushers) < 2:
            p = rng.uniform(-WORKSPACE, WORKSPACE, 2)
            clear = geo.distance_to_t(p, block) > PUSHER_RADIUS + 0.01
            if clear and all(np.linalg.norm(p - q) > 2 * PUSHER_RADIUS + 0.01 for q in pushers):
                pushers.append(p)
        return np.concatenate([pushers[0], pushers[1], block])

    def _n_contacts(self) -> int:
        n = 0
        for c in self.data.contact[: self.data.ncon]:
            pair = {int(c.geom1), int(c.geom2)}
            n += bool(pair & self._block_geoms) and bool(pair & self._pusher_geoms)
        return n

    def _info(self) -> dict:
        pose = self.block_pose
        iou = geo.t_iou(pose, self.goal_pose)
        return {
            "iou": iou,
            "block_pose": pose,
            "goal_pose": self.goal_pose.copy(),
            "is_success": iou >= SUCCESS_IOU,
            "n_contacts": self._n_contacts(),
            "target": self.data.ctrl.astype(np.float32),
        }

    def _obs(self) -> dict:
        return {"pixels": self._render(), "agent_pos": self.agent_pos}

    def _render(self) -> np.ndarray:
        if self._renderer is None:
            self._renderer = mujoco.Renderer(self.model, self.image_size, self.image_size)
        self._renderer.update_scene(self.data, camera="top")
        return self._renderer.render().copy()

    # --- gymnasium API -------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        options = options or {}
        state = options.get("reset_to_state")
        self._set_state(self.sample_state(self.np_random) if state is None else state)
        return self._obs(), self._info()

    def step(self, action):
        self.data.ctrl[:] = limit_targets(self.data.ctrl, check_actions(action, (4,)), self.max_step)
        mujoco.mj_step(self.model, self.data, nstep=SUBSTEPS)
        info = self._info()
        terminated = bool(self.terminate_on_success and info["is_success"])
        return self._obs(), float(info["iou"]), terminated, False, info

    def render(self):
        return None if self.render_mode is None else self._render()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
