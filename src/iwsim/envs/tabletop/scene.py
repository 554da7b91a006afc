"""The tabletop the pushing tasks share (T-push, :mod:`iwsim.envs.pusht.sim`; pile sweeping,
:mod:`iwsim.envs.pilesweep.sim`): a walled table seen straight down by a fixed orthographic
camera, and two cylindrical pushers (left, right) moving in the plane under speed-limited
position control. So the action space, the teleop bindings and the pushers' look are the
same in every tabletop task.

Materials are unlit (emissive, under a black headlight, which stops MuJoCo from adding its
default light), so every surface renders in exactly its palette colour: pixel scorers stay
exact and the frames stay easy to model.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import gymnasium as gym
import mujoco  # (iwsim.envs has set MUJOCO_GL: headless rendering)
import numpy as np

from iwsim.core.errors import InputError
from iwsim.data import views
from iwsim.envs import IMAGE_SIZES, pixels_space

CONTROL_HZ = 10
TIMESTEP = 0.002  # physics step (s); 50 substeps per control step
SUBSTEPS = round(1 / (CONTROL_HZ * TIMESTEP))

VIEW_HALF = 0.26  # the camera sees [-0.26, 0.26]^2 m
WALL_INNER = 0.24  # walls keep what is pushed on the table
PUSHER_RADIUS = 0.015
WORKSPACE = WALL_INNER - PUSHER_RADIUS - 0.005  # pusher targets are clipped to +-WORKSPACE
# Pusher speed limit: the position setpoint of each pusher moves at most this far per
# control step (0.16 m/s), about 2 px per step at 64 px. A far target is approached over
# several steps, like a robot under a velocity limit, instead of being reached within one
# step with a jump a camera-based model cannot predict.
MAX_STEP = 0.016
ACTION_NAMES = ("left_x", "left_y", "right_x", "right_y")
# Which action entries are (x, y) positions in the top-down orthographic camera's world
# frame (metres, x right, y up, image centre at 0): the left and right pushers.
ACTION_POINTS = ((0, 1), (2, 3))

# The colours (RGB in [0, 1]) every tabletop shares; a task's palette adds its own surfaces.
TABLE, WALL = (0.93, 0.93, 0.90), (0.35, 0.35, 0.38)
LEFT, RIGHT = (0.18, 0.42, 0.92), (0.62, 0.22, 0.78)


def palette(**surfaces: tuple[float, float, float]) -> dict[str, tuple[float, float, float]]:
    """A task's palette: the tabletop's surfaces (table, wall, the pushers) and the task's own."""
    return {"table": TABLE, "wall": WALL, **surfaces, "left": LEFT, "right": RIGHT}


# The cameras. "top": straight down, orthographic, sees [-VIEW_HALF, VIEW_HALF]^2 (the task's
# pixel scorers read it; it is every store's first view). "side": an oblique perspective view
# of the table from the front edge (the -y side), SIDE_ELEVATION above the table plane, aimed at
# the table's centre from SIDE_DISTANCE away, with a vertical field of view of SIDE_FOVY degrees.
CAMERAS = ("top", "side")
SIDE_ELEVATION = np.deg2rad(50.0)
SIDE_DISTANCE = 0.85
SIDE_FOVY = 40.0


def side_camera() -> str:
    """The MJCF of the "side" camera (its image's up is the far side of the table)."""
    c, s = np.cos(SIDE_ELEVATION), np.sin(SIDE_ELEVATION)
    return (f'<camera name="side" pos="0 {-SIDE_DISTANCE * c:.6f} {SIDE_DISTANCE * s:.6f}" '
            f'xyaxes="1 0 0 0 {s:.6f} {c:.6f}" fovy="{SIDE_FOVY:g}"/>')


