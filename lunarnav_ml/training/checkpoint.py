"""Reading and writing detector weights: Lightning ``.ckpt`` files and slim ``.pt`` files.

A slim file is ``{"format": SLIM_FORMAT, "config": {...}, "state_dict": {...}}`` with the EMA
weights and what is needed to rebuild the model (preset, classes, anchors, input size).
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import torch
from torch import nn

from lunarnav_ml.errors import ConfigError, InputError

SLIM_FORMAT = "lunarnav-detector-v1"
CONFIG_KEYS = ("preset", "num_classes", "class_names", "anchors", "img_size")


def read_checkpoint(path: str | Path) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """Model config and (EMA) weights from a ``.ckpt`` or slim ``.pt`` file.

    Returns:
        ``(config, state_dict)``; config holds ``CONFIG_KEYS``; state_dict keys are those of
        :class:`lunarnav_ml.models.YOLO`.
    """
    path = Path(path)
    ckpt = load_checkpoint_file(path)
    if isinstance(ckpt, dict) and ckpt.get("format") == SLIM_FORMAT:
        # weights stored in half precision come back as float32 (the model's dtype)
        return dict(ckpt["config"]), {k: v.float() if v.is_floating_point() else v
                                      for k, v in ckpt["state_dict"].items()}
    if not isinstance(ckpt, dict) or "state_dict" not in ckpt or "hyper_parameters" not in ckpt:
        raise InputError(f"{path}: neither a Lightning checkpoint nor a slim detector file")
    hp = ckpt["hyper_parameters"]
    config = {k: hp.get(k) for k in CONFIG_KEYS}
    return config, _model_weights(path, ckpt["state_dict"])


def load_checkpoint_file(path: str | Path) -> Any:
    """The object a checkpoint file holds; ``InputError`` when it is missing or unreadable."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: checkpoint not found")
    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:
        raise InputError(f"{path}: not a readable checkpoint ({err})") from err


def _model_weights(path: Path, state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    for prefix in ("ema.module.", "model."):
        weights = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
        if weights:
            return weights
    raise InputError(f"{path}: the checkpoint holds no detector weights")


def load_weights(model: nn.Module, path: str | Path, preset: str | None = None) -> None:
    """Initialise ``model`` from a checkpoint (fine-tuning); shapes must match.

    Args:
        preset: the model's preset; when the checkpoint was trained as another one with the
            same tensors (``small`` into ``small-relu``), a warning says so: the weights load,
            but the network they meet computes something else until fine-tuned.

    Raises:
        InputError: the checkpoint's tensors do not fit the model (other preset or classes).
    """
    config, state = read_checkpoint(path)
    own = model.state_dict()
    bad = [k for k, v in state.items() if k not in own or own[k].shape != v.shape]
    missing = [k for k in own if k not in state]
    if bad or missing:
        raise InputError(f"{path}: weights do not fit this model ({len(bad)} mismatched, "
                         f"{len(missing)} missing, e.g. {(bad or missing)[0]}); same preset "
                         "and num_classes are needed")
    if preset is not None and config.get("preset") not in (None, preset):
        warnings.warn(f"{path}: weights of preset {config['preset']!r} start a {preset!r} model "
                      "(same tensors, other activations)", stacklevel=2)
    model.load_state_dict(state)


def reanchor(model: nn.Module, anchors: Any) -> list[tuple[int, int]]:
    """Give a trained ``model`` new ``anchors`` and move each changed anchor's ``tw`` and ``th``
    biases by log(old / new), so that its boxes, ``anchor x exp(t)``, start where they were
    (:mod:`lunarnav_ml.models.decode`); training then assigns it the boxes of its new shape.

    ``anchors`` is :math:`(L, A', 2)` px with ``A' >= A``, the model's anchors per level. Slots
    past ``A`` are added: each one's prediction channels (weights and biases) are copied from
    the level's old anchor nearest to it in log width and log height, its size biases moved
    the same way, so that it starts as a copy of that anchor's boxes (duplicates that NMS
    removes) and takes no shape away from the others. Returns the changed or added
    ``(level, anchor)`` slots.

    Raises:
        ConfigError: ``anchors`` has another number of levels, fewer anchors per level than the
            model, or sizes that are not all positive and finite.
    """
    old = model.anchors.detach().clone()
    try:
        new = torch.as_tensor(anchors, dtype=old.dtype, device=old.device)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"reanchor: expected (levels, anchors, 2) sizes in px: {err}") from None
    levels, count = old.shape[:2]
    if (new.ndim != 3 or new.shape[0] != levels or new.shape[1] < count or new.shape[2] != 2
            or not (torch.isfinite(new).all() and (new > 0).all())):
        raise ConfigError(f"reanchor: expected ({levels}, >= {count}, 2) positive sizes in px "
                          f"(the model's anchors: {tuple(old.shape)}), got "
                          f"{tuple(new.shape)} {new.tolist()}")
    # each slot's source: itself, or for an added slot the level's nearest old anchor in log
    # width and log height
    distance = (old.log()[:, None] - new.log()[:, count:, None]).square().sum(-1)  # L, A'-A, A
    sources = [list(range(count)) + distance[level].argmin(-1).tolist()
               for level in range(levels)]
    if new.shape[1] > count:
        model.head.add_anchors([s[count:] for s in sources])
    per = model.head.num_outputs
    changed = []
    with torch.no_grad():
        for level, pred in enumerate(model.head.preds):
            for a, src in enumerate(sources[level]):
                if a < count and torch.equal(new[level, a], old[level, a]):
                    continue
                shift = torch.log(old[level, src] / new[level, a])
                pred.bias[a * per + 2: a * per + 4] += shift.to(pred.bias.dtype)
                changed.append((level, a))
        model.anchors = new.clone()  # the buffer replaced: its shape may have grown
    return changed


def save_slim(path: str | Path, config: dict[str, Any], model: nn.Module,
              half: bool = False) -> Path:
    """Write a slim weights file (``config`` plus ``model``'s state dict).

    Args:
        half: store floating tensors in float16 (half the size; read back as float32).
    """
    from lunarnav_ml.utils.atomic import atomic_path

    path = Path(path)
    state = {k: (v.half() if half and v.is_floating_point() else v).detach().cpu().clone()
             for k, v in model.state_dict().items()}
    with atomic_path(path) as tmp:
        torch.save({"format": SLIM_FORMAT, "config": config, "state_dict": state}, tmp)
    return path
