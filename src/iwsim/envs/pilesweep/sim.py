"""Pile sweeping in MuJoCo: the second ground-truth task (``iwsim/PileSweep-v0``).

A pile of 15-30 small pieces lies on the table; the two pushers of the shared tabletop
(:mod:`iwsim.envs.tabletop.scene`: the same camera, action space, speed limit and look as
T-push) sweep them into a tray drawn along the far wall. Score (the paper's): the number
of pieces in the tray, normalised by the number of pieces; ``info`` gives the exact count.

The pieces are pucks, 1.6 cm across, that slide on the table with friction (three slide
joints each, no rotation): they cannot tip or roll, and walls keep them on the table, so
seen from above every piece is a whole disc. Their collision shape is a sphere, whose
contacts are the cheapest MuJoCo has; seen from above it is the same disc a cylinder
would be. The model holds :data:`MAX_PIECES` pieces; those an episode does not use wait
beyond the walls, out of sight and out of reach.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from iwsim.core.errors import InputError
from iwsim.envs.tabletop.scene import MAX_STEP, PUSHER_RADIUS, WALL_INNER, TabletopEnv, TabletopSpec, palette, scene_xml

IMAGE_SIZE = 64  # the frames rendered unless told otherwise; one of iwsim.envs.IMAGE_SIZES
HORIZON = 200  # steps of an episode (the paper's pile-sweeping score counts pieces within 200 steps)
PIECE_RADIUS = 0.008
HEIGHT = 0.03  # of the walls and the pushers (T-push's)
PIECES = (15, 30)  # pieces per episode, drawn uniformly (inclusive)
MAX_PIECES = PIECES[1]
# The tray: a region drawn along the far (top) wall, x0 < x < x1, y0 < y < the wall. A piece
# is in it when its centre is; pieces swept against the wall stay there.
TRAY = (-0.14, 0.14, 0.09, WALL_INNER)
SUCCESS = 0.9  # an episode with at least this share of its pieces in the tray succeeds
# The initial pile: its centre uniform in these x and y ranges, pieces scattered around it
# (Gaussian, std drawn from PILE_SPREAD) without overlapping, inside the walls, below the tray.
PILE_CENTRE = ((-0.1, 0.1), (-0.08, -0.02))
PILE_SPREAD = (0.018, 0.032)
PIECE_MASS = 0.02  # kg: on the table's friction (0.5) a piece let go at the pushers' top speed slides ~3 mm
PARK = (1.0, 1.0)  # where unused pieces wait (beyond the walls, out of sight, each 5 cm further along x)
STATE_SIZE = 4 + 2 * MAX_PIECES  # reset_to_state: [lx, ly, rx, ry, x_1, y_1, ..., x_30, y_30]

# Palette (RGB in [0, 1]): what each surface renders as, exactly (unlit materials). The
# pieces' saturated red is far from every other surface's colour.
PALETTE = palette(tray=(0.62, 0.86, 0.62), piece=(0.85, 0.12, 0.12))
# Collision bits: pieces 1|2|4, so they rest on the table (1) and touch the pushers (2),
# each other and the walls (1|4). A piece moves along x, y and z (gravity holds it on the
# table): with no vertical motion, every contact's friction along the vertical is a
# degenerate row, with which MuJoCo's solver launched pieces through walls at metres per
# step. Under pushers driven hard through piles, into walls and corners, pieces now stay on
# the table and out of the walls (bench/bench_pilesweep.py, recorded in
# bench/results/pilesweep.md).
PIECE_GEOM = (f'type="sphere" size="{PIECE_RADIUS:g}" mass="{PIECE_MASS:g}" material="piece" contype="7" '
              'conaffinity="7" friction="0.4 0.005 0.0001"')


@dataclass(frozen=True)
class TaskSpec(TabletopSpec):
    """What a consumer of this task's data needs to know (stored with episodes)."""

    name: str = "pilesweep"
    env_id: str = "iwsim/PileSweep-v0"
    tray: tuple[float, ...] = TRAY
    piece_radius: float = PIECE_RADIUS
    pieces: tuple[int, int] = PIECES


def scene_xml_pile() -> str:
    """The MJCF scene: the tabletop with the tray drawn on the table and :data:`MAX_PIECES` pieces."""
    x0, x1, y0, y1 = TRAY
    tray = (f'<geom name="tray" type="box" pos="{(x0 + x1) / 2:g} {(y0 + y1) / 2:g} 0.0005" '
            f'size="{(x1 - x0) / 2:g} {(y1 - y0) / 2:g} 0.0005" material="tray" contype="0" conaffinity="0"/>')
    pieces = "\n".join(
        f"""<body name="piece_{i}" pos="0 0 {PIECE_RADIUS:g}">
      <joint name="piece_{i}_x" type="slide" axis="1 0 0" damping="0.01"/>
      <joint name="piece_{i}_y" type="slide" axis="0 1 0" damping="0.01"/>
      <joint name="piece_{i}_z" type="slide" axis="0 0 1"/>
      <geom name="piece_{i}" {PIECE_GEOM}/>
    </body>"""
        for i in range(MAX_PIECES)
    )
    return scene_xml("pile_sweep", PALETTE, f"{tray}\n    {pieces}", HEIGHT)


def padded(pieces: np.ndarray) -> np.ndarray:
    """Piece positions (n, 2) as (:data:`MAX_PIECES`, 2) float32, NaN past the n-th (a store's
    per-step arrays have one shape)."""
    out = np.full((MAX_PIECES, 2), np.nan, np.float32)
    out[: len(pieces)] = pieces
    return out


