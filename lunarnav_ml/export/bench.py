"""Latency of the detector per image: onnxruntime (fp32 / int8) and eager PyTorch.

Each measurement runs one image at a time (batch 1), after warm-up calls, and reports the
median and 90th percentile in milliseconds. End to end means what the rover pays per frame:
letterbox + network + decoding + NMS; ``network`` is the graph alone (for GFLOP/s).
"""

from __future__ import annotations

import json
import os
import re
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import onnxruntime as ort

from lunarnav_ml.errors import InputError
from lunarnav_ml.runtime import OnnxDetector
from lunarnav_ml.runtime import metadata as md
from lunarnav_ml.runtime.preprocess import prepare_batch
from lunarnav_ml.runtime.session import session_options

CLASS_NAMES = ("crater", "rock", "artifact")


@dataclass(frozen=True)
class LatencyStats:
    """Per-call wall time, ms."""

    median_ms: float
    p90_ms: float
    min_ms: float
    runs: int

    def row(self) -> str:
        return f"median {self.median_ms:8.1f} ms  p90 {self.p90_ms:8.1f} ms  (n={self.runs})"


def time_calls(fn: Callable[[], Any], runs: int = 10, warmup: int = 2) -> LatencyStats:
    """Call ``fn`` ``warmup`` times untimed, then ``runs`` times timed."""
    if runs < 1 or warmup < 0:
        raise ValueError(f"runs must be >= 1 and warmup >= 0, got {runs}, {warmup}")
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    arr = np.asarray(times)
    return LatencyStats(float(np.median(arr)), float(np.percentile(arr, 90)), float(arr.min()),
                        runs)


def synthetic_frame(size: int, seed: int = 0) -> np.ndarray:
    """A size x size uint8 RGB frame of smooth gray noise (a stand-in terrain texture)."""
    import cv2

    rng = np.random.default_rng(seed)
    gray = cv2.GaussianBlur(rng.random((size, size), dtype=np.float32), (0, 0), 3.0)
    gray = (gray - gray.min()) / max(float(np.ptp(gray)), 1e-6) * 255.0
    return np.repeat(gray.astype(np.uint8)[:, :, None], 3, axis=2)


def bench_onnx(path: str | os.PathLike, size: int, threads: int = 1, *, runs: int = 10,
               warmup: int = 2, conf_thres: float = 0.25, network_only: bool = False,
               frame_size: int | None = None) -> LatencyStats:
    """Latency of an exported model on onnxruntime at a size x size input.

    Args:
        path: lunarnav ONNX file (fp32 or int8).
        size: input side, px.
        threads: onnxruntime intra-op threads.
        conf_thres: score threshold of the end-to-end NMS (the operating point).
        network_only: time ``session.run`` on a prepared input only.
        frame_size: side of the camera frame, letterboxed to ``size`` inside the timed call
            (default ``size``: no resize), e.g. a 1024 px frame read at 512.
    """
    det = OnnxDetector(path, threads=threads, img_size=size)
    frame = synthetic_frame(frame_size or size)
    if network_only:
        batch, _ = det.preprocess([frame])
        return time_calls(lambda: det.forward(batch), runs, warmup)
    return time_calls(lambda: det.predict([frame], conf_thres=conf_thres), runs, warmup)


_SCOPE = re.compile(r"/model/(backbone|neck|head)/([^/]+)(/)?")


def stage_of(node: str) -> str:
    """The module a profiled node belongs to, from the scope in its name: ``backbone/stem``,
    ``neck/td3``, ``head/convs.0``; ``neck (joins)`` for a node directly in a part (its
    concatenations and resizes); ``other`` for the rest (the input's quantization, layout
    reorders named after no module, the box decoding)."""
    m = _SCOPE.search(node)
    if m is None:
        return "other"
    return f"{m.group(1)}/{m.group(2)}" if m.group(3) else f"{m.group(1)} (joins)"


def stage_times(path: str | os.PathLike, size: int, threads: int = 1, *, runs: int = 5,
                warmup: int = 1) -> tuple[dict[str, float], dict[str, float]]:
    """Kernel time per module and per operator of an exported model, from onnxruntime's
    profiler, network only, batch 1 at a size x size input.

    Returns:
        (ms per :func:`stage_of` group, ms per optimized operator type), each a mean per run;
        both sum to the kernel time of a run (the wall time less the executor's overhead).
    """
    if runs < 1 or warmup < 0:
        raise ValueError(f"runs must be >= 1 and warmup >= 0, got {runs}, {warmup}")
    det = OnnxDetector(path, threads=threads, img_size=size)
    batch, _ = det.preprocess([synthetic_frame(size)])
    with tempfile.TemporaryDirectory(prefix="lunarnav_profile_") as tmp:
        opts = session_options(threads)
        opts.enable_profiling = True
        opts.profile_file_prefix = str(Path(tmp) / "ort")
        det.session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
        for _ in range(warmup):
            det.forward(batch)
        for _ in range(runs):
            det.forward(batch)
        events = json.loads(Path(det.session.end_profiling()).read_text())
    # timestamps count from the session's start: the timed runs are the last ``runs`` runs
    run_starts = sorted(e["ts"] for e in events if e["name"] == "model_run")
    t0 = run_starts[warmup] if len(run_starts) > warmup else 0
    by_stage: Counter[str] = Counter()
    by_op: Counter[str] = Counter()
    for e in events:
        if e.get("cat") != "Node" or not e["name"].endswith("_kernel_time") or e["ts"] < t0:
            continue
        name = e["name"][: -len("_kernel_time")]
        by_stage[stage_of(name)] += e["dur"] / 1e3 / runs
        by_op[e.get("args", {}).get("op_name", "?")] += e["dur"] / 1e3 / runs
    return dict(by_stage), dict(by_op)


