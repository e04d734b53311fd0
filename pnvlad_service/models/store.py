"""Model checkpoints on disk: a directory with ``model.safetensors`` and ``model.json``.

``model.json``::

    {"format": "pnvlad-model", "version": 1, "model": <ModelConfig>,
     "weights_sha256": "<hex of model.safetensors>", "config_sha256": "<hex>", ...meta}

A training checkpoint is the same directory plus ``train_state.pt`` and ``train.json`` (written
by the trainer). Weights are never pickled: safetensors only.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import ValidationError

from pnvlad_service.errors import InputError
from pnvlad_service.fileio import atomic_directory, default_permissions, sha256_file
from pnvlad_service.models.config import ModelConfig, config_sha256

if TYPE_CHECKING:
    import torch

log = logging.getLogger(__name__)

FORMAT = "pnvlad-model"
VERSION = 1
WEIGHTS_FILE = "model.safetensors"
#: The weights exported for ONNX Runtime (``pnvlad model export``; models/onnx_encoder.py).
ONNX_FILE = "model.onnx"
CONFIG_FILE = "model.json"

__all__ = [
    "CONFIG_FILE",
    "WEIGHTS_FILE",
    "ModelIdentity",
    "config_sha256",
    "is_serving_only",
    "load_model",
    "model_identity",
    "read_model_json",
    "resolve_model_dir",
    "save_model",
    "weights_sha256",
]


def resolve_model_dir(path: str | Path) -> Path:
    """The model directory that ``path`` names: a model directory itself (``model.json`` +
    ``model.safetensors``, a training checkpoint included), a training run's output
    directory, whose final model is ``OUT/model``, or ``pretrained:NAME``, a model that ships
    with pnvlad (:func:`pnvlad_service.models.pretrained.resolve`: its files checked against
    the catalogue). Raises :class:`InputError` naming ``path``.
    """
    from pnvlad_service.models import pretrained

    if pretrained.is_pretrained(path):
        return _named(path)
    path = Path(path)
    if (path / CONFIG_FILE).is_file():
        return path
    if (path / "model" / CONFIG_FILE).is_file():
        return path / "model"
    if not path.exists():
        raise InputError("model directory not found" + pretrained.hint(path), source=path)
    if (path / "checkpoints").is_dir():
        raise InputError(
            "a training run without a final model (OUT/model): the run has not finished; "
            "pass one of its checkpoints, OUT/checkpoints/step-*",
            source=path,
        )
    raise InputError(
        f"not a model directory (no {CONFIG_FILE}) nor a training run (no model/{CONFIG_FILE})",
        source=path,
    )


def _named(directory: str | Path) -> Path:
    """``directory``, or the directory of the pretrained model ``pretrained:NAME`` names
    (checked against its catalogue), for the functions that read a model directory as given."""
    from pnvlad_service.models import pretrained

    if pretrained.is_pretrained(directory):
        return pretrained.resolve(directory)
    return Path(directory)


@dataclass(frozen=True)
class ModelIdentity:
    """What identifies a model: its directory, the sha256 of its weights file and of its
    configuration's canonical JSON, and the configuration itself (JSON-ready)."""

    checkpoint: str
    weights_sha256: str
    config_sha256: str
    config: dict[str, Any]

    def to_json(self) -> dict[str, Any]:
        """The four fields as a JSON object (``config`` copied)."""
        return asdict(self)


def model_identity(directory: str | Path) -> ModelIdentity:
    """The :class:`ModelIdentity` of a model directory (or training run, see
    :func:`resolve_model_dir`)."""
    directory = resolve_model_dir(directory)
    cfg, _ = read_model_json(directory)
    return ModelIdentity(
        checkpoint=str(directory.resolve()),
        weights_sha256=weights_sha256(directory),
        config_sha256=config_sha256(cfg),
        config=cfg.model_dump(mode="json"),
    )


def weights_sha256(directory: str | Path) -> str:
    """SHA-256 (hex) of the checkpoint's ``model.safetensors`` file bytes.

    A serving-only directory (``model.json`` and ``model.onnx``, the weights left out, as the
    server image ships the pretrained models) has the hash ``model.json`` records: the ONNX
    file's own record of the weights it was exported from is checked against it when it loads.
    """
    directory = _named(directory)
    path = directory / WEIGHTS_FILE
    if path.is_file():
        return sha256_file(path)
    recorded = _serving_only_sha256(directory)
    if recorded is not None:
        return recorded
    raise InputError(f"no {WEIGHTS_FILE} in this model directory", directory)


def is_serving_only(directory: str | Path) -> bool:
    """Whether ``directory`` holds ``model.onnx`` and ``model.json`` (recording the weights'
    SHA-256) but no ``model.safetensors``: it embeds with ONNX Runtime only."""
    return _serving_only_sha256(Path(directory)) is not None


def _serving_only_sha256(directory: Path) -> str | None:
    """The weights' SHA-256 that a serving-only ``directory``'s ``model.json`` records; None
    for any other directory."""
    if (directory / WEIGHTS_FILE).exists() or not (directory / ONNX_FILE).is_file():
        return None
    try:
        _, doc = read_model_json(directory)
    except InputError:
        return None
    recorded = doc.get("weights_sha256")
    return recorded if isinstance(recorded, str) else None


