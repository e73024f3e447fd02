"""Metrics: AUC-Judd against its definition, angular errors, the hit rule."""
import math

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from activeloc_ros import metrics
from activeloc_ros.errors import DataError


def brute_force_judd(sal: np.ndarray, fix: np.ndarray) -> float:
    """The AUC-Judd curve computed directly, one threshold at a time (distinct values)."""
    s = (sal - sal.min()) / (sal.max() - sal.min())
    pos, neg = s[fix], s[~fix]
    xs, ys = [0.0], [0.0]
    for t in sorted(pos, reverse=True):
        ys.append(float(np.mean(pos >= t)))
        xs.append(float(np.mean(neg >= t)))
    xs.append(1.0)
    ys.append(1.0)
    xs, ys = np.asarray(xs, float), np.asarray(ys, float)     # np.trapezoid needs numpy 2
    return float(np.sum(np.diff(xs) * (ys[1:] + ys[:-1]) / 2))


def test_peak_on_fixation_scores_one():
    sal = np.zeros((14, 14))
    sal[3, 9] = 1.0
    fix = np.zeros((14, 14), dtype=bool)
    fix[3, 9] = True
    assert metrics.auc_judd(sal, fix) == pytest.approx(1.0)


def test_smooth_peak_on_fixation_scores_near_one():
    yy, xx = np.mgrid[0:14, 0:14]
    sal = np.exp(-((yy - 5) ** 2 + (xx - 8) ** 2) / 8.0)
    fix = np.zeros((14, 14), dtype=bool)
    fix[5, 8] = fix[6, 8] = True
    assert metrics.auc_judd(sal, fix) > 0.99


@pytest.mark.parametrize('n_fix', [1, 2, 5, 20])
def test_uniform_map_follows_the_tie_rule(n_fix):
    # All cells tie: point i sits at TP = i/F, FP = (N - i)/(N - F); the trapezoid sum is
    # (N - F^2) / (2 F (N - F)), exactly 0.5 for a single fixation.
    n = 196
    fix = np.zeros(n, dtype=bool)
    fix[:n_fix] = True
    fix = fix.reshape(14, 14)
    expected = (n - n_fix ** 2) / (2 * n_fix * (n - n_fix))
    assert metrics.auc_judd(np.full((14, 14), 0.3), fix) == pytest.approx(expected)
    if n_fix == 1:
        assert expected == 0.5


def test_random_tie_breaking_gives_the_chance_levels():
    # With one fixation the curve is (0,0) -> (FP, 1) -> (1,1): AUC = 1 - FP/2, and FP is
    # uniform over the ranks, so chance is 0.75, not 0.5. With many fixations the curve
    # has many points and chance tends to 0.5.
    rng = np.random.default_rng(1)
    one = np.zeros((14, 14), dtype=bool)
    one[7, 3] = True
    scores = [metrics.auc_judd(np.ones((14, 14)), one, jitter=True, rng=rng)
              for _ in range(400)]
    assert np.mean(scores) == pytest.approx(0.75, abs=0.03)
    half = np.zeros(196, dtype=bool)
    half[::2] = True
    scores = [metrics.auc_judd(np.ones((14, 14)), half.reshape(14, 14), jitter=True, rng=rng)
              for _ in range(100)]
    assert np.mean(scores) == pytest.approx(0.5, abs=0.03)


def test_inverse_map_scores_below_half():
    rng = np.random.default_rng(2)
    sal = rng.random((14, 14))
    fix = np.zeros((14, 14), dtype=bool)
    fix.ravel()[np.argsort(sal.ravel())[:4]] = True  # the four lowest cells
    # every threshold lets all negatives through: FP = 1 at TP = 1/F, area 1 / (2F)
    assert metrics.auc_judd(sal, fix) == pytest.approx(1 / 8)
    assert metrics.auc_judd(-sal, fix) == pytest.approx(1.0)


def test_single_fixation_is_one_minus_half_fp():
    sal = np.arange(16, dtype=float).reshape(4, 4)
    fix = np.zeros((4, 4), dtype=bool)
    fix[1, 1] = True  # value 5: the 10 larger cells are false positives
    assert metrics.auc_judd(sal, fix) == pytest.approx(1 - (10 / 15) / 2)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2 ** 31 - 1), shape=st.sampled_from([(3, 4), (5, 5), (14, 14)]),
       n_fix=st.integers(1, 8))
