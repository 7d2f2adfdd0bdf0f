"""Atomic file output: write to a temporary name in the same folder, then rename.

A reader never sees a half-written file: either the old file (or none) or the complete new one.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from lunarnav_ml.errors import InputError

_UMASK = os.umask(0)
os.umask(_UMASK)


def check_destination(path: str | os.PathLike, folder: bool = False) -> Path:
    """Check that ``path`` can become a file (or, with ``folder``, a folder) before any work
    is done: it is not an existing entry of the other kind and no folder above it is a file.

    Raises:
        InputError: naming ``path`` and what is in the way.
    """
    path = Path(path)
    if folder and path.exists() and not path.is_dir():
        raise InputError(f"{path}: output folder is an existing file; give a folder path")
    if not folder and path.is_dir():
        raise InputError(f"{path}: output file is an existing folder; give a file path")
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise InputError(f"{path}: cannot write under {parent}, which is a file")
            break
    return path


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    Args:
        path: final destination.
        suffix: suffix of the temporary file (defaults to the destination's, so that writers
            that pick a format by extension, such as OpenCV, still work).
    """
    path = check_destination(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=suffix if suffix is not None else path.suffix,
        dir=path.parent,
    )
    os.close(fd)
    tmp_path = Path(tmp)
    os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the usual permissions
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    return write_bytes(path, text.encode("utf-8"))


def finite_or_none(x: float) -> float | None:
    """A finite number as a float, else None (JSON has no NaN or infinity)."""
    return float(x) if np.isfinite(x) else None


def write_json(path: str | os.PathLike, obj: Any, indent: int | None = 1) -> Path:
    """Write ``obj`` as JSON to ``path`` atomically (numpy scalars and arrays are converted)."""
    return write_text(path, json.dumps(obj, indent=indent, default=_json_default) + "\n")


def write_npy(path: str | os.PathLike, array: np.ndarray) -> Path:
    """Write a numpy array to ``path`` (.npy) atomically."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.save(f, array)
    return Path(path)


def write_npz(path: str | os.PathLike, **arrays: np.ndarray) -> Path:
    """Write compressed numpy arrays to ``path`` (.npz) atomically."""
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **arrays)
    return Path(path)


def write_image(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write an image with OpenCV (format from the extension) atomically.

    Args:
        image: HxW (gray) or HxWx3 (BGR) array, uint8 or uint16.
    """
    import cv2

    path = _check_image_writer(Path(path))
    with atomic_path(path) as tmp:  # checks the destination itself
        try:
            ok = cv2.imwrite(str(tmp), image)
        except cv2.error as err:  # OpenCV raises for some failures instead of returning False
            reason = str(err).strip().splitlines()[-1].strip()
            raise InputError(f"{path}: OpenCV could not write the image ({reason})") from None
        if not ok:
            raise InputError(f"{path}: OpenCV could not write the image")
    return path


def check_image_destination(path: str | os.PathLike) -> Path:
    """Check, before any work, that an image can be written to ``path``: OpenCV has a writer
    for its suffix and it is not a folder (:func:`check_destination`); ``InputError`` naming
    ``path`` otherwise."""
    return _check_image_writer(check_destination(path))


def _check_image_writer(path: Path) -> Path:
    """``InputError`` naming ``path`` when OpenCV has no writer for its suffix."""
    import cv2

    if not cv2.haveImageWriter(str(path)):
        raise InputError(f"{path}: cannot write an image with suffix {path.suffix or '(none)'!r}"
                         " (use .png or .jpg)")
    return path


def write_figure(path: str | os.PathLike, fig: Any, dpi: int = 110) -> Path:
    """Save a matplotlib figure atomically and close it."""
    import matplotlib.pyplot as plt

    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return path


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike) -> Iterator[Path]:
    """Build a folder under a temporary name beside ``path``; on success replace ``path``.

    ``InputError`` naming ``path``, before anything is built, when it is an existing file or
    lies under one (:func:`check_destination`).
    """
    path = check_destination(path, folder=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    try:
        yield tmp
        if path.exists():
            shutil.rmtree(path)
        os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise TypeError(f"cannot write {type(obj).__name__} as JSON")
