"""Point-cloud tools: checks, RANSAC plane, gravity frame, normals, voxel grids."""

import numpy as np
import pytest

from lunarnav_ml.baselines import pointcloud as pc
from lunarnav_ml.errors import InputError


def _plane_cloud(n=3000, seed=0, slope=(0.1, -0.05)):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-10, 10, (n, 2))
    z = slope[0] * xy[:, 0] + slope[1] * xy[:, 1] + rng.normal(0, 0.005, n)
    return np.column_stack([xy, z])


def test_finite_cloud_drops_nan_rows_and_checks_shape():
    pts = np.array([[0, 0, 0], [np.nan, 1, 1], [1, 2, 3.0]])
    assert pc.finite_cloud("points", pts).shape == (2, 3)
    assert pc.finite_cloud("points", []).shape == (0, 3)
    with pytest.raises(InputError, match=r"points: expected shape \(N, 3\)"):
        pc.finite_cloud("points", np.zeros((4, 2)))


def test_ransac_plane_with_outliers():
    pts = _plane_cloud()
    outliers = np.random.default_rng(1).uniform(-10, 10, (600, 3))
    n, _c, inl = pc.fit_plane_ransac(np.vstack([pts, outliers]))
    truth = np.array([-0.1, 0.05, 1.0]) / np.linalg.norm([-0.1, 0.05, 1.0])
    assert n @ truth > 0.9999
    assert inl[:3000].mean() > 0.99
    with pytest.raises(InputError):
        pc.fit_plane_ransac(np.zeros((2, 3)))


def test_ransac_plane_tilt_cap_keeps_the_ground_under_a_steep_wall():
    """A 60 deg wall with more points than the rough ground: uncapped RANSAC takes the wall;
    with the cap it takes the ground; no plane within the cap raises."""
    rng = np.random.default_rng(2)
    ground = _plane_cloud(n=1500, slope=(0.0, 0.0))
    ground[:, 2] += rng.normal(0, 0.02, len(ground))
    u, v = rng.uniform(0, 6, 3000), rng.uniform(-5, 5, 3000)
    wall = np.column_stack([12 + u * np.cos(np.radians(60)), v, u * np.sin(np.radians(60))])
    cloud = np.vstack([ground, wall])
    n_free, _, _ = pc.fit_plane_ransac(cloud)
    assert n_free[2] < 0.6
    n, _, inl = pc.fit_plane_ransac(cloud, max_tilt_deg=30.0)
    assert n[2] > 0.999 and inl[:1500].mean() > 0.9
    with pytest.raises(InputError, match="within 30"):
        pc.fit_plane_ransac(wall, max_tilt_deg=30.0)


def test_ground_frame_levels_the_plane_and_round_trips():
    pts = _plane_cloud()
    n, c, _ = pc.fit_plane_ransac(pts)
    sensor = np.array([0.0, 0.0, 1.5])
    frame = pc.ground_frame(n, c, sensor)
    g = frame.to_ground(pts)
    assert np.abs(g[:, 2]).max() < 0.03
    s = frame.to_ground(sensor[None])[0]
    assert s[:2] == pytest.approx([0, 0], abs=1e-9) and s[2] == pytest.approx(1.5 * n[2], abs=1e-3)
    assert frame.from_ground(g) == pytest.approx(pts, abs=1e-9)


def test_normals_known_and_degenerate():
    pts = _plane_cloud(slope=(0.2, 0.0))
    normals, valid = pc.estimate_normals(pts, k=12)
    truth = np.array([-0.2, 0.0, 1.0]) / np.hypot(0.2, 1.0)
    assert valid.mean() > 0.98 and np.median(normals[valid] @ truth) > 0.999
    line = np.column_stack([np.linspace(0, 5, 100), np.zeros(100), np.zeros(100)])
    _, valid_line = pc.estimate_normals(line, k=8)
    assert not valid_line.any()


def test_voxels_and_columns():
    pts = np.array([[0.01, 0.01, 0.0], [0.02, 0.03, 0.05], [1.0, 1.0, 0.5]])
    assert len(pc.voxel_downsample(pts, 0.1)) == 2
    vox = pc.VoxelGrid.build(pts, 0.1)
    d = vox.nearest(np.array([[0.05, 0.05, 0.05], [5.0, 5.0, 5.0]]), 1.0)
    assert d[0] == pytest.approx(0.0) and np.isinf(d[1])
    cols = pc.ColumnGrid.build(pts, 0.2, 2.0)
    top = cols.lookup(np.array([[0.05, 0.05], [1.05, 1.05], [-1.0, -1.0], [9.0, 9.0]]))
    assert top[0] == pytest.approx(0.05) and top[1] == pytest.approx(0.5)
    assert np.isnan(top[2]) and np.isnan(top[3])
