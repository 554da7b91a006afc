import numpy as np
import pytest

from iwsim.envs.pusht import geometry as geo


def test_t_parts_area_and_centroid():
    areas = [geo.polygon_area(p) for p in geo.T_PARTS]
    assert sum(areas) == pytest.approx(geo.T_AREA)
    assert all(a > 0 for a in areas)  # counter-clockwise
    centroid = sum(a * p.mean(axis=0) for a, p in zip(areas, geo.T_PARTS)) / geo.T_AREA
    np.testing.assert_allclose(centroid, 0.0, atol=1e-12)  # the block frame's origin


def test_iou_identity_and_disjoint():
    pose = np.array([0.03, -0.02, 0.7])
    assert geo.t_iou(pose, pose) == pytest.approx(1.0)
    assert geo.t_iou(pose, pose + [0.5, 0, 0]) == 0.0


@pytest.mark.parametrize("d", [0.0, 0.01, 0.025, 0.039])
def test_iou_of_a_sideways_shift_is_exact(d):
    # Shifting an upright T by d < stem width along x: each part overlaps its twin.
    inter = (geo.BAR_LENGTH - d) * geo.BAR_WIDTH + (geo.STEM_WIDTH - d) * geo.STEM_LENGTH
    expected = inter / (2 * geo.T_AREA - inter)
    assert geo.t_iou(np.zeros(3), np.array([d, 0, 0])) == pytest.approx(expected, abs=1e-12)


def test_iou_of_a_half_turn_about_the_bar_centre_is_the_bar():
    # Rotating by pi about the bar's centre maps the bar onto itself; the stems point apart.
    bar_c = np.array(geo.BAR_CENTER)
    flipped = np.array([*(2 * bar_c), np.pi])  # centroid reflected through the bar centre
    inter = geo.BAR_LENGTH * geo.BAR_WIDTH
    assert geo.t_iou(np.zeros(3), flipped) == pytest.approx(inter / (2 * geo.T_AREA - inter), abs=1e-12)


def test_iou_is_symmetric_and_matches_sampling():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.2, 0.2, (200_000, 2))
    for _ in range(3):
        a = np.array([*rng.uniform(-0.03, 0.03, 2), rng.uniform(-np.pi, np.pi)])
        b = np.array([*rng.uniform(-0.03, 0.03, 2), rng.uniform(-np.pi, np.pi)])
        assert geo.t_iou(a, b) == pytest.approx(geo.t_iou(b, a), abs=1e-12)
        ia, ib = geo.point_in_t(pts, a), geo.point_in_t(pts, b)
        assert geo.t_iou(a, b) == pytest.approx((ia & ib).sum() / (ia | ib).sum(), abs=0.01)


def test_distance_to_t():
    pose = np.zeros(3)
    assert geo.distance_to_t(np.array([0.0, 0.0]), pose) == 0.0
    right_of_stem = np.array([geo.STEM_WIDTH / 2 + 0.01, geo.STEM_CENTER[1]])
    assert geo.distance_to_t(right_of_stem, pose) == pytest.approx(0.01)