def test_matches_brute_force_roc(seed, shape, n_fix):
    rng = np.random.default_rng(seed)
    sal = rng.random(shape)
    fix = np.zeros(shape, dtype=bool)
    n_fix = min(n_fix, sal.size - 1)
    fix.ravel()[rng.choice(sal.size, n_fix, replace=False)] = True
    assert metrics.auc_judd(sal, fix) == pytest.approx(brute_force_judd(sal, fix))


def test_auc_is_invariant_to_monotone_rescaling():
    rng = np.random.default_rng(3)
    sal = rng.random((14, 14))
    fix = rng.random((14, 14)) > 0.9
    assert metrics.auc_judd(sal, fix) == pytest.approx(metrics.auc_judd(5 * sal + 2, fix))


def test_auc_without_fixations_is_nan_and_bad_maps_raise():
    assert math.isnan(metrics.auc_judd(np.ones((3, 3)), np.zeros((3, 3))))
    with pytest.raises(DataError):
        metrics.auc_judd(np.ones((3, 3)), np.ones((3, 4)))
    with pytest.raises(DataError):
        metrics.auc_judd(np.full((2, 2), np.nan), np.eye(2))
    with pytest.raises(DataError):
        metrics.auc_judd(np.ones((2, 2)), np.ones((2, 2)))


@pytest.mark.parametrize('u, v, expected', [
    ((0, 0, 1), (0, 0, 1), 0.0),
    ((0, 0, 1), (1, 0, 0), 90.0),
    ((0, 0, 1), (0, 0, -2), 180.0),
    ((0, 0, 1), (1, 0, 1), 45.0),
    ((0, 0, 1), (0, math.sqrt(3), 1), 60.0),
    ((1, 1, 0), (1, 0, 0), 45.0),
])
def test_angle_between_known_geometry(u, v, expected):
    assert metrics.angle_between(u, v) == pytest.approx(expected, abs=1e-9)


def test_angle_is_accurate_for_tiny_angles():
    # 1 mm off at 1 km: arccos of the dot product would round this to zero
    assert metrics.angle_between((0, 0, 1), (1e-6, 0, 1)) == pytest.approx(
        math.degrees(1e-6), rel=1e-6)


def test_axis_error_pixel_ray_and_fov():
    fx = metrics.focal_from_fov(640, 90.0)
    assert fx == pytest.approx(320.0)
    ray = metrics.pixel_ray((640, 240), fx=fx, fy=fx, cx=320, cy=240)  # right image edge
    assert metrics.axis_error(ray) == pytest.approx(45.0)
    assert metrics.axis_error(metrics.pixel_ray((320, 240), fx=fx, fy=fx, cx=320, cy=240)
                              ) == pytest.approx(0.0)


def test_closest_angle_and_aae():
    # a screen 2 m ahead, actions 2 m left and 2 m * tan(10 deg) right of the axis
    rays = [(-2.0, 0.0, 2.0), (2.0 * math.tan(math.radians(10)), 0.0, 2.0)]
    assert metrics.closest_angle((0, 0, 1), rays) == pytest.approx(10.0)
    assert metrics.average_angular_error([10.0, 20.0, 0.0]) == pytest.approx(10.0)
    assert math.isnan(metrics.average_angular_error([]))
    with pytest.raises(DataError):
        metrics.closest_angle((0, 0, 1), [])
    with pytest.raises(DataError):
        metrics.angle_between((0, 0, 0), (1, 0, 0))


# 140 x 70 image on a 14 x 14 grid: cells are 10 x 5 pixels
IMAGE = (140, 70)


@pytest.mark.parametrize('point, hit', [
    ((55.0, 30.0), True),    # inside the box
    ((40.0, 30.0), True),    # one cell (10 px) left of the box: on the grown border
    ((39.0, 30.0), False),   # just beyond
    ((75.0, 30.0), True),    # right edge 60 + 5 + 10
    ((76.0, 30.0), False),
    ((55.0, 15.0), True),    # one cell (5 px) above: y 20 - 5
    ((55.0, 14.0), False),
    ((55.0, 45.0), True),    # below: 20 + 20 + 5
    ((55.0, 46.0), False),
])
def test_hit_rule_grows_the_box_by_one_cell(point, hit):
    box = (50.0, 20.0, 15.0, 20.0)
    cw, ch = metrics.cell_size((14, 14), IMAGE)
    assert (cw, ch) == (10.0, 5.0)
    assert metrics.is_hit(point, [box], cell_wh=(cw, ch)) is hit


