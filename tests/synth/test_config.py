"""Config validation: unknown keys and impossible values are rejected by name."""

from pathlib import Path

import pytest

from lunarnav_ml.errors import ConfigError
from lunarnav_ml.synth import SynthConfig

CONFIGS = sorted((Path(__file__).parents[2] / "configs" / "synth").rglob("*.yaml"))  # arms too


def test_defaults_are_valid():
    cfg = SynthConfig()
    assert SynthConfig.from_dict(cfg.to_dict()) == cfg


@pytest.mark.parametrize("data, needle", [
    ({"craters": {"diameter": 3}}, "craters.diameter"),
    ({"cameras": {}}, "cameras"),
    ({"craters": {"min_diameter_m": -1.0}}, "craters.min_diameter_m"),
    ({"sun": {"zenith_deg": [0, 95]}}, "sun.zenith_deg"),
    ({"sun": {"zenith_deg": [60, 10]}}, "lo > hi"),
    ({"sensor": {"adc_bits": 10}}, "sensor.adc_bits"),
    ({"artifacts": {"kinds": ["ufo"]}}, "ufo"),
    ({"camera": {"fov_deg": "wide"}}, "camera.fov_deg"),
    ({"terrain": {"extent_m": 40.0}}, "craters.max_diameter_m"),
    ({"craters": {"crest_at_rim": 1}}, "craters.crest_at_rim"),
])
def test_bad_values_name_the_key(data, needle):
    with pytest.raises(ConfigError, match=needle.replace(".", r"\.")):
        SynthConfig.from_dict(data)


def test_yaml_error_names_the_file(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("sun:\n  zenith_deg: [0, 91]\n")
    with pytest.raises(ConfigError, match="bad.yaml"):
        SynthConfig.from_yaml(bad)


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_every_shipped_config_loads(path):
    SynthConfig.from_yaml(path)


def test_a_number_fixes_a_range_field():
    cfg = SynthConfig.from_dict({"camera": {"fov_deg": 60, "pitch_deg": 20.0}})
    assert cfg.camera.fov_deg == (60, 60) and cfg.camera.pitch_deg == (20.0, 20.0)
    with pytest.raises(ConfigError, match=r"camera\.fov_deg"):
        SynthConfig.from_dict({"camera": {"fov_deg": [30, 170]}})
