"""Source frames, cameras, leakage between splits, source-aware splitting."""

import pytest

from lunarnav_ml.realdata.sources import (
    camera_for,
    check_leakage,
    group_by_source,
    original_name,
    source_name,
    split_by_source,
)


@pytest.mark.parametrize("file_name, original", [
    ("C3_TCAM_2_2C_011_png.rf.90edb11624a9f75ec062f67c29043c51.jpg", "C3_TCAM_2_2C_011.png"),
    ("train/PCAML-C-012_SCI_N_20140113191206_0008_A_2C_png.rf.c5d3b5.jpg",
     "PCAML-C-012_SCI_N_20140113191206_0008_A_2C.png"),
    ("plain_frame.png", "plain_frame.png"),
])
def test_original_name(file_name, original):
    assert original_name(file_name) == original


def test_source_name_prefers_extra_name():
    image = {"file_name": "x_png.rf.abc123.jpg", "extra": {"name": "chang4_2019.png"}}
    assert source_name(image) == "chang4_2019.png"
    assert source_name({"file_name": "x_png.rf.abc123.jpg"}) == "x.png"


@pytest.mark.parametrize("name, camera", [
    ("PCAML-C-012_SCI_N_20140113191206_0008_A_2C.png", "pcam_colour"),
    ("PCAML-Q-086_SCI_N_20131223011502_0005_A_2A.png", "pcam_pan"),
    ("C3_TCAM_11_2C_031.png", "ce3_tcam"),
    ("chang4_20190111191735.png", "ce4"),
    ("apollo_15_frame.png", "unknown"),
])
def test_camera_from_original_name_prefix(name, camera):
    assert camera_for(name) == camera


def test_group_and_leakage():
    assert group_by_source(["a", "b", "a"]) == {"a": [0, 2], "b": [1]}
    assert check_leakage({"train": ["a", "a", "b"], "valid": ["c"], "test": ["d"]}) == {}
    leaks = check_leakage({"train": ["a", "b", "b"], "valid": ["b", "c"], "test": ["c", "a"]})
    assert leaks == {"train/valid": ["b"], "train/test": ["a"], "valid/test": ["c"]}


def test_split_by_source_keeps_copies_together():
    names = [f"frame{i // 3}" for i in range(30)]  # 10 sources x 3 copies
    parts = split_by_source(names, {"train": 0.8, "valid": 0.2}, seed=0)
    assert sorted(parts["train"] + parts["valid"]) == list(range(30))
    assert len(parts["valid"]) == 6  # 2 of 10 sources, 3 copies each
    sources = {p: {names[i] for i in idx} for p, idx in parts.items()}
    assert not sources["train"] & sources["valid"]
    assert parts == split_by_source(names, {"train": 0.8, "valid": 0.2}, seed=0)
    with pytest.raises(ValueError):
        split_by_source(names, {"train": -1.0})
