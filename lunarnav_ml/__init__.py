"""lunarnav_ml: onboard lunar crater detection.

Pipeline (data flows one way): synth -> data -> models -> decode/NMS -> geometry (ellipse,
3D lift) -> eval / runtime.
"""

__version__ = "0.1.0"
