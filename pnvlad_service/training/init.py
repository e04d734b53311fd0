"""The weights a training run starts from (``pnvlad train --init MODEL``): fine-tuning a model
on a map of one's own instead of training from random weights.

``MODEL`` is any of

- ``pretrained:NAME``, a model that ships with pnvlad (its files checked against the
  catalogue), a model directory (``model.json`` + ``model.safetensors``, a training
  checkpoint ``OUT/checkpoints/step-N`` included) or a training run (its final ``OUT/model``):
  the weights' SHA-256 checked against the one ``model.json`` records;
- a weights file: ``.safetensors``, or ``.pt``/``.pth`` holding a state dict (read with
  ``torch.load(weights_only=True)``: tensors only, never a pickled object).

The run's own config (``-c``, ``--set``) builds the model; the weights must fit it tensor for
tensor (:func:`initial_weights`): a config that does not match them (another architecture, other
widths, another descriptor size) is an :class:`InputError` naming the first layer that differs.
Where the model directory's own config differs in other fields, they are logged.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pnvlad_service.errors import InputError

if TYPE_CHECKING:
    import torch

    from pnvlad_service.models.config import ModelConfig

log = logging.getLogger(__name__)

#: Suffixes of weights files read as torch state dicts (weights only).
TORCH_SUFFIXES = (".pt", ".pth")


def read_init_weights(ref: str | Path) -> tuple[dict[str, Any], dict[str, Any] | None, str]:
    """``(state dict, its model.json config or None, a name for messages)`` of ``ref``
    (module docstring). :class:`InputError` naming ``--init`` or the file."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    from pnvlad_service.fileio import sha256_file
    from pnvlad_service.models.store import WEIGHTS_FILE, read_model_json, resolve_model_dir

    path = Path(ref)
    if path.is_file() and path.suffix in TORCH_SUFFIXES:
        return _torch_state(path), None, str(path)
    if path.is_file() and path.suffix != ".safetensors":
        raise InputError(
            "expected a model directory, a training run, pretrained:NAME or a .safetensors, "
            ".pt or .pth file of weights",
            "--init",
        )
    config = None
    if not path.is_file():
        directory = resolve_model_dir(ref)
        cfg, doc = read_model_json(directory)
        config = cfg.model_dump(mode="json")
        path = directory / WEIGHTS_FILE
        if not path.is_file():
            raise InputError(f"no {WEIGHTS_FILE} in this model directory", directory)
        recorded = doc.get("weights_sha256")
        if recorded is not None and recorded != sha256_file(path):
            raise InputError("weights do not match the SHA-256 recorded in model.json", path)
    try:
        return load_file(str(path), device="cpu"), config, str(ref)
    except (SafetensorError, OSError) as exc:
        raise InputError(f"cannot read safetensors file: {exc}", path) from None


def _torch_state(path: Path) -> dict[str, Any]:
    """The state dict a ``.pt``/``.pth`` file holds (bare, or under ``state_dict`` or
    ``model_state_dict``), read with ``weights_only=True``."""
    import pickle

    import torch

    try:
        doc = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, OSError, EOFError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(f"not a weights-only torch file: {first}", path) from None
    if isinstance(doc, dict):
        for key in ("state_dict", "model_state_dict"):
            if isinstance(doc.get(key), dict):
                doc = doc[key]
                break
    if not isinstance(doc, dict) or not all(isinstance(v, torch.Tensor) for v in doc.values()):
        raise InputError("holds no state dict (name -> tensor)", path)
    return doc


def mismatch(model: torch.nn.Module, state: dict[str, Any]) -> str | None:
    """The first way ``state`` does not fit ``model`` (a layer's shape, a missing or an
    unexpected tensor, and how many others), or ``None`` when it fits exactly."""
    expected = model.state_dict()
    shapes = [
        f"layer {k}: weights {tuple(state[k].shape)}, this config {tuple(v.shape)}"
        for k, v in expected.items()
        if k in state and tuple(state[k].shape) != tuple(v.shape)
    ]
    missing = [f"layer {k}: in this config, not in the weights" for k in expected if k not in state]
    unexpected = [
        f"layer {k}: in the weights, not in this config" for k in state if k not in expected
    ]
    problems = shapes + missing + unexpected
    if not problems:
        return None
    more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
    return problems[0] + more


def initial_weights(cfg: ModelConfig, ref: str | Path) -> dict[str, Any]:
    """The state dict of ``ref`` (module docstring), checked against a model built from
    ``cfg``: :class:`InputError` naming ``--init`` and the first layer that does not fit
    (:func:`mismatch`). Read before a run loads its data, so a wrong one fails at once."""
    from pnvlad_service.models.factory import build_model

    state, config, name = read_init_weights(ref)
    problem = mismatch(build_model(cfg), state)
    if problem is not None:
        raise InputError(
            f"{name} does not fit the model of this run's config: {problem}; give the "
            "config it was trained with (-c, --set model.*)",
            "--init",
        )
    if config is not None:
        ours = cfg.model_dump(mode="json")
        differ = sorted(k for k in ours.keys() | config.keys() if ours.get(k) != config.get(k))
        if differ:
            log.warning("--init %s: its config differs in %s (the run's apply)", name, differ)
    log.info("initial weights from %s", name)
    return state
