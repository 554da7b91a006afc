"""Planar geometry of the T block: its shape, poses and exact polygon IoU.

A pose is ``(x, y, yaw)`` in metres and radians, in the table plane. The block frame has
its origin at the T's area centroid, so the pose's position is the centroid and a pixel
mask's centre of mass estimates it directly. At yaw 0 the T stands upright: the bar on
top (+y), the stem pointing down (-y).
"""

from __future__ import annotations

import numpy as np

# T dimensions (metres): a 16 x 4 cm bar on a 4 x 12 cm stem, gym-pusht's proportions.
BAR_LENGTH = 0.16
BAR_WIDTH = 0.04
STEM_LENGTH = 0.12
STEM_WIDTH = 0.04
BLOCK_HEIGHT = 0.03

_BAR_AREA = BAR_LENGTH * BAR_WIDTH
_STEM_AREA = STEM_LENGTH * STEM_WIDTH
T_AREA = _BAR_AREA + _STEM_AREA
# With the bar's lower edge at y = 0: bar centre +BAR_WIDTH/2, stem centre -STEM_LENGTH/2.
_CENTROID_Y = (_BAR_AREA * BAR_WIDTH / 2 - _STEM_AREA * STEM_LENGTH / 2) / T_AREA


def _rect(cx: float, cy: float, hx: float, hy: float) -> np.ndarray:
    return np.array([[cx - hx, cy - hy], [cx + hx, cy - hy], [cx + hx, cy + hy], [cx - hx, cy + hy]])


# The T as two disjoint convex parts (counter-clockwise rectangles) in the block frame.
BAR_CENTER = (0.0, BAR_WIDTH / 2 - _CENTROID_Y)
STEM_CENTER = (0.0, -STEM_LENGTH / 2 - _CENTROID_Y)
T_PARTS = (
    _rect(*BAR_CENTER, BAR_LENGTH / 2, BAR_WIDTH / 2),
    _rect(*STEM_CENTER, STEM_WIDTH / 2, STEM_LENGTH / 2),
)
# Distance from the centroid to the farthest corner: bounds the block's footprint.
T_RADIUS = float(max(np.linalg.norm(p, axis=1).max() for p in T_PARTS))


def transform(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """Map (N, 2) block-frame points to the world frame for pose (x, y, yaw)."""
    x, y, yaw = (float(v) for v in pose)
    c, s = np.cos(yaw), np.sin(yaw)
    return points @ np.array([[c, s], [-s, c]]) + np.array([x, y])


def t_polygons(pose: np.ndarray) -> list[np.ndarray]:
    """The T's two convex parts, (4, 2) corner arrays each, placed at ``pose``."""
    return [transform(p, pose) for p in T_PARTS]


def polygon_area(poly: np.ndarray) -> float:
    """Signed area of a simple polygon (shoelace formula); positive if counter-clockwise."""
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def clip_convex(subject: np.ndarray, clip: np.ndarray) -> np.ndarray:
    """Intersection of a convex polygon with a convex counter-clockwise polygon
    (Sutherland-Hodgman clipping). Returns the (M, 2) intersection, M may be 0."""
    out = subject
    n = len(clip)
    for i in range(n):
        if len(out) == 0:
            break
        a, b = clip[i], clip[(i + 1) % n]
        edge = b - a
        # > 0 inside (left of the edge, for a counter-clockwise clip polygon).
        side = edge[0] * (out[:, 1] - a[1]) - edge[1] * (out[:, 0] - a[0])
        kept = []
        m = len(out)
        for j in range(m):
            p, q = out[j], out[(j + 1) % m]
            sp, sq = side[j], side[(j + 1) % m]
            if sp >= 0:
                kept.append(p)
            if (sp >= 0) != (sq >= 0):
                kept.append(p + (q - p) * (sp / (sp - sq)))
        out = np.array(kept).reshape(-1, 2)
    return out


def intersection_area(pose_a: np.ndarray, pose_b: np.ndarray) -> float:
    """Exact area of the intersection of two T blocks (sum over pairs of convex parts)."""
    return sum(
        max(polygon_area(clip_convex(pa, pb)), 0.0)
        for pa in t_polygons(pose_a)
        for pb in t_polygons(pose_b)
    )


def t_iou(pose_a: np.ndarray, pose_b: np.ndarray) -> float:
    """Exact intersection-over-union of two T blocks at the given poses."""
    inter = intersection_area(pose_a, pose_b)
    return inter / (2 * T_AREA - inter)


def point_in_t(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(..., 2) world points -> (...) bool, inside the T at ``pose``."""
    x, y, yaw = (float(v) for v in pose)
    c, s = np.cos(yaw), np.sin(yaw)
    dx, dy = points[..., 0] - x, points[..., 1] - y
    u, v = c * dx + s * dy, -s * dx + c * dy  # block frame
    in_bar = (np.abs(u - BAR_CENTER[0]) <= BAR_LENGTH / 2) & (np.abs(v - BAR_CENTER[1]) <= BAR_WIDTH / 2)
    in_stem = (np.abs(u - STEM_CENTER[0]) <= STEM_WIDTH / 2) & (np.abs(v - STEM_CENTER[1]) <= STEM_LENGTH / 2)
    return in_bar | in_stem


def distance_to_t(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(..., 2) world points -> (...) Euclidean distance to the T (0 inside)."""
    x, y, yaw = (float(v) for v in pose)
    c, s = np.cos(yaw), np.sin(yaw)
    dx, dy = points[..., 0] - x, points[..., 1] - y
    u, v = c * dx + s * dy, -s * dx + c * dy
    dists = []
    for (cx, cy), (hx, hy) in ((BAR_CENTER, (BAR_LENGTH / 2, BAR_WIDTH / 2)),
                               (STEM_CENTER, (STEM_WIDTH / 2, STEM_LENGTH / 2))):
        ex = np.maximum(np.abs(u - cx) - hx, 0.0)
        ey = np.maximum(np.abs(v - cy) - hy, 0.0)
        dists.append(np.hypot(ex, ey))
    return np.minimum(*dists)


def wrap_angle(a: np.ndarray | float) -> np.ndarray | float:
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi
