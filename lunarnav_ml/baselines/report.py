"""Baseline reports on the paper's protocol sets: Pd vs near-rim range per diameter, 3-sigma
horizontal position error per diameter, timings, plots, and the paper's numbers beside ours.

A ground-truth crater is detected when a detection's center lies within max(1 m, 0.25 D) of
its rim-circle center, horizontally (DESIGN.md, "Pd (3D)"). The evaluated craters are the
protocol target of each item (``protocol_item``) or, for other sets, every crater with
D >= ``min_diameter_m``. The position error is horizontal, in the rover frame. Two spreads
are reported: ``sigma`` (the paper's: standard deviation about the mean error vector) and
``rms`` (about zero, bias included); the headline 3-sigma is 3 * sigma.

Lidar (paper): the map prior holds every labelled crater of D >= ``map_min_diameter_m`` with
its center offset by N(0, ``prior_sigma_m``) per axis (approximate rover position); 3-sigma
over craters whose near rim is 15-20 m away. Stereo (paper): 3-sigma over all ranges with
significant detection (range bins with Pd >= ``significant_pd`` for that diameter).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from lunarnav_ml.baselines.lidar import LidarConfig, MapCrater, detect_craters_lidar
from lunarnav_ml.baselines.stereo import StereoConfig, detect_craters_stereo
from lunarnav_ml.errors import InputError
from lunarnav_ml.eval.spread import horizontal_spread
from lunarnav_ml.geometry._checks import crater_labels_3d
from lunarnav_ml.geometry.frames import camera_to_rover
from lunarnav_ml.utils import atomic
from lunarnav_ml.utils.images import read_disparity
from lunarnav_ml.utils.jsonfile import read_json_file

PAPER_3SIGMA_M = {"lidar": {5.0: 0.28, 10.0: 1.04, 15.0: 1.77, 20.0: 1.94},
                  "stereo": {5.0: 1.02, 10.0: 3.22, 15.0: 4.48, 20.0: 4.35}}
PAPER_PD = {"lidar": "Pd met the goal to the maximum range tested (20 m)",
            "stereo": "Pd at goal (0.5) for D >= 10 m to >= 15 m, for 5 m craters to 12 m"}
RANGE_BINS = tuple(float(r) for r in range(5, 21))  # near-rim range bin centers, m
METHODS = ("lidar", "stereo")
DISPARITY_SOURCES = ("sgbm", "truth-noise")


def baseline_report(
    dataset_dir: str | Path,
    out_dir: str | Path,
    *,
    method: str = "lidar",
    disparity: str = "sgbm",
    noise_px: float = 0.2,
    prior_sigma_m: float = 1.0,
    map_min_diameter_m: float = 4.0,
    min_diameter_m: float = 5.0,
    significant_pd: float = 0.5,
    max_images: int | None = None,
    seed: int = 0,
    progress: bool = True,
    lidar_config: LidarConfig | None = None,
    stereo_config: StereoConfig | None = None,
) -> dict[str, Any]:
    """Run one geometric baseline over a dataset and write its report.

    Args:
        dataset_dir: dataset root holding ``annotations.json`` (or that JSON file itself, e.g.
            a shard's ``annotations.shard-k-of-n.json``).
        out_dir: where metrics.json, report.md and the plots go.
        method: ``"lidar"`` (needs ``lidar_file`` per image) or ``"stereo"``.
        disparity: stereo input: ``"sgbm"`` (OpenCV StereoSGBM with left-right check on the
            rendered pair) or ``"truth-noise"`` (rendered disparity + N(0, noise_px)).
        noise_px: disparity noise of ``"truth-noise"``, px.
        prior_sigma_m: lidar map-prior position error per axis, m.
        map_min_diameter_m: smallest labelled crater put in the lidar map prior, m.
        min_diameter_m: smallest crater evaluated outside protocol sets, m.
        significant_pd: stereo 3-sigma uses range bins with at least this Pd.
        max_images: evaluate only the first n images (None: all).
        seed: seed of the prior offsets and disparity noise.
        progress: tqdm bar on stderr.
        lidar_config, stereo_config: detector settings (lidar default: ``LidarConfig`` with
            ``max_prior_offset_m`` = max(4 ``prior_sigma_m``, 1 m)).

    Returns:
        the metrics dict written to ``metrics.json``.

    Raises:
        InputError: unknown method or disparity source, missing files.
    """
    if method not in METHODS:
        raise InputError(f"method: expected one of {METHODS}, got {method!r}")
    if not (np.isfinite(prior_sigma_m) and prior_sigma_m >= 0):
        raise InputError(f"prior_sigma_m: must be >= 0 and finite, got {prior_sigma_m}")
    if disparity not in DISPARITY_SOURCES:
        raise InputError(f"disparity: expected one of {DISPARITY_SOURCES}, got {disparity!r}")
    ann_path = _annotations_path(Path(dataset_dir))
    gt = read_json_file(ann_path, "annotations", expect=dict)
    if not isinstance(gt.get("images"), list):
        raise InputError(f"{ann_path}: missing the 'images' list")
    images = gt["images"][:max_images] if max_images is not None else gt["images"]
    craters = _craters_by_image(ann_path, gt)
    if method == "lidar":
        # placements farther than four prior standard deviations (at least 1 m: a placement's
        # own error) from the prior are dropped
        cfg = lidar_config or LidarConfig(max_prior_offset_m=max(4.0 * prior_sigma_m, 1.0))
        run: Callable = lambda img, crs, rng: _run_lidar(
            ann_path.parent, img, crs, rng, cfg, prior_sigma_m, map_min_diameter_m)
    else:
        scfg = stereo_config or StereoConfig()
        run = lambda img, crs, rng: _run_stereo(
            ann_path, img, rng, scfg, disparity, noise_px)
    records, timings, false_alarms = [], [], 0
    craters = {img["id"]: with_protocol_target(img, craters.get(img["id"], []))
               for img in images}
    for img, dets, secs in _iterate(images, craters, run, seed, progress):
        targets = _targets(img, craters[img["id"]], min_diameter_m)
        recs, fa = match_detections(targets, dets, craters[img["id"]], img)
        for rec, target in zip(recs, targets):
            rec["visible"] = _visible(ann_path.parent, img, target, method)
        records += recs
        false_alarms += fa
        timings.append(secs)
    metrics = summarize(records, timings, false_alarms, len(images), method, significant_pd)
    metrics.update(method=method, dataset=str(ann_path),
                   disparity=disparity if method == "stereo" else None,
                   noise_px=noise_px if method == "stereo" and disparity == "truth-noise" else None,
                   prior_sigma_m=prior_sigma_m if method == "lidar" else None)
    write_baseline_report(metrics, Path(out_dir))
    return metrics


def _annotations_path(path: Path) -> Path:
    if path.is_file():
        return path
    ann = path / "annotations.json"
    if not ann.is_file():
        raise InputError(f"dataset_dir: no annotations.json in {path}")
    return ann


def _craters_by_image(path: Path, gt: dict[str, Any]) -> dict[int, list[dict[str, Any]]]:
    """Crater labels with a 3D centre by image id, each checked (``crater_labels_3d``)."""
    out: dict[int, list[dict[str, Any]]] = {}
    for a in crater_labels_3d(path, gt):
        out.setdefault(a["image_id"], []).append(a)
    return out


def _iterate(
    images: list[dict], craters: dict[int, list[dict]], run: Callable, seed: int,
    progress: bool,
) -> Iterator[tuple[dict, list[np.ndarray], float]]:
    """Run the detector per image: (image, detection centers (rover frame), seconds)."""
    from tqdm import tqdm

    for img in tqdm(images, desc="baseline", unit="img", disable=not progress):
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), int(img["id"])]))
        dets, secs = run(img, craters.get(img["id"], []), rng)
        yield img, dets, secs


def rover_center(ann: dict[str, Any], camera: dict[str, Any]) -> np.ndarray:
    """A crater annotation's rim-circle center in the rover frame, m (3,)."""
    if "center_rover_m" in ann:  # a protocol target added by :func:`with_protocol_target`
        return np.asarray(ann["center_rover_m"], float)
    return camera_to_rover(np.asarray(ann["center_cam_m"], float), float(camera["height_m"]),
                           float(camera["pitch_deg"]), float(camera.get("roll_deg", 0.0)))[0]


def _run_lidar(
    root: Path, img: dict, crs: list[dict], rng: np.random.Generator, cfg: LidarConfig,
    prior_sigma_m: float, map_min_d: float,
) -> tuple[list[np.ndarray], float]:
    if "lidar_file" not in img:
        raise InputError(f"images[{img['id']}]: no lidar_file (render with lidar=True)")
    with np.load(root / img["lidar_file"]) as scan:
        points = np.asarray(scan["points"], float)
        height = float(scan["height_m"]) if "height_m" in scan else 1.5
    prior = []
    for a in crs:
        if a["diameter_m"] >= map_min_d:
            c = rover_center(a, img["camera"])[:2] + rng.normal(0.0, prior_sigma_m, 2)
            prior.append(MapCrater((float(c[0]), float(c[1])), float(a["diameter_m"]),
                                   float(a.get("depth_m", 0.24 * a["diameter_m"]))))
    t0 = time.perf_counter()
    dets = detect_craters_lidar(points, sensor_origin=(0.0, 0.0, height), map_craters=prior,
                                config=cfg)
    return [d.center_m for d in dets], time.perf_counter() - t0


def _run_stereo(
    ann_path: Path, img: dict, rng: np.random.Generator, cfg: StereoConfig, source: str,
    noise_px: float,
) -> tuple[list[np.ndarray], float]:
    disp = load_disparity(ann_path.parent, img, source, noise_px, rng, ann_path=ann_path)
    t0 = time.perf_counter()
    dets = detect_craters_stereo(disp, img["camera"], config=cfg)
    return [d.center_m for d in dets], time.perf_counter() - t0


def load_disparity(
    root: Path, img: dict, source: str, noise_px: float, rng: np.random.Generator,
    ann_path: Path | None = None,
) -> np.ndarray:
    """The stereo detector's input for one image (NaN invalid).

    ``"sgbm"``: ``lunarnav_ml.geometry.stereo.compute_disparity`` on the rendered pair;
    ``"truth-noise"``: the rendered disparity plus N(0, noise_px), 0 (sky) -> NaN.
    ``ann_path``: the annotation file of ``img``, named in errors.

    Shape:
        -> (H, W) px.

    Raises:
        InputError: naming the annotation file, the image and the file that cannot be read.
    """
    if source == "sgbm":
        import cv2

        from lunarnav_ml.geometry.stereo import compute_disparity

        where = f"images[{img['id']}]" if ann_path is None else f"{ann_path}: image id {img['id']}"
        if "right_file" not in img:
            raise InputError(f"{where}: no right_file for SGBM (render with stereo)")
        pair = []
        for key in ("file_name", "right_file"):
            path = root / str(img[key])
            gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None
            if gray is None:
                raise InputError(f"{where}: cannot read its {key} {path} (missing, corrupt or "
                                 f"not an image)")
            pair.append(gray)
        left, right = pair
        max_d = img["camera"]["fx"] * img["camera"]["baseline_m"] / 1.0  # nearest ~1 m
        return compute_disparity(left, right, num_disparities=int(max_d)).disparity
    disp = read_disparity(root, img)
    noisy = disp + rng.normal(0.0, noise_px, disp.shape)
    return np.where(disp > 0, noisy, np.nan)


def _is_target(ann: dict, item: dict) -> bool:
    """The annotation is the protocol item's target crater (its exact diameter, its range)."""
    return (abs(ann["diameter_m"] - item["diameter_m"]) < 0.01 * item["diameter_m"]
            and abs(ann.get("near_rim_range_m", np.inf) - item["near_rim_range_m"]) < 1.0)


def with_protocol_target(img: dict, crs: list[dict]) -> list[dict]:
    """The image's crater annotations, plus the protocol target when no annotation is it.

    The camera labels only craters that show in the image (a small crater far away does not),
    but the protocol's target is always there, straight ahead of the rover
    (:func:`lunarnav_ml.synth.protocols.target_distance_m`), so the lidar and stereo baselines
    are scored on it and find it in their orbital map whether or not the camera saw it.
    """
    from lunarnav_ml.synth.protocols import TARGET_DEPTH_RATIO, target_distance_m

    item = img.get("protocol_item")
    if not item or any(_is_target(a, item) for a in crs):
        return crs
    d, near = float(item["diameter_m"]), float(item["near_rim_range_m"])
    return [*crs, {"diameter_m": d, "near_rim_range_m": near, "depth_m": TARGET_DEPTH_RATIO * d,
                   "center_rover_m": [target_distance_m(d, near), 0.0, 0.0],
                   "protocol_target": True}]


MIN_LIDAR_RETURNS = 10  # noise-free returns on the far half of a crater for the sensor to see it


def _visible(root: Path, img: dict, target: dict, method: str) -> bool:
    """Whether the sensor can see the target at all (hidden targets are left out of Pd, like
    the camera labels' "occluded" rule): for the camera, its label is not ignored as
    occluded; for the lidar, the noise-free scan has at least ``MIN_LIDAR_RETURNS`` returns
    inside the far half of its rim circle (relief between rover and crater can hide it all).
    """
    if "occluded" in target.get("ignore_reasons", []):
        return False
    if method != "lidar" or "lidar_file" not in img:
        return True
    center = rover_center(target, img["camera"])[:2]
    with np.load(root / img["lidar_file"]) as scan:
        pts = np.asarray(scan["points_true"], float)[:, :2]
    rel = pts - center
    inside = np.hypot(rel[:, 0], rel[:, 1]) < 0.5 * target["diameter_m"]
    far = rel @ center / max(float(np.linalg.norm(center)), 1e-9) > 0
    return int(np.count_nonzero(inside & far)) >= MIN_LIDAR_RETURNS


def _targets(img: dict, crs: list[dict], min_d: float) -> list[dict]:
    """The protocol target crater of the item, or every crater with D >= min_d."""
    item = img.get("protocol_item")
    if item:
        return [a for a in crs if _is_target(a, item)][:1]
    return [a for a in crs if a["diameter_m"] >= min_d]


def match_detections(
    targets: list[dict], dets: list[np.ndarray], all_craters: list[dict], img: dict
) -> tuple[list[dict[str, Any]], int]:
    """Greedy nearest matching of detections to targets within max(1 m, 0.25 D).

    Returns:
        one record per target (diameter, near-rim range, hit, error dx, dy in m) and the false
        alarms: detections within that tolerance of no labelled crater at all.
    """
    used: set[int] = set()
    records = []
    for a in targets:
        truth = rover_center(a, img["camera"])
        tol = max(1.0, 0.25 * a["diameter_m"])
        errs = [np.hypot(*(d[:2] - truth[:2])) if i not in used else np.inf
                for i, d in enumerate(dets)]
        best = int(np.argmin(errs)) if errs else -1
        hit = best >= 0 and errs[best] <= tol
        if hit:
            used.add(best)
        err = dets[best][:2] - truth[:2] if hit else np.array([np.nan, np.nan])
        records.append({"image_id": img["id"], "diameter_m": float(a["diameter_m"]),
                        "near_rim_range_m": float(a.get("near_rim_range_m", np.nan)),
                        "hit": bool(hit), "dx": float(err[0]), "dy": float(err[1])})
    centers = [rover_center(a, img["camera"]) for a in all_craters]
    fa = 0
    for i, d in enumerate(dets):
        if i in used:
            continue
        near = [np.hypot(*(d[:2] - c[:2])) <= max(1.0, 0.25 * a["diameter_m"])
                for c, a in zip(centers, all_craters)]
        fa += not any(near)
    return records, fa


def summarize(
    records: list[dict], timings: list[float], false_alarms: int, n_images: int, method: str,
    significant_pd: float,
) -> dict[str, Any]:
    """Pd vs range per diameter, 3-sigma per diameter, paper values and timings."""
    all_records = records
    records = [r for r in records if r.get("visible", True)]
    diams = sorted({r["diameter_m"] for r in records})
    pd_vs_range, position = {}, {}
    for dm in diams:
        mine = [r for r in records if r["diameter_m"] == dm]
        rows = _pd_rows(mine)
        pd_vs_range[f"{dm:g}"] = rows
        if method == "lidar":
            sel = [r for r in mine if r["hit"] and 15.0 <= r["near_rim_range_m"] <= 20.5]
        else:
            good = {row["range_m"] for row in rows if row["pd"] is not None
                    and row["pd"] >= significant_pd}
            sel = [r for r in mine if r["hit"] and round(r["near_rim_range_m"]) in good]
        position[f"{dm:g}"] = _spread(sel)
        paper = PAPER_3SIGMA_M[method].get(dm)
        position[f"{dm:g}"]["paper_3sigma_m"] = paper
    hits = [r["hit"] for r in records]
    return {
        "n_images": n_images, "n_targets": len(all_records),
        "n_hidden": len(all_records) - len(records),
        "pd_all": float(np.mean(hits)) if hits else None,
        "pd_including_hidden": float(np.mean([r["hit"] for r in all_records]))
        if all_records else None,
        "false_alarms_per_image": false_alarms / max(n_images, 1),
        "pd_vs_range": pd_vs_range, "position_error": position,
        "paper_pd": PAPER_PD[method],
        "seconds_per_item": {"mean": float(np.mean(timings)) if timings else None,
                             "max": float(np.max(timings)) if timings else None},
        "records": all_records,
    }


def _pd_rows(records: list[dict]) -> list[dict[str, Any]]:
    rows = []
    for r0 in RANGE_BINS:
        sel = [r for r in records if abs(r["near_rim_range_m"] - r0) < 0.5]
        n, det = len(sel), sum(r["hit"] for r in sel)
        rows.append({"range_m": r0, "n": n, "detected": det, "pd": det / n if n else None})
    return rows


def _spread(sel: list[dict]) -> dict[str, Any]:
    """Horizontal error spread: sigma about the mean vector and rms about zero, m."""
    return horizontal_spread(np.array([[r["dx"], r["dy"]] for r in sel]))


def write_baseline_report(metrics: dict[str, Any], out_dir: Path) -> dict[str, Path]:
    """metrics.json, report.md, pd_vs_range.png and position_error.png in ``out_dir``."""
    from lunarnav_ml.baselines.plots import plot_baseline

    out_dir.mkdir(parents=True, exist_ok=True)
    files = {"metrics": atomic.write_json(out_dir / "metrics.json", metrics),
             "report": atomic.write_text(out_dir / "report.md", render_markdown(metrics))}
    files.update(plot_baseline(metrics, out_dir))
    return files


def render_markdown(metrics: dict[str, Any]) -> str:
    """The report: 3-sigma per diameter beside the paper's, Pd vs range per diameter."""
    m = metrics
    src = f", disparity: {m['disparity']}" if m.get("disparity") else ""
    lines = [f"# {m['method']} baseline", "", f"Dataset: `{m['dataset']}`{src}", "",
             (f"- images {m['n_images']}, targets {m['n_targets']} ({m.get('n_hidden', 0)} "
              f"hidden from the sensor, left out of Pd), Pd (all visible) {_fmt(m['pd_all'])}, "
              f"Pd counting hidden targets as misses {_fmt(m.get('pd_including_hidden'))}, "
              f"false alarms per image {m['false_alarms_per_image']:.3f}"),
             (f"- seconds per item (1 thread): mean {_fmt(m['seconds_per_item']['mean'])}, "
              f"max {_fmt(m['seconds_per_item']['max'])}"), f"- paper: {m['paper_pd']}", "",
             "## 3-sigma horizontal position error", "",
             "| D (m) | n | 3 sigma (m) | 3 rms (m) | paper 3 sigma (m) |", "|---|---|---|---|---|"]
    for dm, row in m["position_error"].items():
        lines.append(f"| {dm} | {row['n']} | {_fmt(row['three_sigma_m'])} | "
                     f"{_fmt(row['three_rms_m'])} | {_fmt(row['paper_3sigma_m'])} |")
    groups = list(m["pd_vs_range"])
    lines += ["", "## Pd vs near-rim range", "",
              "| range (m) | " + " | ".join(f"D {g} m" for g in groups) + " |",
              "|---" * (len(groups) + 1) + "|"]
    for i, r0 in enumerate(RANGE_BINS):
        cells = [f"{_fmt(m['pd_vs_range'][g][i]['pd'], 2)} ({m['pd_vs_range'][g][i]['n']})"
                 for g in groups]
        lines.append(f"| {r0:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _fmt(x: float | None, nd: int = 3) -> str:
    return "n/a" if x is None else f"{x:.{nd}f}"
