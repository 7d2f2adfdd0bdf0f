"""Fixtures of tests/export and tests/runtime: a small untrained nano detector (BatchNorm
statistics set on noise) and its ONNX exports at 128 px, cached under pytest's base temp folder
so that both folders share one copy per session."""

import pytest

from lunarnav_ml.export.bench import random_detector
from lunarnav_ml.export.onnx_export import export_onnx
from lunarnav_ml.models.presets import PRESETS, Preset


@pytest.fixture(scope="session")
def parts():
    return random_detector("nano", img_size=128, seed=0)


@pytest.fixture
def mish_parts(monkeypatch):
    """An untrained 64 px detector with YOLOv4's Mish backbone (the medium and full presets'
    activation) at small's size: depth 0.33, so 44 backbone activations."""
    monkeypatch.setitem(PRESETS, "small-mish", Preset(depth=0.33, width=0.375))
    return random_detector("small-mish", img_size=64, seed=0)


def _cached_export(parts, tmp_path_factory, name, **kwargs):
    path = tmp_path_factory.getbasetemp() / "lunarnav_onnx" / name
    return path if path.is_file() else export_onnx(parts, path, **kwargs)


@pytest.fixture(scope="session")
def onnx_path(parts, tmp_path_factory):
    return _cached_export(parts, tmp_path_factory, "nano.onnx")


@pytest.fixture(scope="session")
def onnx_nms_path(parts, tmp_path_factory):
    return _cached_export(parts, tmp_path_factory, "nano_nms.onnx", nms=True)


@pytest.fixture(scope="session")
def onnx_static_path(parts, tmp_path_factory):
    return _cached_export(parts, tmp_path_factory, "nano_static.onnx", dynamic=False)
