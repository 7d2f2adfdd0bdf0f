"""Read and write the lunarnav metadata of an in-memory ONNX model (no torch)."""

from __future__ import annotations

import onnx

from lunarnav_ml import __version__
from lunarnav_ml.runtime import metadata as md


def read_metadata(model: onnx.ModelProto, source: str) -> md.ModelMetadata:
    """The lunarnav metadata of ``model`` (see :mod:`lunarnav_ml.runtime.metadata`).

    Raises:
        InputError: a foreign file, an incompatible format version or malformed fields.
    """
    return md.ModelMetadata.from_props({p.key: p.value for p in model.metadata_props}, source)


def set_metadata(model: onnx.ModelProto, meta: md.ModelMetadata) -> None:
    """Replace the model's lunarnav metadata with ``meta`` and set the producer fields."""
    keep = [p for p in model.metadata_props if not p.key.startswith(md.PREFIX)]
    del model.metadata_props[:]
    model.metadata_props.extend(keep)
    for key, value in meta.to_props().items():
        model.metadata_props.add(key=key, value=value)
    model.producer_name, model.producer_version = "lunarnav_ml", __version__
    model.doc_string = (f"lunarnav_ml detector '{meta.model}' ({meta.precision}); classes "
                        f"{', '.join(meta.class_names)}; see lunarnav.* metadata")
