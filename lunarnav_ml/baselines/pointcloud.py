"""Point-cloud tools for the lidar baseline: checks, ground plane, gravity alignment, normals,
voxel grids. Neighbour search is scipy's cKDTree; linear algebra is numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from lunarnav_ml.errors import InputError


def finite_cloud(name: str, points: object) -> np.ndarray:
    """Check an (N, 3) cloud and drop rows with NaN or inf (lidar no-returns).

    Raises:
        InputError: not convertible to float, or not shaped (N, 3).

    Shape:
        points: (N, 3) -> (M, 3) float64, M <= N.
    """
    try:
        arr = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: cannot convert to a float array ({exc})") from None
    if arr.size == 0:
        return np.zeros((0, 3))
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name}: expected shape (N, 3), got {tuple(arr.shape)}")
    return arr[np.all(np.isfinite(arr), axis=1)]


def fit_plane_ransac(
    points: np.ndarray, *, inlier_tol_m: float = 0.05, iterations: int = 200, seed: int = 0,
    max_tilt_deg: float | None = None,
) -> tuple[np.ndarray, float, np.ndarray]:
    """Dominant plane n . p + c = 0 by RANSAC, refined by least squares on the inliers.

    Args:
        points: cloud, m.
        inlier_tol_m: point-to-plane distance counted as inlier, m.
        iterations: RANSAC hypotheses.
        seed: sampling seed (the same seed gives the same plane).
        max_tilt_deg: hypotheses whose normal leans farther than this from +z are dropped
            (None: any plane); the refined plane keeps the best hypothesis when it would lean
            farther.

    Returns:
        unit normal n with n_z >= 0, offset c (m), inlier mask.

    Raises:
        InputError: fewer than 3 points.

    Shape:
        points: (N, 3) -> n (3,), inliers (N,).
    """
    if len(points) < 3:
        raise InputError(f"points: need at least 3 points for a plane, got {len(points)}")
    rng = np.random.default_rng(seed)
    tri = points[rng.integers(0, len(points), (iterations, 3))]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    norms = np.linalg.norm(normals, axis=1)
    ok = norms > 1e-9
    if not ok.any():
        raise InputError("points: degenerate cloud (collinear), no plane")
    normals = normals[ok] / norms[ok, None]
    offsets = -np.einsum("ij,ij->i", normals, tri[ok, 0])
    min_nz = -1.0 if max_tilt_deg is None else np.cos(np.radians(max_tilt_deg))
    if max_tilt_deg is not None:
        upright = np.abs(normals[:, 2]) >= min_nz
        if not upright.any():
            raise InputError(f"points: no plane within {max_tilt_deg} deg of level")
        normals, offsets = normals[upright], offsets[upright]
    sub = points[rng.integers(0, len(points), min(len(points), 4000))]
    counts = (np.abs(sub @ normals.T + offsets) < inlier_tol_m).sum(axis=0)
    best = int(np.argmax(counts))
    inliers = np.abs(points @ normals[best] + offsets[best]) < inlier_tol_m
    n, c = _lsq_plane(points[inliers]) if inliers.sum() >= 3 else (normals[best], offsets[best])
    if abs(n[2]) < min_nz:
        n, c = normals[best], offsets[best]
    if n[2] < 0:
        n, c = -n, -c
    return n, float(c), np.abs(points @ n + c) < inlier_tol_m


def _lsq_plane(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Total-least-squares plane through points: normal = smallest singular vector."""
    mean = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - mean, full_matrices=False)
    n = vt[-1]
    return n, float(-n @ mean)


@dataclass(frozen=True)
class GroundFrame:
    """Rigid transform from the input frame to a gravity-aligned ground frame.

    In the ground frame the fitted plane is z = 0 and the sensor is at (0, 0, sensor_height).
    p_ground = R (p_in - t).

    Attributes:
        rotation: (3, 3) R.
        translation: (3,) t, m (the sensor's foot on the plane, input frame).
    """

    rotation: np.ndarray
    translation: np.ndarray

    def to_ground(self, p: np.ndarray) -> np.ndarray:
        """(N, 3) input-frame points -> (N, 3) ground-frame points, m."""
        return (np.asarray(p) - self.translation) @ self.rotation.T

    def from_ground(self, p: np.ndarray) -> np.ndarray:
        """(N, 3) ground-frame points -> (N, 3) input-frame points, m."""
        return np.asarray(p) @ self.rotation + self.translation


def ground_frame(normal: np.ndarray, offset: float, sensor: np.ndarray) -> GroundFrame:
    """Frame with z along the plane normal, origin at the sensor's foot on the plane.

    The rotation is the smallest one taking ``normal`` to +z, so the input x axis stays as
    close to forward as the tilt allows.

    Shape:
        normal: (3,), sensor: (3,).
    """
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    z = np.array([0.0, 0.0, 1.0])
    v, cos = np.cross(n, z), float(n @ z)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    rot = np.eye(3) + vx + vx @ vx / (1.0 + cos)  # Rodrigues, valid for cos > -1
    foot = sensor - (sensor @ n + offset) * n
    return GroundFrame(rot, foot)


