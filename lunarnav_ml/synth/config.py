"""Synthetic-scene configuration: nested dataclasses with validation.

A field written as ``(lo, hi)`` is a domain-randomization range: every scene draws a value
uniformly from it (write ``[v, v]``, or just ``v``, in YAML to fix it). Units are in the field names.
Unknown keys and impossible values raise :class:`lunarnav_ml.errors.ConfigError` naming the
dotted key (and the file, for :meth:`SynthConfig.from_yaml`).
"""

# ruff: noqa: RUF009  (``_f`` returns a dataclasses.field carrying bounds and a comment)

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lunarnav_ml.errors import ConfigError

Range = tuple[float, float]


def _f(default: Any, lo: float | None = None, hi: float | None = None, doc: str = "") -> Any:
    """A dataclass field with allowed bounds [lo, hi] (None = unbounded) and a comment."""
    meta = {"lo": lo, "hi": hi, "doc": doc}
    if isinstance(default, (tuple, list)):
        value = tuple(default)
        return field(default_factory=lambda: value, metadata=meta)
    return field(default=default, metadata=meta)


@dataclass
class TerrainConfig:
    """Heightfield DEM around the camera (periodic, so rays beyond it see a seamless tiling)."""

    extent_m: float = _f(64.0, 10.0, 1000.0, "side of the square DEM, m")
    resolution_m: float = _f(0.05, 0.005, 1.0, "DEM cell size, m")
    # Relief of the fractal base: RMS height at 10 m baseline and spectral (Hurst) exponent,
    # calibrated on the Apollo 15 NAC DTM crop (docs/synth.md).
    relief_rms_m: Range = _f((0.15, 0.6), 0.0, 20.0, "RMS height difference at 10 m lag, m")
    hurst: float = _f(0.9, 0.05, 1.0, "Hurst exponent of the fractal relief")
    roughness_rms_m: Range = _f((0.008, 0.025), 0.0, 0.5, "cm-scale roughness RMS, m")
    # Soil detail finer than the DEM, shaded only (bump-mapped normals, albedo speckle): what a
    # narrow camera sees of regolith close by; faded out where pixels are coarser (render.py).
    micro_slope_rms: Range = _f((0.0, 0.0), 0.0, 2.0, "sub-DEM texture: RMS added slope")
    micro_albedo_rms: Range = _f((0.0, 0.0), 0.0, 1.0, "sub-DEM texture: relative albedo RMS")
    micro_wavelength_m: float = _f(0.04, 0.002, 1.0, "sub-DEM texture: longest wavelength, m")
    # Pebbles too small for the DEM (shaded only: a lit hemisphere and its cast shadow), the
    # dots that cover real regolith close by; unlabelled (rocks.min_diameter_m is the label's).
    pebble_per_m2: Range = _f((0.0, 0.0), 0.0, 100.0, "sub-DEM pebbles per m^2")
    pebble_max_radius_m: float = _f(0.04, 0.005, 0.2, "largest sub-DEM pebble radius, m")


@dataclass
class CraterConfig:
    """Crater population (cumulative power law N(>=D) = density * D^-slope per m^2)."""

    # Calibrated on LRO NAC crater boxes near the Chang'e 4 site (docs/synth.md).
    density_per_m2: Range = _f((0.04, 0.10), 0.0, 10.0, "N(>=1 m) per m^2")
    sfd_slope: float = _f(2.0, 0.5, 4.0, "cumulative SFD slope (equilibrium: 2)")
    min_diameter_m: float = _f(0.5, 0.05, 100.0, "smallest crater placed, m")
    max_diameter_m: float = _f(25.0, 0.1, 500.0, "largest crater placed, m")
    fresh_fraction: Range = _f((0.3, 0.6), 0.0, 1.0, "share of fresh craters")
    depth_ratio_fresh: float = _f(0.2, 0.01, 0.5, "depth/diameter of a fresh crater (Pike 1977)")
    depth_ratio_degraded: Range = _f((0.06, 0.15), 0.01, 0.5, "depth/diameter, degraded")
    rim_ratio_fresh: float = _f(0.04, 0.0, 0.2, "rim height / D of a fresh crater")
    near_camera_boost: Range = _f((2, 5), 0, 50, "extra craters of 2-20 m placed ahead")
    near_camera_range_m: Range = _f((4.0, 35.0), 0.5, 500.0,
                                    "near-rim distance of the extra craters (uniform), m")
    crest_at_rim: bool = _f(True, doc="move each smoothed profile's crest onto the labelled "
                                      "rim (off: degraded crests lie at 1.1-1.4 radii)")


