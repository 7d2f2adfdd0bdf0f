"""The stereo detector stage by stage on one analytic crater with a known answer, plus the
inputs that must give no detection (all-invalid, flat) and those that must raise."""

import numpy as np
import pytest

from lunarnav_ml.baselines import stereo as S
from lunarnav_ml.baselines.analytic import AnalyticScene
from lunarnav_ml.errors import InputError
from tests.baselines.conftest import CAMERA, CRATER_D, CRATER_XY, disparity_of

CENTER = np.array(CRATER_XY)


@pytest.fixture(scope="module")
def flat_disparity():
    return disparity_of(AnalyticScene(), seed=6)


def test_plane_fit_is_exact_on_flat_ground():
    clean = disparity_of(AnalyticScene(), noise_px=0.0)
    valid = clean > 1.0
    plane = S.fit_disparity_plane(clean, valid)
    resid = clean - S.plane_disparity(plane, clean.shape)
    assert plane[2] == -1.0 and np.abs(resid[valid]).max() < 1e-3
    # flat ground: disparity depends on the row only, with slope B cos(p) / h
    assert plane[0] == pytest.approx(0.0, abs=1e-6)
    assert plane[1] == pytest.approx(0.3 * np.cos(np.radians(20)) / 1.5, rel=1e-3)


def test_column_runs_known_answer():
    m = np.zeros((6, 2), bool)
    m[1:3, 0] = m[4:6, 0] = m[0:6, 1] = True
    starts, ends, cols = S.column_runs(m)
    assert sorted(zip(cols, starts, ends)) == [(0, 1, 3), (0, 4, 6), (1, 0, 6)]


def test_split_at_crest_cuts_the_gentler_rise_behind_the_crest():
    wall = 0.2 * np.arange(10)  # far wall: 0.2 px per row for 10 rows
    behind = wall[-1] + 0.05 * np.arange(1, 9)  # rising ground behind the crest, 4x gentler
    kinked = np.concatenate([wall, behind])
    straight = 0.2 * np.arange(18)
    bowl = 0.02 * np.arange(18) ** 2  # steepest at the top: a bowl's far wall is kept whole
    drop = S.split_at_crest(np.stack([kinked, straight, bowl]), ratio=0.5)
    assert drop.tolist() == [8, 0, 0]
    assert S.split_at_crest(np.stack([kinked]), ratio=0.0).tolist() == [0]
    assert S.split_at_crest(np.zeros((0, 18)), ratio=0.5).shape == (0,)


def test_far_wall_mask_stops_at_the_crest():
    resid = np.full((40, 1), -2.0)
    rows = np.arange(40)
    # going up from row 35: the far wall rises 0.2 px/row to the crest at row 25, then the
    # ground behind the crater keeps rising at 0.04 px/row up to row 5
    resid[25:36, 0] = -2.0 + 0.2 * (35 - rows[25:36])
    resid[5:25, 0] = resid[25, 0] + 0.04 * (25 - rows[5:25])
    plane_d = np.full_like(resid, 10.0)
    cut = S.far_wall_mask(resid, plane_d, S.StereoConfig())
    whole = S.far_wall_mask(resid, plane_d, S.StereoConfig(crest_slope_ratio=0.0))
    assert whole[8:33, 0].all()
    top = np.nonzero(cut[:, 0])[0].min()
    assert 23 <= top <= 27 and cut[30, 0]


def test_rim_discontinuity_across_an_invalid_gap():
    d = np.tile(np.linspace(5.0, 10.0, 40)[:, None], (1, 3))  # disparity grows down the image
    d[:20] -= 2.0  # a 2 px drop going up at row 20 -> rim pixel is row 20
    d[18:20, 1] = np.nan  # invalid pixels at the discontinuity in column 1
    rims = S.rim_discontinuities(d, S.StereoConfig())
    assert np.nonzero(rims[:, 0])[0].tolist() == [20]
    assert np.nonzero(rims[:, 1])[0].tolist() == [20]