def in_tray(xy: np.ndarray) -> np.ndarray:
    """(..., 2) positions -> (...) bool: inside the tray (NaN positions are not)."""
    x0, x1, y0, y1 = TRAY
    x, y = xy[..., 0], xy[..., 1]
    return (x > x0) & (x < x1) & (y > y0) & (y < y1)


def sample_pile(rng: np.random.Generator) -> np.ndarray:
    """A random initial pile: (n, 2) piece positions, n uniform in :data:`PIECES`."""
    n = int(rng.integers(PIECES[0], PIECES[1] + 1))
    centre = np.array([rng.uniform(*PILE_CENTRE[0]), rng.uniform(*PILE_CENTRE[1])])
    spread = rng.uniform(*PILE_SPREAD)
    limit = WALL_INNER - PIECE_RADIUS - 0.002
    pieces: list[np.ndarray] = []
    while len(pieces) < n:
        p = centre + rng.normal(0.0, spread, 2)
        if (np.all(np.abs(p) < limit) and p[1] < TRAY[2] - 2 * PIECE_RADIUS
                and all(np.linalg.norm(p - q) > 2 * PIECE_RADIUS + 0.001 for q in pieces)):
            pieces.append(p)
    return np.array(pieces)


class PileSweepEnv(TabletopEnv):
    """Sweep the pile of pieces into the tray with two pushers.

    Action: ``[lx, ly, rx, ry]``, absolute pusher targets (m), clipped to the workspace and
    approached at bounded speed (``max_step`` m per step), as in T-push.
    Observation: ``{"pixels": (H, W, 3) uint8, "agent_pos": (4,) float32}``.
    Reward: the share of the pieces in the tray. ``info``: ``score`` (that share),
    ``n_in_tray`` (the exact count), ``n_pieces``, ``pieces`` (``n_pieces``, 2) float32
    positions, ``is_success`` (score >= 0.9),
    ``n_contacts`` (pusher-piece contacts) and ``target`` (the rate-limited setpoints the
    last step executed; the pushers' positions after a reset).
    State for ``reset(options={"reset_to_state": s})``: :data:`STATE_SIZE` floats ``[lx,
    ly, rx, ry, x_1, y_1, ..., x_30, y_30]``, NaN for the pieces an episode does not use.
    """

    def __init__(self, image_size: int = IMAGE_SIZE, render_mode: str | None = "rgb_array",
                 terminate_on_success: bool = False, max_step: float = MAX_STEP,
                 cameras: tuple[str, ...] = ("top",)) -> None:
        self.spec_info = TaskSpec()
        super().__init__(scene_xml_pile(), image_size, render_mode, max_step, terminate_on_success, cameras)
        m = self.model
        self._piece_qpos = np.array([[m.joint(f"piece_{i}_{a}").qposadr[0] for a in "xy"] for i in range(MAX_PIECES)])
        self._piece_geoms = {m.geom(f"piece_{i}").id for i in range(MAX_PIECES)}
        self.n_pieces = 0

    # --- state -------------------------------------------------------------------------
    @property
    def pieces(self) -> np.ndarray:
        """(n_pieces, 2) float64 positions of the pieces in play."""
        return self.data.qpos[self._piece_qpos[: self.n_pieces]]

    def get_state(self) -> np.ndarray:
        """:data:`STATE_SIZE` floats (float64), accepted by ``reset_to_state``."""
        out = np.full(STATE_SIZE, np.nan)
        out[:4] = self.data.qpos[self._pusher_qpos]
        out[4: 4 + 2 * self.n_pieces] = self.pieces.reshape(-1)
        return out

    def _set_state(self, state: np.ndarray) -> None:
        state = np.asarray(state, dtype=np.float64)
        pieces = state[4:].reshape(-1, 2) if state.shape == (STATE_SIZE,) else np.zeros((0, 2))
        used = np.isfinite(pieces).all(axis=1)
        if (state.shape != (STATE_SIZE,) or not np.all(np.isfinite(state[:4])) or not used.any()
                or (np.isfinite(pieces).any(axis=1) != used).any()):
            raise InputError(f"reset_to_state must be {STATE_SIZE} floats [lx, ly, rx, ry, x_1, y_1, ..., x_30, y_30]: "
                             f"finite pushers and at least one piece, NaN pairs for unused pieces; got {state!r}.")
        mujoco.mj_resetData(self.model, self.data)
        self._set_pushers(state[:4])
        self.n_pieces = int(used.sum())
        parked = np.array([[PARK[0] + 0.05 * i, PARK[1]] for i in range(MAX_PIECES - self.n_pieces)])
        self.data.qpos[self._piece_qpos] = np.concatenate([pieces[used], parked.reshape(-1, 2)])
        mujoco.mj_forward(self.model, self.data)

    def sample_state(self, rng: np.random.Generator) -> np.ndarray:
        """A random initial state: a pile (:func:`sample_pile`) and the pushers in the
        workspace clear of every piece and of each other."""
        pile = sample_pile(rng)
        reach = PUSHER_RADIUS + PIECE_RADIUS + 0.01
        pushers = self.sample_pushers(rng, lambda p: bool(np.min(np.linalg.norm(pile - p, axis=1)) > reach))
        out = np.full(STATE_SIZE, np.nan)
        out[:4], out[4: 4 + pile.size] = pushers, pile.reshape(-1)
        return out

    def _info(self) -> dict:
        n_in = int(in_tray(self.pieces).sum())
        score = n_in / self.n_pieces
        return {
            "score": score,
            "n_in_tray": n_in,
            "n_pieces": self.n_pieces,
            "pieces": self.pieces.astype(np.float32),
            "is_success": score >= SUCCESS,
            "n_contacts": self._n_contacts(self._piece_geoms),
            "target": self.data.ctrl.astype(np.float32),
        }