@dataclass
class RockConfig:
    """Rock population (cumulative power law N(>=D) = density * (D / 0.1 m)^-slope per m^2)."""

    density_per_m2: Range = _f((0.05, 0.4), 0.0, 20.0, "N(>=0.1 m) per m^2")
    sfd_slope: float = _f(2.5, 0.5, 5.0, "cumulative SFD slope")
    min_diameter_m: float = _f(0.1, 0.01, 10.0, "smallest rock, m")
    max_diameter_m: float = _f(1.5, 0.02, 20.0, "largest rock, m")
    burial: Range = _f((0.1, 0.6), 0.0, 0.95, "buried fraction of the rock height")
    albedo_factor: Range = _f((1.0, 1.6), 0.1, 5.0, "rock single-scattering albedo / soil's")


@dataclass
class ArtifactConfig:
    """Human-made objects: lander, rover, hardware (boxes, masts, cylinders; foil or paint)."""

    probability: float = _f(0.35, 0.0, 1.0, "chance that a scene holds artifacts")
    max_count: int = _f(2, 0, 20, "most artifacts in one scene")
    range_m: Range = _f((4.0, 25.0), 0.5, 500.0, "distance ahead of the camera, m")
    kinds: tuple[str, ...] = field(default=("lander", "rover", "hardware"),
                                   metadata={"lo": None, "hi": None, "doc": "kinds to draw"})


@dataclass
class CameraConfig:
    """Stereo camera rig (paper table: 90 deg FOV, 1.5 m height, 0.30 m baseline)."""

    fov_deg: Range = _f((90.0, 90.0), 10.0, 150.0,
                        "horizontal field of view, deg (a range: drawn per scene)")
    aspect: Range = _f((1.0, 1.0), 0.5, 2.0,
                       "fy / fx of the square image (a range: drawn per scene); 1 is the "
                       "paper's square pixels; the Chang'e frames, 2352 x 1728 stretched to "
                       "432 x 432, have 1.36")
    height_m: Range = _f((1.3, 1.7), 0.1, 20.0, "camera height above the ground, m")
    pitch_deg: Range = _f((15.0, 25.0), -60.0, 89.0, "depression below horizontal, deg")
    roll_deg: Range = _f((-3.0, 3.0), -45.0, 45.0, "roll about the optical axis, deg")
    baseline_m: float = _f(0.30, 0.01, 5.0, "stereo baseline, m")
    supersample: int = _f(1, 1, 4, "render at k x size and Lanczos-downsample (paper: 2)")
    max_range_m: float = _f(150.0, 5.0, 5000.0, "farthest terrain a ray sees, m")


@dataclass
class SunConfig:
    """Sun direction relative to the camera heading (azimuth 0 = in front, 180 = behind)."""

    zenith_deg: Range = _f((0.0, 85.0), 0.0, 90.0, "sun zenith angle, deg")
    azimuth_deg: Range = _f((0.0, 360.0), -360.0, 720.0, "sun azimuth, deg, clockwise from ahead")


@dataclass
class HapkeConfig:
    """Hapke IMSA photometry with shadow-hiding and coherent-backscatter opposition terms.

    Defaults: w from Chang'e-3 PCAM mare photometry (0.17-0.21), theta_bar from Sato et al. 2014
    (LROC WAC Hapke maps), double Henyey-Greenstein b, c and opposition widths typical of
    lunar Hapke fits (Sato et al. 2014; Hapke 2012). See docs/synth.md.
    """

    w: Range = _f((0.17, 0.21), 0.01, 0.99, "single-scattering albedo")
    b: float = _f(0.21, 0.0, 0.99, "double Henyey-Greenstein asymmetry")
    c: float = _f(0.7, -1.0, 1.0, "double Henyey-Greenstein back/forward partition")
    b_s0: float = _f(1.0, 0.0, 5.0, "shadow-hiding opposition amplitude")
    h_s: float = _f(0.07, 0.001, 1.0, "shadow-hiding opposition width")
    b_c0: float = _f(0.6, 0.0, 5.0, "coherent-backscatter opposition amplitude")
    h_c: float = _f(0.03, 0.001, 1.0, "coherent-backscatter opposition width")
    theta_bar_deg: float = _f(23.657, 0.0, 60.0, "macroscopic roughness, deg (Sato 2014)")
    albedo_texture_rms: Range = _f((0.03, 0.12), 0.0, 0.5, "relative RMS of the albedo texture")


@dataclass
class SensorConfig:
    """Image sensor: exposure, gain, shot and read noise, blur, gamma, ADC bits."""

    exposure: Range = _f((0.6, 1.1), 0.01, 10.0, "brightest-terrain level / full scale")
    full_well_e: float = _f(12000.0, 10.0, 1e7, "electrons at full scale (sets shot noise)")
    read_noise_e: Range = _f((3.0, 15.0), 0.0, 1e4, "read noise RMS, electrons")
    blur_sigma_px: Range = _f((0.3, 0.8), 0.0, 10.0, "Gaussian PSF sigma, px")
    gamma: Range = _f((1.0, 2.2), 0.2, 5.0, "output gamma (1 = linear)")
    adc_bits: int = _f(12, 8, 12, "ADC bits (8 or 12); output PNG is 8-bit")


@dataclass
class LidarConfig:
    """360 deg scanning lidar (paper table)."""

    h_fov_deg: float = _f(360.0, 1.0, 360.0, "horizontal field of view, deg")
    v_fov_deg: float = _f(75.0, 1.0, 180.0, "vertical field of view, deg")
    h_res_deg: float = _f(0.333, 0.01, 10.0, "horizontal angular resolution, deg")
    v_res_deg: float = _f(0.333, 0.01, 10.0, "vertical angular resolution, deg")
    height_m: float = _f(1.5, 0.1, 20.0, "sensor height, m")
    tilt_deg: float = _f(23.0, -90.0, 90.0, "downward tilt of the scan axis, deg")
    range_noise_m: float = _f(0.01, 0.0, 5.0, "range noise sigma at 0 m, m")
    range_noise_per_m: float = _f(0.0005, 0.0, 0.5, "range noise sigma growth per m")
    max_range_m: float = _f(100.0, 1.0, 5000.0, "no return beyond this range, m")


@dataclass
class LabelConfig:
    """Label rules (DESIGN.md) and this generator's documented extensions."""

    max_near_rim_range_m: float = _f(35.0, 1.0, 1e4, "craters farther are ignored, m")
    min_box_height_px: float = _f(6.0, 0.0, 1e4, "shorter boxes are ignored, px")
    min_clip_fraction: float = _f(0.5, 0.0, 1.0, "clipped/unclipped area below -> ignored")
    min_emit_height_px: float = _f(3.0, 0.0, 1e4, "shorter boxes are not written, px")
    crater_min_diameter_m: float = _f(1.0, 0.0, 1e4, "smaller craters are ignored, m")
    min_visible_rim_fraction: float = _f(0.3, 0.0, 1.0, "less visible rim -> ignored")
    min_depth_m: float = _f(0.08, 0.0, 100.0, "shallower craters are ignored, m")
    min_surviving_bowl_fraction: float = _f(
        0.5, 0.0, 1.0, "less of the bowl's relief left by later craters' stamps -> ignored")
    min_rim_minor_axis_px: float = _f(
        6.0, 0.0, 1e4, "thinner projected rim ellipses (craters seen edge-on) are ignored, px")

    def edge_on(self, minor_px: float, height_px: float) -> bool:
        """The ``edge_on`` rule: a rim ellipse thinner than ``min_rim_minor_axis_px`` (its
        minor axis, px) in a box tall enough for ``min_box_height_px``, i.e. tall only because
        the thin ellipse is tilted."""
        return minor_px < self.min_rim_minor_axis_px and height_px >= self.min_box_height_px


