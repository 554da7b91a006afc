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


# The T as two disjoint boxes in the block frame: (centre, half extents) of bar and stem.
BAR_CENTER = (0.0, BAR_WIDTH / 2 - _CENTROID_Y)
STEM_CENTER = (0.0, -STEM_LENGTH / 2 - _CENTROID_Y)
T_BOXES = (
    (np.array(BAR_CENTER), np.array([BAR_LENGTH / 2, BAR_WIDTH / 2])),
    (np.array(STEM_CENTER), np.array([STEM_WIDTH / 2, STEM_LENGTH / 2])),
)
# The same two parts as counter-clockwise (4, 2) corner arrays.
T_PARTS = tuple(c + h * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) for c, h in T_BOXES)
# Distance from the centroid to the farthest corner: bounds the block's footprint.
T_RADIUS = float(max(np.linalg.norm(p, axis=1).max() for p in T_PARTS))


def to_world(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(..., 2) block-frame points -> world frame, for pose (x, y, yaw)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    q = np.asarray(points, dtype=np.float64)
    return np.stack([c * q[..., 0] - s * q[..., 1], s * q[..., 0] + c * q[..., 1]], axis=-1) + pose[:2]


def to_block(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(..., 2) world points -> block frame, for pose (x, y, yaw)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    d = np.asarray(points, dtype=np.float64) - pose[:2]
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], axis=-1)


def t_polygons(pose: np.ndarray) -> list[np.ndarray]:
    """The T's two convex parts, (4, 2) corner arrays each, placed at ``pose``."""
    return [to_world(p, pose) for p in T_PARTS]


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


def t_signed_distance(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(..., 2) world points -> (...) signed distance to the T's outline (< 0 inside)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    dx, dy = points[..., 0] - pose[0], points[..., 1] - pose[1]
    u, v = c * dx + s * dy, c * dy - s * dx  # block frame, per axis (this is a hot loop)
    out = None
    for (cx, cy), (hx, hy) in T_BOXES:
        ex, ey = np.abs(u - cx) - hx, np.abs(v - cy) - hy  # distance outside each slab
        d = np.hypot(np.maximum(ex, 0), np.maximum(ey, 0)) + np.minimum(np.maximum(ex, ey), 0)
        out = d if out is None else np.minimum(out, d)
    assert out is not None  # T_BOXES is not empty
    return out


def point_in_t(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(..., 2) world points -> (...) bool, inside the T (or on its outline) at ``pose``."""
    return t_signed_distance(points, pose) <= 0


def distance_to_t(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(..., 2) world points -> (...) Euclidean distance to the T (0 inside)."""
    return np.maximum(t_signed_distance(points, pose), 0.0)


def wrap_angle(a: np.ndarray | float) -> np.ndarray | float:
    """Wrap angles to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi
