"""Export a checkpoint to ONNX (and int8): ``python export/export_onnx.py --checkpoint ... --out ...``.

Thin entry point: the same as ``lunarnav export``; see ``lunarnav_ml/export/cli.py``.
"""

import sys

from lunarnav_ml.export.cli import main

if __name__ == "__main__":
    sys.exit(main(["export", *sys.argv[1:]]))