def write_model_files(
    directory: str | Path,
    model: torch.nn.Module,
    cfg: ModelConfig,
    meta: dict[str, Any] | None,
    *,
    state: dict[str, Any] | None = None,
) -> None:
    """Write ``model.safetensors`` and ``model.json`` into an existing (temporary) directory.

    For callers that build a larger directory atomically themselves (the trainer adds
    ``train_state.pt``; a pretrained model stores ``state``, the model's tensors some of them
    in float16, in place of ``model.state_dict()``); everyone else calls :func:`save_model`.
    :func:`load_model` restores the model's own dtypes.
    """
    from safetensors.torch import save_file

    directory = Path(directory)
    state = model.state_dict() if state is None else state
    state = {k: v.detach().to("cpu").contiguous() for k, v in state.items()}
    save_file(state, str(directory / WEIGHTS_FILE), metadata={"format": FORMAT})
    default_permissions(directory / WEIGHTS_FILE)  # save_file makes it 0600
    doc: dict[str, Any] = dict(meta or {})
    doc.update(
        {
            "format": FORMAT,
            "version": VERSION,
            "model": cfg.model_dump(mode="json"),
            "weights_sha256": sha256_file(directory / WEIGHTS_FILE),
            "config_sha256": config_sha256(cfg),
        }
    )
    (directory / CONFIG_FILE).write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")


def save_model(
    directory: str | Path,
    model: torch.nn.Module,
    cfg: ModelConfig,
    meta: dict[str, Any] | None = None,
    *,
    overwrite: bool = False,
) -> Path:
    """Save ``model``'s weights and ``cfg`` as a checkpoint directory, atomically.

    ``meta`` (JSON-serialisable) is merged into ``model.json`` (e.g. ``{"source": ...}``); the
    keys ``format``, ``version``, ``model``, ``weights_sha256`` and ``config_sha256`` are
    always ours. Raises ``FileExistsError`` if ``directory`` exists and not ``overwrite``.
    """
    directory = Path(directory)
    with atomic_directory(directory, overwrite=overwrite) as tmp:
        write_model_files(tmp, model, cfg, meta)
    log.info("saved model (%s) to %s", cfg.arch, directory)
    return directory


def read_model_json(directory: str | Path) -> tuple[ModelConfig, dict[str, Any]]:
    """Read and check ``model.json``: returns (config, the whole document)."""
    directory = _named(directory)
    path = directory / CONFIG_FILE
    if not directory.is_dir():
        raise InputError(
            "not a model directory (expected model.json and model.safetensors)", directory
        )
    if not path.is_file():
        raise InputError(f"no {CONFIG_FILE} in this model directory", directory)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not valid JSON: {exc}", path) from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError(f"not a {FORMAT} file (missing or wrong 'format')", path)
    if doc.get("version") != VERSION:
        raise InputError(
            f"unsupported version {doc.get('version')!r} (this pnvlad reads version {VERSION})",
            path,
        )
    try:
        cfg = ModelConfig.model_validate(doc.get("model"))
    except ValidationError as exc:
        raise InputError(f"invalid model configuration: {exc}", path) from None
    return cfg, doc


def load_model(
    directory: str | Path, device: str | None = None
) -> tuple[torch.nn.Module, ModelConfig]:
    """Load a checkpoint directory: returns (model in eval mode, its config).

    Raises :class:`InputError` when a file is missing, the weights' SHA-256 differs from the one
    recorded in ``model.json``, or the tensors do not match the configuration (names the
    missing, unexpected and mis-shaped tensors).
    """
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    from pnvlad_service.models.factory import build_model

    directory = _named(directory)
    cfg, doc = read_model_json(directory)
    wpath = directory / WEIGHTS_FILE
    if not wpath.is_file():
        why = f"no {WEIGHTS_FILE} in this model directory"
        if is_serving_only(directory):
            why += " (a serving-only directory: it embeds with ONNX Runtime, --runtime onnx)"
        raise InputError(why, directory)
    recorded = doc.get("weights_sha256")
    if recorded is not None and recorded != sha256_file(wpath):
        raise InputError(
            "weights do not match the SHA-256 recorded in model.json (file changed or corrupt)",
            wpath,
        )
    try:
        state = load_file(str(wpath), device="cpu")
    except (SafetensorError, OSError) as exc:
        raise InputError(f"cannot read safetensors file: {exc}", wpath) from None
    model = build_model(cfg)
    check_state_dict(model, state, wpath)
    model.load_state_dict(state, strict=True)  # copies into the model's dtypes: float16 -> 32
    model.eval()
    if device is not None:
        model.to(device)
    return model, cfg


def check_state_dict(model: torch.nn.Module, state: dict[str, Any], source: str | Path) -> None:
    """Raise :class:`InputError` listing missing, unexpected and mis-shaped tensors of ``state``
    against ``model.state_dict()``."""
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    shapes = sorted(
        f"{k}: file {tuple(state[k].shape)}, model {tuple(expected[k].shape)}"
        for k in set(expected) & set(state)
        if tuple(state[k].shape) != tuple(expected[k].shape)
    )
    if missing or unexpected or shapes:
        raise InputError(
            "weights do not fit the model: " + state_mismatch(missing, unexpected, shapes), source
        )


def state_mismatch(missing: list[str], unexpected: list[str], shapes: list[str]) -> str:
    """One line for a state dict that does not fit: the missing, unexpected and mis-shaped
    tensors, each group with its count, the groups that are empty left out."""
    parts = []
    if missing:
        parts.append(f"missing {len(missing)}: {', '.join(missing)}")
    if unexpected:
        parts.append(f"unexpected {len(unexpected)}: {', '.join(unexpected)}")
    if shapes:
        parts.append(f"shape mismatch {len(shapes)}: {'; '.join(shapes)}")
    return " | ".join(parts)
