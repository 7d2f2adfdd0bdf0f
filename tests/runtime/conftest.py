"""ONNX fixtures shared with tests/export (tests/onnx_fixtures.py)."""

from tests.onnx_fixtures import onnx_nms_path, onnx_path, onnx_static_path, parts  # noqa: F401
