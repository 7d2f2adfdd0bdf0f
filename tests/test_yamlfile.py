"""YAML files read with one-line errors that name the file."""

import pytest

from lunarnav_ml.errors import ConfigError
from lunarnav_ml.utils.yamlfile import read_yaml


def test_read_yaml(tmp_path):
    good = tmp_path / "good.yaml"
    good.write_text("a: [1, 2]\nb: {c: x}\n")
    assert read_yaml(good) == {"a": [1, 2], "b": {"c": "x"}}
    with pytest.raises(ConfigError, match="nowhere.yaml: scene config not found"):
        read_yaml(tmp_path / "nowhere.yaml", "scene config")


def test_malformed_yaml_is_one_line_naming_the_file(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("a: [\n  1,\nb: }\n")
    with pytest.raises(ConfigError, match="bad.yaml: not valid YAML") as err:
        read_yaml(bad)
    assert "\n" not in str(err.value)