def test_far_wall_regions_pair_with_the_near_rim(crater_disparity):
    cfg = S.StereoConfig()
    valid = crater_disparity > 1
    disp = S.median_filter(crater_disparity, valid, 5)
    plane_d = S.plane_disparity(S.fit_disparity_plane(disp, valid), disp.shape)
    walls = S.far_wall_mask(np.where(valid, disp - plane_d, np.nan), plane_d, cfg, 0.5)
    labels = S.wall_regions(walls, 30)
    rims = S.rim_discontinuities(disp, cfg)
    assert labels.max() >= 1 and rims.any()
    paired = []
    for lab in range(1, labels.max() + 1):  # far wall pairs; the near rim's outer flank does not
        rows, cols = np.nonzero(labels == lab)
        paired.append(np.mean([rims[r + 1 : r + 1 + cfg.pair_rows, c].any()
                               for c in np.unique(cols) for r in [rows[cols == c].max()]]))
    assert max(paired) > 0.9 and min(paired) < 0.5


def test_detects_center_and_diameter(crater_disparity):
    dets = S.detect_craters_stereo(crater_disparity, CAMERA)
    assert 1 <= len(dets) <= 2  # a piece of the far wall may pair on its own
    assert all(np.hypot(*(d.center_m[:2] - CENTER)) < 0.25 * CRATER_D for d in dets)
    det = max(dets, key=lambda d: d.n_near + d.n_far)
    assert np.hypot(*(det.center_m[:2] - CENTER)) < 0.3
    assert det.diameter_m == pytest.approx(CRATER_D, rel=0.05)
    assert det.near_rim_range_m == pytest.approx(np.hypot(*CENTER) - 5.0, abs=0.4)
    assert det.score > 0.8 and det.bbox_px[2] > 0


def test_rim_pixels_lift_with_the_nearest_disparity_in_the_window():
    rig = S.StereoRigParams.from_record(CAMERA)
    disp = np.full((20, 3), 4.0)
    disp[10:] = 8.0  # the crest at row 10; the farther surface above it
    disp[12, 1] = np.nan
    uv = np.array([[0.0, 9.0], [1.0, 12.0], [2.0, 10.0]])  # one row above the crest; invalid; on it
    plain = S.pixels_to_rover(uv, disp, rig)
    windowed = S.pixels_to_rover(uv, disp, rig, window_rows=1)
    on_crest = S.pixels_to_rover(uv[2:], disp, rig)[0]
    assert np.isnan(plain[1]).all() and np.isfinite(windowed[1]).all()
    # a pixel on the crest keeps its own disparity though a nearer one is in the window
    assert np.allclose(S.pixels_to_rover(np.array([[0.0, 11.0]]), disp + np.arange(20)[:, None] * 0.1, rig, 2),
                       S.pixels_to_rover(np.array([[0.0, 11.0]]), disp + np.arange(20)[:, None] * 0.1, rig))
    # the pixel above the crest lifts to the crest's range, not the farther surface's
    assert np.hypot(*windowed[0, :2]) == pytest.approx(np.hypot(*on_crest[:2]), rel=0.02)
    assert np.hypot(*plain[0, :2]) > 1.8 * np.hypot(*on_crest[:2])
    assert np.allclose(windowed[2], on_crest)


def test_circle_fit_known_answer():
    t = np.linspace(0, np.pi, 50)
    xy = np.column_stack([3 + 4 * np.cos(t), -2 + 4 * np.sin(t)])
    center, radius = S.fit_circle(xy)
    assert center == pytest.approx([3, -2], abs=1e-9) and radius == pytest.approx(4.0)
    assert S.fit_circle(np.zeros((2, 2))) is None


def test_flat_and_invalid_maps_give_no_detection(flat_disparity):
    assert S.detect_craters_stereo(flat_disparity, CAMERA) == []
    assert S.detect_craters_stereo(np.full((64, 64), np.nan), CAMERA) == []
    assert S.detect_craters_stereo(np.zeros((64, 64)), CAMERA) == []


def test_bad_input_raises(crater_disparity):
    with pytest.raises(InputError, match="disparity"):
        S.detect_craters_stereo(np.zeros((4, 64, 64)), CAMERA)
    with pytest.raises(InputError, match="camera: missing key"):
        S.detect_craters_stereo(crater_disparity, {"fx": 256.0})
    with pytest.raises(InputError, match="median_px"):
        S.detect_craters_stereo(crater_disparity, CAMERA, config=S.StereoConfig(median_px=7))
