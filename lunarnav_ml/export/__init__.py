"""ONNX export, int8 quantization and latency benchmarks of the detector."""