def voxel_downsample(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Mean point of each occupied voxel.

    Shape:
        points: (N, 3) -> (M, 3), M <= N, in voxel-key order (deterministic).
    """
    if len(points) == 0:
        return points.reshape(0, 3)
    _, inverse, counts = np.unique(_voxel_keys(points, voxel_m), return_inverse=True,
                                   return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse, points)
    return sums / counts[:, None]


def _voxel_keys(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """One int64 key per point naming its voxel (x-major), for fast 1-D ``np.unique``.

    Shape:
        points: (N, 3) -> (N,).
    """
    ijk = np.floor(points / voxel_m).astype(np.int64)
    ijk -= ijk.min(axis=0)
    span = ijk.max(axis=0) + 1
    return (ijk[:, 0] * span[1] + ijk[:, 1]) * span[2] + ijk[:, 2]


def estimate_normals(
    points: np.ndarray, k: int = 12, min_planarity: float = 0.05
) -> tuple[np.ndarray, np.ndarray]:
    """Surface normal of the k-nearest-neighbour patch of every point (PCA), pointing up.

    A patch whose points lie on a line (a single lidar ring at long range) has no defined
    normal: it is marked invalid when its middle eigenvalue is below ``min_planarity`` times the
    largest.

    Returns:
        unit normals (n_z >= 0) and a validity mask.

    Shape:
        points: (N, 3) -> normals (N, 3), valid (N,).
    """
    n = len(points)
    if n < 3:
        return np.zeros((n, 3)), np.zeros(n, bool)
    k = min(k, n)
    _, idx = cKDTree(points).query(points, k=k, workers=1)
    patch = points[idx] - points[idx].mean(axis=1, keepdims=True)
    cov = patch.transpose(0, 2, 1) @ patch / k
    evals, evecs = np.linalg.eigh(cov)  # ascending eigenvalues
    normals = evecs[:, :, 0]
    normals *= np.where(normals[:, 2] < 0, -1.0, 1.0)[:, None]
    valid = evals[:, 1] >= min_planarity * np.maximum(evals[:, 2], 1e-12)
    return normals, valid


@dataclass
class ColumnGrid:
    """2.5D voxelization: the highest return in each vertical column of a square grid.

    Attributes:
        cell_m: column width, m.
        x0, y0: corner of cell (0, 0), m.
        top: (nx, ny) highest z per column, NaN where the column holds no return.
    """

    cell_m: float
    x0: float
    y0: float
    top: np.ndarray

    @classmethod
    def build(cls, points: np.ndarray, cell_m: float, half_size_m: float) -> ColumnGrid:
        """Grid over [-half_size, half_size]^2 around the origin (ground frame)."""
        n = int(np.ceil(2 * half_size_m / cell_m))
        top = np.full((n, n), -np.inf)
        ij = np.floor((points[:, :2] + half_size_m) / cell_m).astype(np.int64)
        inside = np.all((ij >= 0) & (ij < n), axis=1)
        np.maximum.at(top, (ij[inside, 0], ij[inside, 1]), points[inside, 2])
        top[np.isneginf(top)] = np.nan
        return cls(cell_m, -half_size_m, -half_size_m, top)

    def lookup(self, xy: np.ndarray) -> np.ndarray:
        """Column top under each (x, y), NaN when empty or off the grid.

        Shape:
            xy: (..., 2) m -> (...) m.
        """
        i = np.floor((xy[..., 0] - self.x0) / self.cell_m).astype(np.int64)
        j = np.floor((xy[..., 1] - self.y0) / self.cell_m).astype(np.int64)
        n0, n1 = self.top.shape
        inside = (i >= 0) & (i < n0) & (j >= 0) & (j < n1)
        out = np.full(i.shape, np.nan)
        out[inside] = self.top[i[inside], j[inside]]
        return out


@dataclass
class VoxelGrid:
    """Occupied voxels of a cloud with a cKDTree over their centers (nearest occupied voxel).

    Attributes:
        voxel_m: voxel edge, m.
        centers: (M, 3) occupied voxel centers, m.
        tree: cKDTree over ``centers``.
    """

    voxel_m: float
    centers: np.ndarray
    tree: cKDTree

    @classmethod
    def build(cls, points: np.ndarray, voxel_m: float) -> VoxelGrid:
        """Voxelize ``points`` (N, 3) m with edge ``voxel_m``."""
        ijk = np.floor(points / voxel_m).astype(np.int64)
        _, first = np.unique(_voxel_keys(points, voxel_m), return_index=True)
        centers = (ijk[first].reshape(-1, 3) + 0.5) * voxel_m
        return cls(voxel_m, centers, cKDTree(centers if len(centers) else np.zeros((1, 3)) + 1e9))

    def nearest(self, p: np.ndarray, max_dist_m: float) -> np.ndarray:
        """Distance to the nearest occupied voxel center (inf beyond ``max_dist_m``).

        Shape:
            p: (K, 3) m -> (K,) m.
        """
        d, _ = self.tree.query(p, k=1, distance_upper_bound=max_dist_m, workers=1)
        return d
