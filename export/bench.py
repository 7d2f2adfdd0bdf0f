"""Per-image latency of ONNX models / a checkpoint: ``python export/bench.py --onnx m.onnx``.

Thin entry point: the same as ``lunarnav bench``; see ``lunarnav_ml/export/cli.py``.
"""

import sys

from lunarnav_ml.export.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", *sys.argv[1:]]))
