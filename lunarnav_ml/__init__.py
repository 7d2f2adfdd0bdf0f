"""lunarnav_ml: onboard lunar crater detection.

Pipeline (data flows one way): synth -> data -> models -> decode/NMS -> geometry (ellipse,
3D lift) -> eval / runtime.
"""

import os

# albumentations (>= 1.4) asks PyPI for a newer version on every import, waiting up to 2 s and
# warning when offline, as a rover or a lent GPU machine is. Off unless the user sets it.
os.environ.setdefault("NO_ALBUMENTATIONS_UPDATE", "1")

__version__ = "0.1.0"