def test_hit_with_several_actors_and_from_a_map():
    heat = np.zeros((14, 14))
    heat[2, 11] = 1.0  # cell centre (115, 12.5)
    far = (0.0, 50.0, 10.0, 10.0)
    near = (120.0, 20.0, 10.0, 10.0)  # grown: x 110..140, y 15..35 -> misses y 12.5
    assert not metrics.map_hit(heat, [far, near], IMAGE)
    nearer = (120.0, 17.0, 10.0, 10.0)  # grown: y 12..32
    assert metrics.map_hit(heat, [far, nearer], IMAGE)
    assert not metrics.map_hit(heat, [], IMAGE)


def test_grid_geometry_helpers():
    assert metrics.cell_of((0.0, 0.0), (14, 14), IMAGE) == (0, 0)
    assert metrics.cell_of((139.9, 69.9), (14, 14), IMAGE) == (13, 13)
    assert metrics.cell_of((500.0, -3.0), (14, 14), IMAGE) == (0, 13)
    assert metrics.cell_centre((1, 2), (14, 14), IMAGE) == (25.0, 7.5)
    heat = np.ones((14, 14))
    assert metrics.peak_cell(heat) == (0, 0)  # ties: first in row-major order
    fix = metrics.fixation_map([(25.0, 7.5), (26.0, 8.0), (135.0, 65.0)], (14, 14), IMAGE)
    assert fix.sum() == 2 and fix[1, 2] and fix[13, 13]


def test_chance_hit_rate_counts_cells():
    # a box covering exactly the 2x2 cells (0..1, 0..1); grown, it holds cell centres of
    # rows/cols 0..2 -> 9 of 196 cells
    rate = metrics.chance_hit_rate([(0.0, 0.0, 20.0, 10.0)], (14, 14), IMAGE)
    assert rate == pytest.approx(9 / 196)


def test_centre_gaussian_is_centred_and_normalised():
    g = metrics.centre_gaussian((14, 14))
    assert g.sum() == pytest.approx(1.0, abs=1e-6)
    assert set(map(tuple, np.argwhere(g == g.max()))) == {(6, 6), (6, 7), (7, 6), (7, 7)}
    assert g[0, 0] < g[3, 3] < g[6, 6]


def test_summarise_drops_nan():
    s = metrics.summarise([1.0, 3.0, float('nan')])
    assert (s.n, s.mean) == (2, 2.0)
    assert s.std == pytest.approx(math.sqrt(2))
    assert metrics.summarise([]).n == 0


def test_blob_box_is_the_peak_cells_connected_blob():
    heat = np.zeros((14, 14))
    heat[3:6, 4:6] = 1.0           # the blob round the peak
    heat[4, 5] = 2.0
    heat[10, 10] = 1.5             # as strong, but apart
    x, y, w, h = metrics.blob_box(heat, (140, 280), share=0.0)
    assert (x, y, w, h) == (40.0, 60.0, 20.0, 60.0)
    assert metrics.blob_box(np.zeros((14, 14)), (140, 280)) is None


def test_blob_box_of_a_surprise_map_spans_the_person_not_only_its_head():
    """
    A surprise map is a softmax of the error: the head most surprising, the body below
    it less, the floor not at all. The blob reaches down to the feet, where the base reads
    the person's distance; half the peak held the head alone.
    """
    error = np.zeros((14, 14))
    error[3, 6] = 2.0              # head
    error[4:9, 6] = 0.6            # body, down to the feet in row 8
    error[2, 11] = 1.8             # a passer-by's head, apart
    heat = np.exp(error) / np.exp(error).sum()
    assert metrics.blob_box(heat, (140, 140)) == (60.0, 30.0, 10.0, 60.0)
    head_only = heat >= 0.5 * heat.max()
    assert head_only.sum() == 2 and not head_only[4:9].any()
