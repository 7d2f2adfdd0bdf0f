"""ONNX fixtures shared with tests/runtime (tests/onnx_fixtures.py)."""

from tests.onnx_fixtures import mish_parts, onnx_nms_path, onnx_path, onnx_static_path, parts  # noqa: F401
