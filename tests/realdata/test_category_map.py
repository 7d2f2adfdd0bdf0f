"""Category maps: the shipped YAML, name matching, drop / error policies, bad files."""

from pathlib import Path

import pytest

from lunarnav_ml.errors import ConfigError
from lunarnav_ml.realdata.category_map import DEFAULT_MAPPING, CategoryMap, load_category_map

SHIPPED = Path(__file__).parents[2] / "configs" / "realdata" / "category_map.yaml"


def test_shipped_map_is_the_builtin_default():
    cmap = load_category_map(SHIPPED)
    assert cmap.mapping == DEFAULT_MAPPING
    assert (cmap.unmapped, cmap.ignore_height_below_px) == ("drop", 6.0)


@pytest.mark.parametrize("name, target", [
    ("crater", 1), ("Rock", 2), (" boulder ", 2), ("ARTIFACT", 3),
    ("rocky region", None), ("objects", None), ("anything else", None),
])
def test_default_targets(name, target):
    assert CategoryMap().target_id(name) == target


def test_error_policy_raises_for_unlisted_names(tmp_path):
    path = tmp_path / "map.yaml"
    path.write_text("map: {crater: crater}\nunmapped: error\n")
    cmap = load_category_map(path)
    assert cmap.target_id("Crater") == 1
    with pytest.raises(KeyError):
        cmap.target_id("rock")


@pytest.mark.parametrize("text, match", [
    ("map: {crater: hole}\n", "target must be one of"),
    ("map: {crater: crater}\nunmapped: maybe\n", "'unmapped' must be one of"),
    ("map: {crater: crater}\ncolour: red\n", "unknown key"),
    ("map: {Crater: crater, crater: rock}\n", "twice"),
    ("- crater\n", "'map' table"),
    ("map: {crater: crater}\nignore_height_below_px: -1\n", "ignore_height_below_px"),
    ("map: {crater: crater}\nignore_height_below_px: .nan\n",
     "'ignore_height_below_px' must be a finite number >= 0, got nan"),
    ("map: {crater: crater}\nignore_height_below_px: .inf\n", "finite number >= 0, got inf"),
])
def test_bad_map_files_name_the_file(tmp_path, text, match):
    path = tmp_path / "map.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=match) as err:
        load_category_map(path)
    assert "map.yaml" in str(err.value)


def test_missing_map_file(tmp_path):
    with pytest.raises(ConfigError, match="nope.yaml: category map file not found"):
        load_category_map(tmp_path / "nope.yaml")
