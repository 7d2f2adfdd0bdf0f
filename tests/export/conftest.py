"""ONNX fixtures shared with tests/runtime (tests/onnx_fixtures.py)."""

from tests.onnx_fixtures import (  # noqa: F401
    mish_parts,
    onnx_nms_path,
    onnx_path,
    onnx_static_path,
    parts,
)
