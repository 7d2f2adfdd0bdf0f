"""Open a lunarnav ONNX file in onnxruntime and check that it is one this runtime can run."""

from __future__ import annotations

import os
from pathlib import Path

import onnxruntime as ort
from onnxruntime.capi import onnxruntime_pybind11_state as ort_errors

from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.runtime import metadata as md

# What InferenceSession raises for a file it cannot parse or build a graph from.
ORT_LOAD_ERRORS = (ort_errors.Fail, ort_errors.InvalidProtobuf, ort_errors.InvalidGraph,
                   ort_errors.InvalidArgument, ort_errors.NotImplemented,
                   ort_errors.RuntimeException)


def session_options(threads: int) -> ort.SessionOptions:
    """onnxruntime options for ``threads`` intra-op threads, sequential execution."""
    if not isinstance(threads, int) or threads < 1:
        raise ConfigError(f"threads: expected a positive integer, got {threads!r}")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.log_severity_level = 3  # errors only: no warnings on stderr onboard
    return opts


def load_session(path: Path, threads: int, what: str, writer: str) -> ort.InferenceSession:
    """``path`` on the CPU execution provider with :func:`session_options`.

    Raises:
        InputError: "``path``: ``what`` not found", or not a loadable model (naming ``writer``,
            the command that writes such files).
        ConfigError: ``threads`` is not a positive integer.
    """
    opts = session_options(threads)
    if not path.is_file():
        raise InputError(f"{path}: {what} not found")
    try:
        return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
    except ORT_LOAD_ERRORS as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise InputError(f"{path}: not a loadable ONNX model (truncated, corrupt or not ONNX; "
                         f"expected a file written by {writer}): {first}") from None


def load_tool_session(path: Path, threads: int, kind: str, what: str, writer: str
                      ) -> tuple[ort.InferenceSession, dict[str, str]]:
    """:func:`load_session` of a geometry tool's file (a refiner), checked to carry
    ``lunarnav.kind`` = ``kind``; the session and the file's metadata.

    Raises:
        InputError: as :func:`load_session`, or "``path``: not a ``what``" for another kind.
    """
    session = load_session(path, threads, what, writer)
    props = session.get_modelmeta().custom_metadata_map
    if props.get("lunarnav.kind") != kind:
        raise InputError(f"{path}: not a {what} (metadata lunarnav.kind is "
                         f"{props.get('lunarnav.kind')!r}, expected {kind!r}; write one with "
                         f"{writer})")
    return session, props


def open_session(path: str | os.PathLike, threads: int = 1
                 ) -> tuple[ort.InferenceSession, md.ModelMetadata]:
    """Load ``path`` on the CPU execution provider and read its lunarnav metadata.

    Raises:
        InputError: missing file; a truncated, corrupt or non-ONNX file; a foreign ONNX file
            (no lunarnav metadata); an incompatible format version; inputs/outputs other than
            the ones the exporter writes.
        ConfigError: ``threads`` is not a positive integer.
    """
    path = Path(path)
    session = load_session(path, threads, "ONNX file", "`lunarnav export`")
    meta = md.ModelMetadata.from_props(session.get_modelmeta().custom_metadata_map, str(path))
    check_io(session, meta, path)
    return session, meta


def check_io(session: ort.InferenceSession, meta: md.ModelMetadata, path: Path) -> None:
    """Check the graph's input and outputs against the exporter's layout (format version 1).

    Raises:
        InputError: naming the input or output that differs and what was expected.
    """
    inputs = {i.name: i for i in session.get_inputs()}
    image = inputs.get(md.INPUT_NAME)
    if image is None or len(image.shape) != 4 or image.shape[1] != 3:
        got = [(i.name, i.shape) for i in session.get_inputs()]
        raise InputError(f"{path}: expected input '{md.INPUT_NAME}' of shape (B, 3, H, W), "
                         f"got {got}")
    outputs = {o.name: o for o in session.get_outputs()}
    decoded = outputs.get(md.DECODED_NAME)
    width = decoded.shape[-1] if decoded is not None and decoded.shape else None
    if width != 5 + meta.num_classes:
        if isinstance(width, int) and width > 5:  # a graph that scores another class count
            n = meta.num_classes
            raise InputError(f"{path}: metadata {md.PREFIX}class_names names {n} class"
                             f"{'es' if n != 1 else ''} but output '{md.DECODED_NAME}' scores "
                             f"{width - 5}")
        raise InputError(f"{path}: expected output '{md.DECODED_NAME}' of shape (B, N, "
                         f"{5 + meta.num_classes}) for {meta.num_classes} classes, got "
                         f"{[(o.name, o.shape) for o in session.get_outputs()]}")
    if meta.nms_in_graph:
        missing = [n for n in (*md.NMS_OUTPUTS,) if n not in outputs]
        missing += [n for n in (md.CONF_NAME, md.IOU_NAME, md.MAX_PER_CLASS_NAME)
                    if n not in inputs]
        if missing:
            raise InputError(f"{path}: metadata says NMS is in the graph but {missing} "
                             f"are not among its inputs/outputs")
