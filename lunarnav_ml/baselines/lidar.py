"""The paper's lidar crater detector (LunarNav 2022, "LIDAR-based Approach").

Stage 1  fit the ground plane, rotate the cloud so z is along gravity; estimate a surface normal
         per patch; keep normals facing the sensor; cluster them and size-filter the clusters:
         candidate crater back walls.
Stage 2  from each back-wall centroid, ray-trace the voxelized cloud downward along the line to
         the sensor; the no-data -> data transition is the front rim. The midpoint is a first
         center; normals of the cluster re-filtered toward it give the back rim as the farthest
         point along the viewing direction. Back rim - front rim = diameter, and a new center.
Stage 3  with the orbital-map prior: for each detection, the map craters of similar diameter
         (and near the prior position); a parametric model of each (diameter, depth) sampled in
         points is placed on a 2D grid around the estimate and scored against the voxelized
         cloud with the paper's four rules; the best placement of the best map crater wins.
         The model sits on a plane fitted to the ground around it (the paper names only a 2D
         grid of positions, which we read as level gravity-aligned ground), its sight lines
         meet it at the angle they meet that plane (``plane_sight``), and a placement landing
         over ``max_prior_offset_m`` from its prior is dropped.
         Each map crater is also placed on a grid around its prior center (``prior_search_m``:
         kept when its shadow is emptier than open ground at the same range and its center is
         not inside a larger detected crater), and the better scoring of the two placements is
         kept: an addition to the paper, which starts only from detections.

All stages work in the gravity-aligned ground frame (plane z = 0, sensor at (0, 0, h)); results
are returned in the frame of the input points.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from lunarnav_ml.baselines import pointcloud as pc
from lunarnav_ml.baselines.crater_model import RIM_RATIO, CraterProfile, occluded
from lunarnav_ml.errors import InputError


@dataclass(frozen=True)
class LidarConfig:
    """Settings of :func:`detect_craters_lidar` (defaults: the paper's sensor, 1.5 m high).

    Attributes:
        roi_m: horizontal radius around the sensor that is processed, m.
        plane_tol_m: RANSAC inlier distance of the ground-plane fit, m.
        max_ground_tilt_deg: ground-plane hypotheses leaning farther than this from the input
            frame's z are not tried (None: any). Where the rover stands in a hollow, a steep
            wall near the sensor can hold more returns than any stretch of ground.
        min_ground_fraction: a scan whose ground plane holds fewer of its points (within
            ``plane_tol_m``) is not processed. Rough scans of the development renders hold
            0.14-0.25 of their points within 5 cm of the best plane.
        downsample_m: voxel edge of the downsampling before normals, m.
        normal_k: neighbours per normal patch.
        min_slope_deg: a normal "faces the sensor" when the surface tilts toward it by more.
        cluster_link_m: facing points closer than this join one cluster, m.
        min_cluster_points: smallest back-wall cluster kept (points after downsampling).
        min_cluster_extent_m, max_cluster_extent_m: horizontal size filter of clusters, m.
        column_cell_m: column width of the voxelized cloud ray-traced in Stage 2, m.
        angular_res_deg: lidar angular resolution (sets the ring gap not taken for a shadow).
        backrim_cos: cosine a normal must reach toward the first center to count as back rim.
        min_diameter_m, max_diameter_m: Stage-2 diameter estimates kept, m.
        diameter_tol: map craters within this relative diameter difference are candidates.
        prior_radius_m: map craters whose prior center is farther than this from the estimate
            are not tried, m (None: any distance).
        max_prior_offset_m: a Stage-3 placement whose center lands farther than this from the
            map crater's prior center is dropped, m (None: kept). 4 m is four standard
            deviations of the 1 m rover-position error of the protocol's priors; without it a
            neighbouring crater of similar size 4-6 m away could win the map crater.
        voxel_m: voxel edge of the grid the model is scored against, m.
        search_frac, search_min_m: half-width of the placement grid: max(min, frac D), m.
        rim_tol_m, rim_search_m: rim points with a voxel within tol are fine; none within
            search costs a full point, m (tol 0.1 m, one voxel: chosen on development renders
            over 0.05 and 0.15 m, BENCHMARKS.md issue 6).
        height_tol_m: a voxel this far above a model point is "higher than the point", m.
        min_score: placements scoring below this (mean per model point, 0 = perfect, -1 = every
            point penalized) are rejected.
        prior_search_m: every map crater is also searched for around its prior center, on a
            grid of this half-width (m; 0 disables). Far away a small crater's back wall holds
            too few returns for Stage 1 while its shadow and rim still show in the voxel grid,
            and a neighbouring wall's Stage-2 estimate can claim a map crater and place it
            metres off. A prior-search placement must pass ``min_score`` and the shadow test
            below, and its center must not lie inside a larger detected crater (whose shadow
            would explain its own); it replaces the Stage-3 placement when it scores higher
            (BENCHMARKS.md, issue 6: on development renders it raised Pd for 5-20 m craters
            and narrowed most diameters' 3-sigma error).
        min_shadow_contrast, min_shadow_expected: a prior-search placement is kept when its
            shadow columns are emptier than the same ranges beside the crater
            (:func:`shadow_contrast` at least this) over at least this many occupied twin
            columns. A flat scan scores about -0.16, no worse than a far 5 m crater, but its
            contrast stays below 0.5 (far 5 m craters of the development renders: >= 0.75).
        tilted_ground: the model sits on a plane fitted around it (:func:`local_ground`)
            rather than on a level one. Slopes of a few degrees under a 5 m crater tilt its
            rim by as much as the rim rises; on development renders the tilted ground
            narrowed the 3-sigma error of every diameter (BENCHMARKS.md, issue 6).
        plane_sight: the model's line-of-sight classes (rim seen, shadow) are computed with the
            sensor's height over the crater's local plane where that plane passes under the
            sensor (:func:`sight_height`), so the sight lines meet the model at the angle they
            meet the terrain around the crater; off, the height over the scan's ground plane.
            On terrain that rises away from the sensor more of the bowl is in view than a
            level model predicts, and the placement slid toward the sensor to hide the returns
            from its shadow. On development renders it narrowed the 3-sigma error of 5 m
            craters on six of eight renders and of 7 m craters (BENCHMARKS.md, issue 6).
        model_width: the model's diameter as a fraction of the map diameter (the reported
            diameter stays the map's). The map gives the rim crest's diameter; a degraded
            crater's smoothed bowl is narrower than the sharp model with its crest there, so a
            model sized to the bowl places it better: 0.94 (session 47), chosen on six
            development renders with ``craters.crest_at_rim`` among 0.94, 0.97 and 1.0 (the
            3-sigma of 5 m craters at 15-20 m narrower on all six; BENCHMARKS.md issue 6,
            "Crests on the labelled rim, the default"). 1.0 on the renders before it.
    """

    roi_m: float = 45.0
    plane_tol_m: float = 0.05
    max_ground_tilt_deg: float | None = 30.0
    min_ground_fraction: float = 0.1
    downsample_m: float = 0.15
    normal_k: int = 12
    min_slope_deg: float = 12.0
    cluster_link_m: float = 0.6
    min_cluster_points: int = 15
    min_cluster_extent_m: float = 0.8
    max_cluster_extent_m: float = 30.0
    column_cell_m: float = 0.2
    angular_res_deg: float = 0.333
    backrim_cos: float = 0.5
    min_diameter_m: float = 2.0
    max_diameter_m: float = 40.0
    diameter_tol: float = 0.4
    prior_radius_m: float | None = 8.0
    max_prior_offset_m: float | None = 4.0
    voxel_m: float = 0.1
    search_frac: float = 0.25
    search_min_m: float = 1.5
    rim_tol_m: float = 0.1
    rim_search_m: float = 1.0
    height_tol_m: float = 0.15
    min_score: float = -0.3
    prior_search_m: float = 2.5
    min_shadow_contrast: float = 0.6
    min_shadow_expected: int = 10
    tilted_ground: bool = True
    plane_sight: bool = True
    model_width: float = 0.94

    def __post_init__(self) -> None:
        if not (np.isfinite(self.model_width) and 0.5 <= self.model_width <= 1.5):
            raise InputError(f"model_width: expected a fraction of the map diameter in "
                             f"[0.5, 1.5], got {self.model_width}")


@dataclass(frozen=True)
class MapCrater:
    """A crater of the orbital landmark map, as predicted in the frame of the input points.

    Attributes:
        center_xy: prior rim-circle center (from the map and the approximate rover pose), m.
        diameter_m: map diameter, m.
        depth_m: rim crest to floor, m (the dataset's ``depth_m``).
        rim_height_m: rim crest above the surroundings, m (None: 0.04 D).
    """

    center_xy: tuple[float, float]
    diameter_m: float
    depth_m: float
    rim_height_m: float | None = None


@dataclass
class BackWall:
    """Stage 1 output: one cluster of sensor-facing normals (ground frame).

    Attributes:
        points: (K, 3) m.  normals: (K, 3) unit.  centroid: (3,) m.
    """

    points: np.ndarray
    normals: np.ndarray
    centroid: np.ndarray


@dataclass
class CraterEstimate:
    """Stage 2 output (ground frame).

    Attributes:
        wall: the back-wall cluster.
        front_rim: (3,) m.  back_rim: (3,) m.  center: (3,) m.
        diameter_m: back rim - front rim along the viewing direction, m.
    """

    wall: BackWall
    front_rim: np.ndarray
    back_rim: np.ndarray
    center: np.ndarray
    diameter_m: float


@dataclass
class LidarDetection:
    """A detected crater in the frame of the input points.

    Attributes:
        center_m: (3,) rim-circle center, m.
        diameter_m: the matched map crater's diameter (Stage 3) or the Stage-2 estimate, m.
        score: Stage-3 score (mean per model point, 0 best, -1 worst); NaN without a map.
        map_index: index of the matched map crater, or None without a map.
        stage2_center_m: (3,) Stage-2 center estimate, m (NaN when found by the prior search).
        stage2_diameter_m: Stage-2 diameter estimate, m (NaN likewise).
    """

    center_m: np.ndarray
    diameter_m: float
    score: float
    map_index: int | None
    stage2_center_m: np.ndarray
    stage2_diameter_m: float


@dataclass
class _Scene:
    """The aligned cloud and its voxelizations, shared by Stages 2 and 3."""

    frame: pc.GroundFrame
    sensor_h: float
    points: np.ndarray
    columns: pc.ColumnGrid
    voxels: pc.VoxelGrid
    extras: dict = field(default_factory=dict)


def detect_craters_lidar(
    points: np.ndarray,
    *,
    sensor_origin: Sequence[float] = (0.0, 0.0, 1.5),
    map_craters: Sequence[MapCrater] | None = None,
    config: LidarConfig | None = None,
) -> list[LidarDetection]:
    """Detect craters in one lidar scan: Stages 1-2, and Stage 3 when a map prior is given.

    Args:
        points: the scan, m, any frame with z roughly up; rows with NaN are no-returns.
        sensor_origin: sensor position in that frame, m.
        map_craters: craters expected around the rover (orbital map + approximate pose). None
            returns the Stage-2 estimates unmatched.
        config: settings (defaults: the paper's sensor).

    Returns:
        detections, best score first (Stage 3) or in cluster order (Stage 2 only). An empty
        cloud, an all-NaN cloud or a flat scene gives an empty list.

    Raises:
        InputError: ``points`` not (N, 3), or ``sensor_origin`` not 3 finite numbers.

    Shape:
        points: (N, 3) -> list of detections with (3,) centers.
    """
    cfg = config or LidarConfig()
    pts = pc.finite_cloud("points", points)
    sensor = np.asarray(sensor_origin, float)
    if sensor.shape != (3,) or not np.all(np.isfinite(sensor)):
        raise InputError(f"sensor_origin: expected 3 finite numbers, got {sensor_origin!r}")
    scene = prepare_scene(pts, sensor, cfg)
    if scene is None:
        return []
    estimates = [e for w in find_back_walls(scene, cfg) if (e := estimate_crater(scene, w, cfg))]
    if map_craters is None:
        return [_unmatched(scene, e) for e in estimates]
    return match_to_map(scene, estimates, list(map_craters), cfg)


def prepare_scene(pts: np.ndarray, sensor: np.ndarray, cfg: LidarConfig) -> _Scene | None:
    """Ground plane, gravity alignment, ROI crop, downsampling and voxel grids (None: too few
    points for a plane)."""
    near = np.hypot(pts[:, 0] - sensor[0], pts[:, 1] - sensor[1]) <= cfg.roi_m
    pts = pts[near]
    if len(pts) < 50:
        return None
    try:
        normal, offset, inliers = pc.fit_plane_ransac(
            pts, inlier_tol_m=cfg.plane_tol_m, max_tilt_deg=cfg.max_ground_tilt_deg)
    except InputError:  # no level-enough plane among the hypotheses
        return None
    if inliers.mean() < cfg.min_ground_fraction:
        return None
    frame = pc.ground_frame(normal, offset, sensor)
    ground = pc.voxel_downsample(frame.to_ground(pts), cfg.downsample_m)
    sensor_h = float(frame.to_ground(sensor[None])[0, 2])
    if sensor_h <= 0:
        return None
    columns = pc.ColumnGrid.build(ground, cfg.column_cell_m, cfg.roi_m + 1.0)
    return _Scene(frame, sensor_h, ground, columns, pc.VoxelGrid.build(ground, cfg.voxel_m))


def find_back_walls(scene: _Scene, cfg: LidarConfig) -> list[BackWall]:
    """Stage 1: clusters of normals tilted toward the sensor, size-filtered."""
    pts = scene.points
    normals, valid = pc.estimate_normals(pts, k=cfg.normal_k)
    to_sensor = -pts[:, :2] / np.maximum(np.linalg.norm(pts[:, :2], axis=1, keepdims=True), 1e-9)
    facing = valid & (np.einsum("ij,ij->i", normals[:, :2], to_sensor)
                      > np.sin(np.radians(cfg.min_slope_deg)))
    idx = np.nonzero(facing)[0]
    if len(idx) < cfg.min_cluster_points:
        return []
    pairs = cKDTree(pts[idx]).query_pairs(cfg.cluster_link_m, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                       shape=(len(idx), len(idx)))
    _, labels = connected_components(graph, directed=False)
    walls = []
    for lab in np.unique(labels):
        members = idx[labels == lab]
        if len(members) < cfg.min_cluster_points:
            continue
        xy = pts[members, :2]
        extent = float(np.max(np.ptp(xy, axis=0)))
        if cfg.min_cluster_extent_m <= extent <= cfg.max_cluster_extent_m:
            walls.append(BackWall(pts[members], normals[members], pts[members].mean(axis=0)))
    return walls


def trace_front_rim(
    scene: _Scene, wall: BackWall, cfg: LidarConfig
) -> np.ndarray | None:
    """Stage 2: walk from the back-wall centroid toward the sensor, casting vertical rays into
    the column grid; the front rim is the first return after a no-data stretch longer than the
    lidar's ring spacing on flat ground there.

    Returns:
        (3,) front-rim point (ground frame, m), or None when no shadow is found.
    """
    rho_c = float(np.hypot(*wall.centroid[:2]))
    u = wall.centroid[:2] / max(rho_c, 1e-9)
    s = np.arange(rho_c, max(rho_c - cfg.max_diameter_m, 0.5), -cfg.column_cell_m)
    tops = scene.columns.lookup(s[:, None] * u)
    has = np.isfinite(tops)
    dtheta = np.radians(cfg.angular_res_deg)
    i = int(np.argmin(has)) if not has.all() else len(has)  # first no-data cell
    while i < len(has):
        j = i + int(np.argmax(has[i:])) if has[i:].any() else len(has)
        if j == len(has):
            return None
        gap = s[i - 1] - s[j] if i > 0 else s[0] - s[j]
        ring = s[j] ** 2 * dtheta / scene.sensor_h
        if gap >= max(2 * cfg.column_cell_m, 1.1 * ring + cfg.column_cell_m):
            return np.array([s[j] * u[0], s[j] * u[1], tops[j]])
        i = j + int(np.argmin(has[j:])) if not has[j:].all() else len(has)
    return None


def estimate_crater(scene: _Scene, wall: BackWall, cfg: LidarConfig) -> CraterEstimate | None:
    """Stage 2: front rim, back rim from re-filtered normals, diameter and center."""
    front = trace_front_rim(scene, wall, cfg)
    if front is None:
        return None
    u = wall.centroid[:2] / max(float(np.hypot(*wall.centroid[:2])), 1e-9)
    center0 = 0.5 * (front[:2] + wall.centroid[:2])
    toward = center0 - wall.points[:, :2]
    toward /= np.maximum(np.linalg.norm(toward, axis=1, keepdims=True), 1e-9)
    nh = wall.normals[:, :2] / np.maximum(np.linalg.norm(wall.normals[:, :2], axis=1,
                                                         keepdims=True), 1e-9)
    keep = np.einsum("ij,ij->i", nh, toward) > cfg.backrim_cos
    if keep.sum() < 3:
        return None
    proj = wall.points[keep, :2] @ u
    back = wall.points[keep][int(np.argmin(np.abs(proj - np.quantile(proj, 0.98))))]
    diameter = float(np.quantile(proj, 0.98) - front[:2] @ u)
    if not cfg.min_diameter_m <= diameter <= cfg.max_diameter_m:
        return None
    center_xy = front[:2] + 0.5 * diameter * u
    center = np.array([center_xy[0], center_xy[1], 0.5 * (front[2] + back[2])])
    return CraterEstimate(wall, front, back, center, diameter)


def _unmatched(scene: _Scene, est: CraterEstimate) -> LidarDetection:
    center = scene.frame.from_ground(est.center[None])[0]
    return LidarDetection(center, est.diameter_m, float("nan"), None, center, est.diameter_m)


def match_to_map(
    scene: _Scene, estimates: list[CraterEstimate], map_craters: list[MapCrater],
    cfg: LidarConfig,
) -> list[LidarDetection]:
    """Stage 3: for each estimate, the best-scoring placement of the map craters of similar
    diameter, then (``prior_search_m`` > 0) each map crater's placement around its prior
    center where it scores higher; one detection per map crater, best score first."""
    best: dict[int, LidarDetection] = {}
    if not map_craters:
        return []
    # prior centers in the ground frame (m), once
    priors = scene.frame.to_ground(np.array([[*mc.center_xy, 0.0] for mc in map_craters]))[:, :2]
    for est in estimates:
        for k, mc in enumerate(map_craters):
            if not _is_candidate(est, mc, priors[k], cfg):
                continue
            center, score = fit_model(scene, est.center[:2], mc, cfg)
            if score < cfg.min_score or (k in best and best[k].score >= score):
                continue
            if (cfg.max_prior_offset_m is not None
                    and np.hypot(*(center[:2] - priors[k])) > cfg.max_prior_offset_m):
                continue
            stage2 = scene.frame.from_ground(est.center[None])[0]
            best[k] = LidarDetection(scene.frame.from_ground(center[None])[0], mc.diameter_m,
                                     score, k, stage2, est.diameter_m)
    if cfg.prior_search_m > 0:
        for k, mc in enumerate(map_craters):
            det = _search_at_prior(scene, mc, k, priors[k], cfg)
            if (det is not None and (k not in best or det.score > best[k].score)
                    and not _inside_another(det, k, best)):
                best[k] = det
    return sorted(best.values(), key=lambda d: -d.score)


def _inside_another(det: LidarDetection, k: int, best: dict[int, LidarDetection]) -> bool:
    """The prior-search placement's center lies within the rim of another map crater's
    detection: that crater's shadow explains the empty columns the placement was kept for."""
    return any(j != k and other.diameter_m > det.diameter_m
               and np.hypot(*(det.center_m[:2] - other.center_m[:2])) < 0.5 * other.diameter_m
               for j, other in best.items())


def _search_at_prior(scene: _Scene, mc: MapCrater, k: int, prior: np.ndarray,
                     cfg: LidarConfig) -> LidarDetection | None:
    """Place map crater ``k`` around its prior center ``prior`` (ground frame, m) (None:
    outside the processed region or scoring below ``min_score``)."""
    if np.hypot(*prior) + 0.5 * mc.diameter_m > cfg.roi_m:
        return None
    center, score = fit_model(scene, prior, mc, cfg, half_width_m=cfg.prior_search_m)
    if score < cfg.min_score:
        return None
    _, model = sighted_model(scene, mc, center[:2], cfg)
    contrast, expected = shadow_contrast(scene, model, center[:2], mc.diameter_m)
    if expected < cfg.min_shadow_expected or contrast < cfg.min_shadow_contrast:
        return None
    out = scene.frame.from_ground(center[None])[0]
    return LidarDetection(out, mc.diameter_m, score, k, np.full(3, np.nan), float("nan"))


MIN_SIGHT_HEIGHT = 0.2  # m: floor of sight_height where a plane rises over the sensor
TWIN_OFFSET = 1.25  # lateral offset of the twin columns of shadow_contrast, in diameters


def shadow_contrast(scene: _Scene, model: ModelPoints, center_xy: np.ndarray,
                    diameter_m: float) -> tuple[float, int]:
    """How much emptier the model's shadow is than the same ranges beside the crater.

    Far away the rings on flat ground are metres apart, so most columns are empty whether a
    crater hides them or not. Each shadow column is compared with its twins: the columns at
    the same range from the sensor, turned about it so they sit ``TWIN_OFFSET`` D to either
    side of the crater, where the rings of open ground pass. A crater leaves its shadow
    columns empty where the twins hold returns; open ground fills both about alike (0.3-0.5
    on the analytic flat scan: the placement search picks the emptiest spot, and a tilted
    spin axis spaces the rings differently with azimuth).

    Returns:
        1 - (occupied shadow columns / occupied twins), and the number of occupied twins
        (0: no ring reaches those ranges and the test says nothing; contrast NaN).
    """
    pts = model.shadow[:, :2] + np.asarray(center_xy, float)
    if len(pts) == 0:
        return float("nan"), 0
    turn = TWIN_OFFSET * diameter_m / max(float(np.hypot(*center_xy)), diameter_m)
    occupied = np.isfinite(scene.columns.lookup(pts)).sum()
    twins = 0
    for a in (turn, -turn):
        rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        twins += np.isfinite(scene.columns.lookup(pts @ rot.T)).sum()
    if twins == 0:
        return float("nan"), 0
    return float(1.0 - 2.0 * occupied / twins), int(twins)


def _is_candidate(est: CraterEstimate, mc: MapCrater, prior: np.ndarray,
                  cfg: LidarConfig) -> bool:
    """Similar diameter and (with a prior radius) the prior center ``prior`` (ground frame,
    m) near the estimate."""
    if abs(est.diameter_m - mc.diameter_m) > cfg.diameter_tol * mc.diameter_m:
        return False
    if cfg.prior_radius_m is None:
        return True
    return float(np.hypot(*(prior - est.center[:2]))) <= cfg.prior_radius_m


def fit_model(
    scene: _Scene, center_xy: np.ndarray, mc: MapCrater, cfg: LidarConfig,
    half_width_m: float | None = None,
) -> tuple[np.ndarray, float]:
    """Place the map crater's model on a coarse then a fine 2D grid around ``center_xy`` (a
    Stage-2 estimate or a prior center, ground frame).

    Args:
        half_width_m: half-width of the coarse grid, m (default max(search_min_m,
            search_frac D)).

    Returns:
        best center (3,) in the ground frame (m, z = rim crest) and its score.
    """
    profile = map_profile(mc, cfg.model_width)
    center = np.asarray(center_xy, float)[:2]
    ground, model = sighted_model(scene, mc, center, cfg)
    half = (max(cfg.search_min_m, cfg.search_frac * mc.diameter_m) if half_width_m is None
            else half_width_m)
    step = max(0.2, mc.diameter_m / 40.0)
    for half_w, st in ((half, step), (step, step / 4), (step / 4, step / 16)):
        g = np.arange(-half_w, half_w + 1e-9, st)
        offsets = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2) + center
        scores = score_placements(scene, model, offsets, ground, cfg)
        center, score = offsets[int(np.argmax(scores))], float(np.max(scores))
    return np.array([*center, plane_z(ground, center) + float(profile.rim_height_m)]), score


def map_profile(mc: MapCrater, width: float = 1.0) -> CraterProfile:
    """The parametric model of a map crater (floor depth = crest-to-floor depth - rim), its
    diameter ``width`` times the map's (``LidarConfig.model_width``)."""
    rim = RIM_RATIO * mc.diameter_m if mc.rim_height_m is None else mc.rim_height_m
    return CraterProfile(width * mc.diameter_m, max(mc.depth_m - rim, 0.0), rim)


def map_model(mc: MapCrater, center_xy: np.ndarray, sensor_h: float,
              profile: CraterProfile | None = None) -> ModelPoints:
    """The map crater's model (``profile``, default :func:`map_profile`) sampled every D / 50
    of the map diameter (at least 0.1 m), its points classified as seen from the sensor with
    the crater at ``center_xy`` (ground frame, m)."""
    profile = map_profile(mc) if profile is None else profile
    return ModelPoints.build(profile, max(0.1, mc.diameter_m / 50.0), center_xy, sensor_h)


def sighted_model(scene: _Scene, mc: MapCrater, center_xy: np.ndarray,
                  cfg: LidarConfig) -> tuple[np.ndarray, ModelPoints]:
    """The local ground at ``center_xy`` (:func:`local_ground`, (a, b, c)) and the map
    crater's model there (``cfg.model_width``), its sight lines set from that ground
    (:func:`sight_height`)."""
    profile = map_profile(mc, cfg.model_width)
    ground = local_ground(scene, profile, center_xy, cfg.tilted_ground)
    return ground, map_model(mc, center_xy, sight_height(scene, ground, cfg), profile)


def local_ground(scene: _Scene, profile: CraterProfile, center_xy: np.ndarray,
                 tilt: bool = False) -> np.ndarray:
    """The surface the crater sits in, from (column top - model flank height) over the annulus
    1.5-2.5 R around the center: z = a + b x + c y in the ground frame (m).

    Level (``tilt`` False): a is the median, b = c = 0. Tilted: a least-squares plane, refit
    once without the points more than 3 MAD off; level when the annulus holds too few points
    or they span too little of it. No data at all: the ground plane, z = 0.

    Returns:
        (a, b, c).
    """
    ang = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    rr = np.linspace(1.5, 2.5, 6) * profile.radius_m
    offsets = np.stack([np.outer(rr, np.cos(ang)), np.outer(rr, np.sin(ang))], -1).reshape(-1, 2)
    resid = scene.columns.lookup(center_xy + offsets) - np.repeat(profile.height(rr), len(ang))
    ok = np.isfinite(resid)
    if ok.sum() < 8:
        return np.zeros(3)
    level = np.array([float(np.median(resid[ok])), 0.0, 0.0])
    # a plane needs returns on more than one side: at least a quarter of the directions
    if not tilt or ok.reshape(len(rr), -1).any(axis=0).sum() < len(ang) // 4:
        return level
    a = np.column_stack([np.ones(ok.sum()), offsets[ok]])  # about the center: well conditioned
    z = resid[ok]
    coef = np.linalg.lstsq(a, z, rcond=None)[0]
    err = z - a @ coef
    mad = np.median(np.abs(err - np.median(err)))
    keep = np.abs(err - np.median(err)) <= 3 * 1.4826 * mad + 1e-6
    if keep.sum() >= 8:
        coef = np.linalg.lstsq(a[keep], z[keep], rcond=None)[0]
    return np.array([coef[0] - coef[1:] @ center_xy, coef[1], coef[2]])


def sight_height(scene: _Scene, ground: np.ndarray, cfg: LidarConfig) -> float:
    """The sensor's height for the model's line-of-sight classes, m: over the crater's local
    plane ``ground`` where it passes under the sensor (``plane_sight``), so that the sight lines
    meet the model at the angle they meet that plane. Over the scan's ground plane when
    ``plane_sight`` is off or the local ground is level (too few returns around the crater to
    fit its slope, or ``tilted_ground`` off): a crater's height alone, without the slope that
    usually comes with it, gave worse placements on development renders."""
    if not cfg.plane_sight or not np.any(ground[1:]):
        return scene.sensor_h
    return max(scene.sensor_h - float(ground[0]), MIN_SIGHT_HEIGHT)


def plane_z(ground: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Height of the plane ``ground`` = (a, b, c), z = a + b x + c y, at ``xy`` (..., 2), m."""
    return ground[0] + xy[..., 0] * ground[1] + xy[..., 1] * ground[2]


@dataclass
class ModelPoints:
    """Sampled parametric crater, relative to its center, split by the paper's rules.

    Attributes:
        rim: (R, 3) points on the rim band the sensor can see (rule 2).
        shadow: (S, 3) interior points the sensor cannot see: the area before the front rim
            (rule 1).
        other: (O, 3) every other point (rules 3 and 4).
    """

    rim: np.ndarray
    shadow: np.ndarray
    other: np.ndarray

    @classmethod
    def build(
        cls, profile: CraterProfile, spacing: float, center_xy: np.ndarray, sensor_h: float
    ) -> ModelPoints:
        """Sample ``profile`` and classify its points as seen from a sensor at the origin
        with the crater at ``center_xy`` (ground frame, m)."""
        pts, rho = profile.sample(spacing, extent=1.25)
        band = max(0.08, 1.5 * spacing / profile.radius_m)
        hidden = occluded(profile, pts, -np.asarray(center_xy, float), sensor_h)
        rim = (np.abs(rho - 1.0) <= band) & ~hidden
        shadow = hidden & (rho < 1.0)
        return cls(pts[rim], pts[shadow], pts[~rim & ~shadow])

    @property
    def count(self) -> int:
        """Number of scored points."""
        return len(self.rim) + len(self.shadow) + len(self.other)


def score_placements(
    scene: _Scene, model: ModelPoints, centers: np.ndarray, ground: np.ndarray,
    cfg: LidarConfig,
) -> np.ndarray:
    """Mean per-point score of the model placed at each center (0 best, -1 worst).

    Rules (paper, Stage 3): shadow points are penalized when their column holds a return (it
    should be occluded); rim points when no occupied voxel is near, in proportion to how far
    the nearest one is; other points when a return lies above them by more than the height
    tolerance; otherwise no penalty.

    Shape:
        centers: (P, 2) m -> (P,).
    """
    def place(part: np.ndarray) -> np.ndarray:
        # (P, M, 3): the model points at every center, lifted onto the ground plane
        pts = part[None] + np.concatenate([centers, np.zeros((len(centers), 1))], 1)[:, None]
        pts[..., 2] += plane_z(ground, pts[..., :2])
        return pts

    total = np.zeros(len(centers))
    if len(model.shadow):  # only their columns matter: no heights
        tops = scene.columns.lookup(model.shadow[None, :, :2] + centers[:, None])
        total -= np.isfinite(tops).sum(axis=1)
    if len(model.rim):
        rim = place(model.rim).reshape(-1, 3)
        d = scene.voxels.nearest(rim, cfg.rim_search_m).reshape(len(centers), -1)
        pen = np.clip((d - cfg.rim_tol_m) / (cfg.rim_search_m - cfg.rim_tol_m), 0.0, 1.0)
        total -= pen.sum(axis=1)
    if len(model.other):
        pts = place(model.other)
        above = scene.columns.lookup(pts[..., :2]) - pts[..., 2] - cfg.height_tol_m
        total -= np.clip(np.nan_to_num(above, nan=0.0) / 0.3, 0.0, 1.0).sum(axis=1)
    return total / max(model.count, 1)
