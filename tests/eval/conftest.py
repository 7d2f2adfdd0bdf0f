"""ONNX fixtures shared with tests/export and tests/runtime (tests/onnx_fixtures.py)."""

from tests.onnx_fixtures import onnx_path, onnx_static_path, parts  # noqa: F401