SECTIONS = {
    "terrain": TerrainConfig, "craters": CraterConfig, "rocks": RockConfig,
    "artifacts": ArtifactConfig, "camera": CameraConfig, "sun": SunConfig, "hapke": HapkeConfig,
    "sensor": SensorConfig, "lidar": LidarConfig, "labels": LabelConfig,
}
ARTIFACT_KINDS = ("lander", "rover", "hardware")


@dataclass
class SynthConfig:
    """All synth settings, one section per concern (see the section classes for fields)."""

    terrain: TerrainConfig = field(default_factory=TerrainConfig)
    craters: CraterConfig = field(default_factory=CraterConfig)
    rocks: RockConfig = field(default_factory=RockConfig)
    artifacts: ArtifactConfig = field(default_factory=ArtifactConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    sun: SunConfig = field(default_factory=SunConfig)
    hapke: HapkeConfig = field(default_factory=HapkeConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    lidar: LidarConfig = field(default_factory=LidarConfig)
    labels: LabelConfig = field(default_factory=LabelConfig)

    def __post_init__(self) -> None:
        for name, cls in SECTIONS.items():
            value = getattr(self, name)
            if isinstance(value, dict):
                setattr(self, name, _section_from_dict(cls, value, name))
            elif not isinstance(value, cls):
                raise ConfigError(f"synth config: '{name}' must be a mapping, got {value!r}")
        self.validate()

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None, source: str = "synth config") -> SynthConfig:
        """Build from a nested mapping; unknown keys or bad values raise ConfigError."""
        data = {} if data is None else data
        if not isinstance(data, dict):
            raise ConfigError(f"{source}: top level must be a mapping, got {type(data).__name__}")
        unknown = sorted(set(data) - set(SECTIONS))
        if unknown:
            raise ConfigError(f"{source}: unknown key '{unknown[0]}' (known: {', '.join(SECTIONS)})")
        try:
            return cls(**{k: _section_from_dict(SECTIONS[k], v, k) for k, v in data.items()})
        except ConfigError as err:
            raise ConfigError(f"{source}: {err}") from None

    @classmethod
    def from_yaml(cls, path: str | Path) -> SynthConfig:
        """Load a YAML file; errors name the file and the dotted key."""
        from lunarnav_ml.utils.yamlfile import read_yaml

        return cls.from_dict(read_yaml(path, "synth config file"), source=str(path))

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict (tuples as lists), the inverse of :meth:`from_dict`."""
        return {k: {f: _plain(v) for f, v in dataclasses.asdict(getattr(self, k)).items()}
                for k in SECTIONS}

    def validate(self) -> None:
        """Check every value against its bounds and the cross-field rules."""
        for name in SECTIONS:
            section = getattr(self, name)
            for f in dataclasses.fields(section):
                _check_value(f"{name}.{f.name}", getattr(section, f.name), f)
        _cross_checks(self)


def _plain(value: Any) -> Any:
    return list(value) if isinstance(value, tuple) else value


def _section_from_dict(cls: type, data: Any, name: str) -> Any:
    if not isinstance(data, dict):
        raise ConfigError(f"'{name}' must be a mapping, got {data!r}")
    names = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(data) - set(names))
    if unknown:
        raise ConfigError(f"unknown key '{name}.{unknown[0]}' (known: {', '.join(names)})")
    ranged = {f.name for f in dataclasses.fields(cls) if _is_range(f)}
    kwargs = {k: _as_range(v) if k in ranged else tuple(v) if isinstance(v, list) else v
              for k, v in data.items()}
    section = cls(**kwargs)
    for f in dataclasses.fields(cls):
        _check_value(f"{name}.{f.name}", getattr(section, f.name), f)
    return section


def _default(f: dataclasses.Field) -> Any:
    return f.default if f.default is not dataclasses.MISSING else f.default_factory()


def _is_names(f: dataclasses.Field) -> bool:
    """A list-of-names field (a tuple default of strings)."""
    default = _default(f)
    return isinstance(default, tuple) and bool(default) and isinstance(default[0], str)


def _is_range(f: dataclasses.Field) -> bool:
    """A numeric [lo, hi] field (a tuple default of numbers)."""
    return isinstance(_default(f), tuple) and not _is_names(f)


def _as_range(value: Any) -> Any:
    """A YAML value for a range field: a list becomes a tuple, a lone number a fixed range."""
    if isinstance(value, list):
        return tuple(value)
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return (value, value)
    return value


def _check_value(key: str, value: Any, f: dataclasses.Field) -> None:
    """Raise ConfigError unless ``value`` has the field's type and lies in its bounds."""
    if _is_names(f):
        if not isinstance(value, tuple) or not all(isinstance(v, str) for v in value):
            raise ConfigError(f"'{key}' must be a list of names, got {value!r}")
        return
    if isinstance(_default(f), bool):
        if not isinstance(value, bool):
            raise ConfigError(f"'{key}' must be true or false, got {value!r}")
        return
    values = _numbers(key, value, ranged=_is_range(f), integer=type(_default(f)) is int)
    lo, hi = f.metadata.get("lo"), f.metadata.get("hi")
    for v in values:
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise ConfigError(f"'{key}' = {v} is impossible (allowed {lo} .. {hi})")


def _numbers(key: str, value: Any, ranged: bool, integer: bool) -> tuple[float, ...]:
    """Validate a scalar or a [lo, hi] range; returns the numbers to bound-check."""
    if ranged:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            raise ConfigError(f"'{key}' must be a range [lo, hi], got {value!r}")
        if not isinstance(value, tuple) or len(value) != 2:
            raise ConfigError(f"'{key}' must be a range [lo, hi], got {value!r}")
        values = tuple(value)
    else:
        values = (value,)
    for v in values:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise ConfigError(f"'{key}' must be a finite number, got {v!r}")
        if integer and not float(v).is_integer():
            raise ConfigError(f"'{key}' must be an integer, got {v!r}")
    if ranged and values[0] > values[1]:
        raise ConfigError(f"'{key}' range [{values[0]}, {values[1]}] has lo > hi")
    return values


def _cross_checks(cfg: SynthConfig) -> None:
    if cfg.craters.min_diameter_m > cfg.craters.max_diameter_m:
        raise ConfigError("'craters.min_diameter_m' is larger than 'craters.max_diameter_m'")
    if cfg.craters.max_diameter_m * 2.5 > cfg.terrain.extent_m:
        raise ConfigError(f"'craters.max_diameter_m' = {cfg.craters.max_diameter_m} needs "
                          f"'terrain.extent_m' >= {cfg.craters.max_diameter_m * 2.5} (a crater "
                          "and its ejecta, 2.5 diameters across, must fit in the DEM)")
    if cfg.rocks.min_diameter_m > cfg.rocks.max_diameter_m:
        raise ConfigError("'rocks.min_diameter_m' is larger than 'rocks.max_diameter_m'")
    if cfg.sensor.adc_bits not in (8, 12):
        raise ConfigError(f"'sensor.adc_bits' must be 8 or 12, got {cfg.sensor.adc_bits}")
    for kind in cfg.artifacts.kinds:
        if kind not in ARTIFACT_KINDS:
            raise ConfigError(f"'artifacts.kinds' has unknown kind '{kind}' "
                              f"(known: {', '.join(ARTIFACT_KINDS)})")
    n = cfg.terrain.extent_m / cfg.terrain.resolution_m
    if n > 8192:
        raise ConfigError(f"'terrain.extent_m' / 'terrain.resolution_m' = {n:.0f} cells per side "
                          "is over 8192")


def uniform(rng: Any, r: Range) -> float:
    """Draw one value from a [lo, hi] range (always one draw, so streams stay aligned)."""
    return float(rng.uniform(r[0], r[1]))