def bench_torch(parts: Any, size: int, threads: int = 1, *, runs: int = 10, warmup: int = 2,
                conf_thres: float = 0.25, network_only: bool = False) -> LatencyStats:
    """Latency of eager PyTorch (inference mode, float32, CPU) on the same frame.

    Args:
        parts: ``DetectorParts`` or a ``Detector`` (see :func:`export.onnx_export.load_parts`).
        Others as :func:`bench_onnx`; ``threads`` sets ``torch.set_num_threads``.
    """
    import torch

    from lunarnav_ml.export.onnx_export import load_parts
    from lunarnav_ml.models.decode import decode, postprocess

    p = load_parts(parts)
    model = p.model.float().cpu().eval()
    frame = synthetic_frame(size)

    def network(x: torch.Tensor) -> torch.Tensor:
        return decode(model(x), p.anchors, p.strides, p.scale_xy)

    def end_to_end() -> Any:
        batch, _ = prepare_batch([frame], (size, size))
        return postprocess(network(torch.from_numpy(batch)), conf_thres, 0.6)

    x = torch.from_numpy(prepare_batch([frame], (size, size))[0])
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        with torch.inference_mode():
            return time_calls((lambda: network(x)) if network_only else end_to_end, runs, warmup)
    finally:
        torch.set_num_threads(previous)


def conv_flops(path: str | os.PathLike, size: int) -> float:
    """Multiply-add FLOPs (2 per MAC) of the Conv nodes of an ONNX model at (1, 3, size, size).

    Output shapes come from one onnxruntime pass with every Conv output exposed (static shape
    inference cannot follow the channel splits of some presets). Works on fp32 and QDQ int8
    files. Conv layers are all but a fraction of a percent of this detector's arithmetic.
    """
    model = onnx.load(Path(path))
    convs = [n for n in model.graph.node if n.op_type == "Conv"]
    weights = _conv_weight_shapes(model)
    outputs = {o.name for o in model.graph.output}
    model.graph.output.extend(onnx.ValueInfoProto(name=n.output[0]) for n in convs
                              if n.output[0] not in outputs)
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    opts.log_severity_level = 3
    sess = ort.InferenceSession(model.SerializeToString(), opts,
                                providers=["CPUExecutionProvider"])
    feeds = {md.INPUT_NAME: np.zeros((1, 3, size, size), np.float32),
             md.CONF_NAME: np.array([0.5], np.float32), md.IOU_NAME: np.array([0.5], np.float32),
             md.MAX_PER_CLASS_NAME: np.array([1], np.int64)}
    feeds = {i.name: feeds[i.name] for i in sess.get_inputs()}
    shapes = sess.run([n.output[0] for n in convs], feeds)
    total = 0.0
    for node, out in zip(convs, shapes):
        if node.input[1] not in weights:
            raise InputError(f"{path}: weight of {node.name} is not a constant")
        total += 2.0 * float(out.size) * float(np.prod(weights[node.input[1]][1:]))
    return total


def _conv_weight_shapes(model: onnx.ModelProto) -> dict[str, list[int]]:
    """Shape of every constant weight, by the name a Conv reads it under (initializer or the
    output of the DequantizeLinear of a QDQ int8 weight)."""
    shapes = {i.name: list(i.dims) for i in model.graph.initializer}
    for node in model.graph.node:
        if node.op_type == "DequantizeLinear" and node.input[0] in shapes:
            shapes[node.output[0]] = shapes[node.input[0]]
    return shapes


def random_detector(preset: str, img_size: int = 512, seed: int = 0, calib_batches: int = 3
                    ) -> Any:
    """An untrained detector of a preset whose activations have a sane scale.

    A freshly built model's BatchNorm statistics (mean 0, variance 1) make eval-mode features
    vanish layer by layer; a few train-mode passes on noise images set them. Good for latency
    and export parity tests; carries no accuracy.

    Returns:
        ``DetectorParts`` (accepted by ``export_onnx`` and :func:`bench_torch`).
    """
    import torch

    from lunarnav_ml.export.onnx_export import DetectorParts
    from lunarnav_ml.models import build_model

    gen = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    model = build_model(preset, num_classes=len(CLASS_NAMES))
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.momentum = None  # cumulative average over the calibration passes
            m.reset_running_stats()
    model.train()
    side = min(img_size, 256)
    with torch.no_grad():
        for _ in range(calib_batches):
            model(torch.rand(2, 3, side, side, generator=gen))
    model.eval()
    return DetectorParts(model, model.anchors.clone(), model.strides, model.scale_xy,
                         (img_size, img_size), CLASS_NAMES, preset)