def side_project(points: np.ndarray, image_size: int) -> np.ndarray:
    """World points (..., 3) (m) -> where the "side" camera sees them: continuous (col, row)
    pixel coordinates (..., 2) of its ``image_size`` square frames (MuJoCo's pinhole model
    of :func:`side_camera`; pixel (i, j) spans [j - 0.5, j + 0.5] x [i - 0.5, i + 0.5])."""
    c, s = np.cos(SIDE_ELEVATION), np.sin(SIDE_ELEVATION)
    eye = np.array([0.0, -SIDE_DISTANCE * c, SIDE_DISTANCE * s])
    right, up, back = np.array([1.0, 0.0, 0.0]), np.array([0.0, s, c]), np.array([0.0, -c, s])
    q = np.asarray(points, dtype=np.float64) - eye
    depth = -(q @ back)  # along the viewing direction
    f = (image_size / 2) / np.tan(np.deg2rad(SIDE_FOVY) / 2)
    u, v = f * (q @ right) / depth, f * (q @ up) / depth
    return np.stack([u + image_size / 2 - 0.5, image_size / 2 - v - 0.5], axis=-1)


def check_cameras(cameras: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    """A tabletop env's ``cameras``: names of :data:`CAMERAS`, "top" first (the view its
    pixel scorer reads and every store's ``data/img``)."""
    if isinstance(cameras, str) or not isinstance(cameras, list | tuple):
        raise InputError(f"cameras must be a tuple of camera names such as ('top', 'side'), got {cameras!r}.")
    names = views.check_cameras(cameras, "cameras")
    unknown = [c for c in names if c not in CAMERAS]
    if unknown:
        raise InputError(f"cameras: {unknown[0]!r} is not a camera of this task; it has {', '.join(CAMERAS)}.")
    if names[0] != "top":
        raise InputError(f"cameras: the first camera must be 'top' (the view the task's scores are read from), "
                         f"got {list(names)}.")
    return names


# Collision bits: the table 1 (what rests on it: T-push's block), the walls 1|4 (all that is
# pushed), the pushers 2; the pushers glide above the table and pass through the walls (their
# targets stay in the workspace).
WALL_COLLISION = 'contype="5" conaffinity="5"'


@dataclass(frozen=True)
class TabletopSpec:
    """What a consumer of a tabletop task's data needs to know (stored with episodes); a
    task's spec adds its own fields."""

    name: str
    env_id: str
    fps: int = CONTROL_HZ
    action_low: tuple[float, ...] = (-WORKSPACE,) * 4
    action_high: tuple[float, ...] = (WORKSPACE,) * 4
    action_names: tuple[str, ...] = ACTION_NAMES
    view_half: float = VIEW_HALF
    max_step: float = MAX_STEP  # pusher speed limit (m per control step), see limit_targets
    action_points: tuple[tuple[int, int], ...] = ACTION_POINTS


def limit_targets(setpoint: np.ndarray, command: np.ndarray, max_step: float = MAX_STEP) -> np.ndarray:
    """The setpoints the pushers' position controllers receive: each pusher's setpoint
    moves from its previous value towards the commanded target (clipped to the
    workspace) by at most ``max_step`` metres (Euclidean, per pusher).

    ``setpoint`` and ``command`` are (..., 4) ``[lx, ly, rx, ry]``; returns (..., 4)
    float64. The one definition of the motion MuJoCo executes: the environments, the
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
    (raised before any state changes); the MuJoCo envs and the world-model envs check alike."""
    a = np.asarray(actions, dtype=np.float64)
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise InputError(f"expected finite actions of shape {shape} [lx, ly, rx, ry] in metres, got "
                         f"{a.shape if a.shape != shape else a.tolist()}.")
    return a


def spaces(image_size: int, cameras: tuple[str, ...] = ("top",)) -> tuple[gym.spaces.Box, gym.spaces.Dict]:
    """A tabletop task's action and observation spaces (shared with ``iwsim/WorldModel-v0``):
    ``pixels`` is one frame with one camera, {camera: frame} with several (gym-aloha's
    convention)."""
    low = np.full(4, -WORKSPACE, np.float32)
    action = gym.spaces.Box(low, -low, dtype=np.float32)
    obs = gym.spaces.Dict({"pixels": pixels_space(image_size, cameras),
                           "agent_pos": gym.spaces.Box(low, -low, dtype=np.float32)})
    return action, obs


def scene_xml(model: str, palette: dict[str, tuple[float, float, float]], bodies: str, height: float,
              option: str = "") -> str:
    """The MJCF scene of a tabletop: the table, its walls and the two pushers (each
    ``height`` high), the task's ``bodies`` between them, materials for every surface of
    ``palette`` (which names table, wall, left and right) and ``option`` (more attributes
    of ``<option>``)."""
    h = height / 2
    w = WALL_INNER + (VIEW_HALF - WALL_INNER) / 2
    wt = (VIEW_HALF - WALL_INNER) / 2
    walls = "\n".join(
        f'<geom name="wall_{i}" type="box" pos="{x:g} {y:g} {h:g}" size="{sx:g} {sy:g} {h:g}" '
        f'material="wall" {WALL_COLLISION}/>'
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
        f'<material name="{n}" rgba="{" ".join(f"{c:g}" for c in rgb)} 1" emission="1" specular="0" shininess="0" '
        f'reflectance="0"/>'
        for n, rgb in palette.items()
    )
    return f"""<mujoco model="{model}">
  <compiler angle="radian"/>
  <option timestep="{TIMESTEP}" gravity="0 0 -9.81" integrator="implicitfast"{option}/>
  <visual>
    <headlight active="1" ambient="0 0 0" diffuse="0 0 0" specular="0 0 0"/>
    <quality shadowsize="0" offsamples="4"/>
  </visual>
  <asset>{materials}</asset>
  <worldbody>
    <camera name="top" pos="0 0 1" projection="orthographic" fovy="{2 * VIEW_HALF:g}"/>
    {side_camera()}
    <geom name="table" type="plane" size="1 1 0.01" material="table" contype="1" conaffinity="1"
          friction="0.5 0.005 0.0001"/>
    {walls}
    {bodies}
    {pushers}
  </worldbody>
  <actuator>{actuators}</actuator>
</mujoco>"""


class TabletopEnv(gym.Env):
    """The shared part of a tabletop task's environment: the MuJoCo model of ``xml``
    (:func:`scene_xml`), the pushers' state and speed-limited control, rendering, spaces.

    Action: ``[lx, ly, rx, ry]``, absolute pusher targets (m), clipped to the workspace and
    approached at bounded speed (:func:`limit_targets`, ``max_step`` m per step).
    Observation: ``{"pixels": (H, W, 3) uint8, "agent_pos": (4,) float32}``; with several
    ``cameras`` (e.g. ``("top", "side")``), ``pixels`` is ``{camera: (H, W, 3) uint8}``.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": CONTROL_HZ}
    reward_key = "score"  # the entry of ``info`` that is the reward

    def __init__(self, xml: str, image_size: int, render_mode: str | None, max_step: float,
                 terminate_on_success: bool, cameras: tuple[str, ...] = ("top",)) -> None:
        if image_size not in IMAGE_SIZES:
            raise InputError(f"image_size must be one of {IMAGE_SIZES}, got {image_size!r}.")
        if render_mode not in (None, "rgb_array"):
            raise InputError(f"render_mode must be 'rgb_array' or None, got {render_mode!r}.")
        if not max_step > 0:
            raise InputError(f"max_step must be a positive distance in metres, got {max_step!r}.")
        self.cameras = check_cameras(cameras)
        self.image_size = image_size
        self.render_mode = render_mode
        self.max_step = float(max_step)
        self.terminate_on_success = terminate_on_success
        self.model = mujoco.MjModel.from_xml_string(xml)
        self.data = mujoco.MjData(self.model)
        self._renderer: mujoco.Renderer | None = None
        m = self.model
        self._pusher_qpos = np.array([m.joint(f"{s}_{a}").qposadr[0] for s in ("left", "right") for a in "xy"])
        self._pusher_qvel = np.array([m.joint(f"{s}_{a}").dofadr[0] for s in ("left", "right") for a in "xy"])
        self._pusher_geoms = {m.geom("left").id, m.geom("right").id}
        self.action_space, self.observation_space = spaces(image_size, self.cameras)

    @property
    def agent_pos(self) -> np.ndarray:
        return self.data.qpos[self._pusher_qpos].astype(np.float32)

    def _set_pushers(self, pushers: np.ndarray) -> None:
        """Put the pushers at ``[lx, ly, rx, ry]`` (in the workspace), their setpoints with
        them (after ``mj_resetData``, before ``mj_forward``)."""
        self.data.qpos[self._pusher_qpos] = np.clip(pushers, -WORKSPACE, WORKSPACE)
        self.data.ctrl[:] = self.data.qpos[self._pusher_qpos]  # the setpoints start at the pushers

    @staticmethod
    def sample_pushers(rng: np.random.Generator, clear: Callable[[np.ndarray], bool]) -> np.ndarray:
        """Two random pusher positions ``[lx, ly, rx, ry]`` in the workspace, each ``clear``
        (of the task's objects) and clear of the other."""
        pushers: list[np.ndarray] = []
        while len(pushers) < 2:
            p = rng.uniform(-WORKSPACE, WORKSPACE, 2)
            if clear(p) and all(np.linalg.norm(p - q) > 2 * PUSHER_RADIUS + 0.01 for q in pushers):
                pushers.append(p)
        return np.concatenate(pushers)

    def _n_contacts(self, geoms: set[int]) -> int:
        """The number of contacts between a pusher and one of ``geoms``."""
        n = 0
        for c in self.data.contact[: self.data.ncon]:
            pair = {int(c.geom1), int(c.geom2)}
            n += bool(pair & geoms) and bool(pair & self._pusher_geoms)
        return n

    def _actuate(self, action: object) -> None:
        """One control step towards the commanded targets ``action`` (checked first)."""
        self.data.ctrl[:] = limit_targets(self.data.ctrl, check_actions(action, (4,)), self.max_step)
        mujoco.mj_step(self.model, self.data, nstep=SUBSTEPS)

    def _render(self, camera: str = "top") -> np.ndarray:
        if self._renderer is None:
            self._renderer = mujoco.Renderer(self.model, self.image_size, self.image_size)
        self._renderer.update_scene(self.data, camera=camera)
        return self._renderer.render().copy()

    def _pixels(self) -> np.ndarray | dict[str, np.ndarray]:
        """The observation's ``pixels``: the top view, or {camera: frame} with several cameras."""
        if len(self.cameras) == 1:
            return self._render()
        return {c: self._render(c) for c in self.cameras}

    def _obs(self) -> dict:
        return {"pixels": self._pixels(), "agent_pos": self.agent_pos}

    # --- what a task defines ---------------------------------------------------------------
    def sample_state(self, rng: np.random.Generator) -> np.ndarray:
        """A random initial state (the task's distribution), as ``reset_to_state`` takes it."""
        raise NotImplementedError

    def get_state(self) -> np.ndarray:
        """The simulator's state (float64), as ``reset_to_state`` takes it."""
        raise NotImplementedError

    def _set_state(self, state: np.ndarray) -> None:
        """Reset the simulation to ``state`` (checked; an InputError for a bad one)."""
        raise NotImplementedError

    def _info(self) -> dict:
        raise NotImplementedError

    # --- gymnasium API -------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        state = (options or {}).get("reset_to_state")
        self._set_state(self.sample_state(self.np_random) if state is None else state)
        return self._obs(), self._info()

    def step(self, action):
        self._actuate(action)
        info = self._info()
        terminated = bool(self.terminate_on_success and info["is_success"])
        return self._obs(), float(info[self.reward_key]), terminated, False, info

    def render(self):
        return None if self.render_mode is None else self._render()

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
