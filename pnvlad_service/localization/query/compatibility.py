"""The compatibility check: a bundle is loaded only with the model whose weights built it
(:func:`checked_model`; :meth:`~.localizer.Localizer.load` runs it, and ``pnvlad serve``
before it starts)."""

from __future__ import annotations

from pathlib import Path

from pnvlad_service.errors import InputError
from pnvlad_service.index.manifest import Manifest
from pnvlad_service.models.store import ModelIdentity, model_identity


def checked_model(index: str | Path, model: str | Path | None = None) -> ModelIdentity:
    """The model to load with the bundle at ``index``: ``model`` (a model directory or a
    training run), else the one the bundle records. :class:`InputError` naming both files when
    the bundle was built with other weights (``Manifest.check_model``)."""
    manifest = Manifest.read(index)
    if model is None:
        model = manifest.model.checkpoint
        if not model:
            raise InputError(
                "the bundle records no model; pass one (-m/--model, or PNVLAD_CHECKPOINT)", index
            )
    identity = model_identity(model)
    manifest.check_model(identity)
    return identity
