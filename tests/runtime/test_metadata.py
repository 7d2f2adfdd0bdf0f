"""The metadata every exported file carries: round trip, foreign files, incompatible versions."""

import json

import pytest

from lunarnav_ml.errors import InputError
from lunarnav_ml.runtime.metadata import ModelMetadata

META = ModelMetadata(class_names=("crater", "rock", "artifact"), input_size=(512, 384),
                     strides=(8, 16, 32), anchors=(((1, 2),), ((3, 4),), ((5, 6),)),
                     scale_xy=(1.2, 1.1, 1.05), model="nano", project_version="0.1.0")


def test_round_trip_and_json_values():
    props = META.to_props()
    assert json.loads(props["lunarnav.class_names"]) == ["crater", "rock", "artifact"]
    back = ModelMetadata.from_props(props, "m.onnx")
    assert back == META and back.num_classes == 3 and back.max_stride == 32


def test_foreign_file_is_named():
    with pytest.raises(InputError, match="m.onnx: not a lunarnav export"):
        ModelMetadata.from_props({"author": "someone"}, "m.onnx")


def test_incompatible_format_version_says_what_is_expected():
    props = {**META.to_props(), "lunarnav.format_version": "7"}
    with pytest.raises(InputError, match="format version 7.*reads format version.*1"):
        ModelMetadata.from_props(props, "m.onnx")


def test_missing_and_malformed_fields():
    props = META.to_props()
    del props["lunarnav.anchors"]
    with pytest.raises(InputError, match="lunarnav.anchors is missing"):
        ModelMetadata.from_props(props, "m.onnx")
    with pytest.raises(InputError, match="not JSON"):
        ModelMetadata.from_props({**META.to_props(), "lunarnav.strides": "[8,"}, "m.onnx")
    with pytest.raises(InputError, match="malformed"):
        ModelMetadata.from_props({**META.to_props(), "lunarnav.input_size": "[1]"}, "m.onnx")


@pytest.mark.parametrize("key, value, match", [
    ("input_size", [-5, 384], "input_size must be .*multiples of the largest stride 32"),
    ("input_size", [100, 384], "input_size"),
    ("input_size", [384.5, 384], "input_size"),
    ("strides", [8, 0, 32], "strides must be"),
    ("std", [0.0, 0.0, 0.0], "std must be 3 finite numbers > 0"),
    ("std", [1.0, -1.0, 1.0], "std must be"),
    ("mean", [0.0, float("nan"), 0.0], "mean must be 3 finite numbers"),
    ("class_names", [], "class_names must be a non-empty list"),
    ("anchors", [[[1, 2]], [[3, 4]]], "anchors must be 3 levels"),
    ("anchors", [[[1, 2]], [[3, -4]], [[5, 6]]], "anchors must be"),
    ("scale_xy", [1.2, 1.1], "scale_xy must be 3 finite numbers"),
    ("pad_value", 300, "pad_value must be a gray level"),
])
def test_impossible_values_name_the_file_and_key(key, value, match):
    props = {**META.to_props(), f"lunarnav.{key}": json.dumps(value)}
    with pytest.raises(InputError, match=f"^m.onnx: metadata lunarnav.{match}"):
        ModelMetadata.from_props(props, "m.onnx")
