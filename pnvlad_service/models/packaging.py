"""``pnvlad model package``: a trained model directory added to the pretrained catalogue.

The model is copied into the catalogue's folder under its name (``model.json``,
``model.safetensors`` and, unless ``onnx=False``, ``model.onnx`` exported from the stored
weights), its weight matrices stored as float16 with ``float16=True`` (:func:`half_state`),
checked against the original float32 model on the seeded check clouds (and any given real
clouds), held to the size limits (:data:`~.pretrained.MAX_MODEL_BYTES`,
:data:`~.pretrained.MAX_TOTAL_BYTES`), and only then committed: the directory is built under a
temporary name and renamed, the catalogue rewritten atomically with the files' SHA-256 and
sizes. Needs torch (and onnx for ``model.onnx``).
"""

from __future__ import annotations

import datetime as _dt
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from pnvlad_service.errors import InputError
from pnvlad_service.fileio import atomic_directory, atomic_write_text, sha256_file
from pnvlad_service.models import pretrained, store
from pnvlad_service.models.config import ModelConfig
from pnvlad_service.models.pretrained import Catalogue, Entry, FileRecord

log = logging.getLogger(__name__)

#: The smallest cosine a stored model's descriptor may keep against the original's.
MIN_COSINE = 0.999
#: Seeded check clouds of the comparison (``onnx_encoder.check_clouds``).
CHECK_SEED = 20261205
CHECK_CLOUDS = 64


@dataclass(frozen=True)
class Fidelity:
    """The stored model's descriptors against the original's on the same clouds: the smallest
    and mean cosine, and, over the real clouds when some were given (places of a map, where a
    nearest neighbour means something; else over the seeded ones), the share of clouds whose
    nearest other cloud is the same for both."""

    clouds: int
    min_cosine: float
    mean_cosine: float
    top1_agreement: float

    def to_json(self) -> dict[str, Any]:
        """Rounded for the catalogue."""
        return {
            "clouds": self.clouds,
            "min_cosine": round(self.min_cosine, 7),
            "mean_cosine": round(self.mean_cosine, 7),
            "top1_agreement": round(self.top1_agreement, 4),
        }


def half_state(model: Any) -> dict[str, Any]:
    """``model``'s state with every floating tensor of two or more dimensions (weight matrices,
    convolution kernels: nearly all the bytes) in float16 when its values fit float16's range;
    vectors (biases, batch-norm statistics) and anything else keep their dtype."""
    import torch

    limit = float(torch.finfo(torch.float16).max)
    out = {}
    for k, v in model.state_dict().items():
        fits = v.is_floating_point() and v.dim() >= 2 and bool(v.abs().max() <= limit)
        out[k] = v.half() if fits else v
    return out


def fidelity(original: Any, stored: Any, cfg: Any, points: np.ndarray | None = None) -> Fidelity:
    """:class:`Fidelity` of the model ``stored`` against ``original`` (both torch modules of
    ``cfg``) on the seeded check clouds and ``points`` float [M, N, 3] when given."""
    import torch

    from pnvlad_service.models.inference import Encoder
    from pnvlad_service.models.onnx_encoder import check_clouds

    # The seeded clouds have the model's num_points, the submaps their own (4096 for a model
    # trained on 1024, as the index and the server embed them): each set embedded apart.
    sets = [check_clouds(CHECK_SEED, CHECK_CLOUDS, cfg.num_points)]
    real = points is not None and len(points) > 1
    if real:
        sets.append(np.asarray(points, dtype=np.float32))
    descs = []
    for module in (original, stored):
        enc = Encoder(module, cfg, weights_sha256="fidelity", batch_size=16)
        try:
            with torch.inference_mode():
                descs.append(np.concatenate([enc.embed(c) for c in sets]))
        finally:
            enc.close()
    a, b = descs
    cos = np.sum(a * b, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    top = slice(CHECK_CLOUDS if real else 0, None)
    return Fidelity(len(a), float(cos.min()), float(cos.mean()), _top1_agreement(a[top], b[top]))


def _top1_agreement(a: np.ndarray, b: np.ndarray) -> float:
    """Share of rows whose nearest other row (L2) is the same in ``a`` and in ``b``."""

    def nearest(d: np.ndarray) -> np.ndarray:
        dist = np.sum(d**2, 1)[:, None] + np.sum(d**2, 1)[None, :] - 2 * d @ d.T
        np.fill_diagonal(dist, np.inf)
        return np.argmin(dist, axis=1)

    return float(np.mean(nearest(a) == nearest(b)))


@dataclass(frozen=True)
class Card:
    """What the catalogue says of a model besides its files: kind (``submap`` / ``scan``), the
    command that trained it, its training data, its figures and the date."""

    kind: str = "submap"
    trained_with: str = ""
    data: str = ""
    figures: dict[str, Any] | None = None
    date: str = ""


def _with_entry(cat: Catalogue, entry: Entry) -> Catalogue:
    """The catalogue with ``entry`` added at its end, or in place of the one of its name (a
    replaced model keeps its place in ``pnvlad model list``)."""
    names = [e.name for e in cat.entries]
    if entry.name not in names:
        return Catalogue(cat.path, (*cat.entries, entry))
    at = names.index(entry.name)
    return Catalogue(cat.path, (*cat.entries[:at], entry, *cat.entries[at + 1 :]))


def package_model(
    source: str | Path,
    name: str,
    card: Card,
    *,
    float16: bool = True,
    onnx: bool = True,
    points: np.ndarray | None = None,
    catalogue: str | Path | None = None,
    overwrite: bool = False,
    embed_scales: tuple[float, ...] | None = None,
    max_model_bytes: int = pretrained.MAX_MODEL_BYTES,
    max_total_bytes: int = pretrained.MAX_TOTAL_BYTES,
) -> Entry:
    """Add the model directory (or training run) ``source`` to the catalogue (default: the
    package's, or ``$PNVLAD_PRETRAINED``) as ``name``; returns its entry. :class:`InputError`
    for a bad name or kind, a name already there (without ``overwrite``), a stored model whose
    descriptors fall below cosine :data:`MIN_COSINE` of the original's, or sizes over the
    limits; nothing is written then. ``embed_scales``: the packaged model's
    ``ModelConfig.embed_scales`` (None: the source's)."""
    if not pretrained.NAME_RE.match(name):
        raise InputError("use lower-case letters, digits and dashes (e.g. bev-benchmark)", "name")
    if card.kind not in pretrained.KINDS:
        raise InputError(f"must be one of {', '.join(pretrained.KINDS)}", "kind")
    cat = Catalogue.read(catalogue)
    others = tuple(e for e in cat.entries if e.name != name)
    if len(others) != len(cat.entries) and not overwrite:
        raise InputError("already in the catalogue (pass overwrite to replace it)", name)
    src = store.resolve_model_dir(source)
    original, cfg = store.load_model(src)
    cfg = _with_scales(cfg, embed_scales, src)
    source_sha = store.weights_sha256(src)
    target = cat.root / name
    # A directory under the name that the catalogue does not list is a leftover: replaced.
    with atomic_directory(target, overwrite=True) as tmp:
        meta = {
            "source": "pnvlad model package",
            "pretrained": name,
            "packaged_from_weights_sha256": source_sha,
        }
        state = half_state(original) if float16 else None
        store.write_model_files(tmp, original, cfg, meta, state=state)
        stored, _ = store.load_model(tmp)
        fid = fidelity(original, stored, cfg, points)
        if not fid.min_cosine >= MIN_COSINE:
            raise InputError(
                f"the stored weights' descriptors fall to cosine {fid.min_cosine:.6f} of the "
                f"original's (< {MIN_COSINE}); package without float16",
                src,
            )
        _carry_calibration(src, tmp, source_sha)
        checks = {"fidelity": fid.to_json()}
        if onnx:
            from pnvlad_service.models.onnx_export import export_onnx

            checks["onnx_min_cosine"] = round(export_onnx(tmp, float16=float16).min_cosine, 7)
        files = {
            p.name: FileRecord(sha256=sha256_file(p), bytes=p.stat().st_size)
            for p in sorted(tmp.iterdir())
            if p.is_file()
        }
        entry = Entry(
            name=name,
            kind=card.kind,
            encoder=cfg.arch,
            dir=name,
            dtype="float16" if float16 else "float32",
            files=files,
            trained_with=card.trained_with,
            data=card.data,
            figures=dict(card.figures or {}),
            date=card.date or _dt.date.today().isoformat(),
            extra={**checks, "packaged_from_weights_sha256": source_sha},
        )
        _check_sizes(entry, others, max_model_bytes, max_total_bytes)
    new = _with_entry(cat, entry)
    atomic_write_text(cat.path, json.dumps(new.to_json(), indent=2) + "\n")
    log.info("packaged %s as %s (%.1f MiB) in %s", src, name, entry.bytes / 2**20, cat.path)
    return entry


def _with_scales(cfg: ModelConfig, scales: tuple[float, ...] | None, src: Path) -> ModelConfig:
    """``cfg`` (of the model ``src``) with ``embed_scales`` set to ``scales`` (None: as it is),
    checked as the field is (:class:`InputError` naming the model and the field)."""
    if scales is None:
        return cfg
    try:
        return ModelConfig.model_validate({**cfg.model_dump(), "embed_scales": scales})
    except ValidationError as exc:
        msg = exc.errors()[0]["msg"].removeprefix("Value error, ")
        raise InputError(msg, src) from None


#: The verification threshold chosen for a model (``localization/calibration.py``).
CALIBRATION_FILE = "verification.json"


def _carry_calibration(src: Path, tmp: Path, source_sha: str) -> None:
    """Copy the source model's ``verification.json`` (``pnvlad eval --save-threshold``) into
    ``tmp``, recorded for the stored weights (their descriptors are the original's within
    :data:`MIN_COSINE`, so the threshold chosen on them holds) with the original weights'
    sha256 kept as ``calibrated_on_weights_sha256``; one chosen for other weights is left out
    with a warning."""
    path = src / CALIBRATION_FILE
    if not path.is_file():
        return
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"unreadable verification record: {exc}", path) from None
    if not isinstance(doc, dict) or doc.get("weights_sha256") != source_sha:
        log.warning("%s was chosen for other weights: not packaged", path)
        return
    doc["calibrated_on_weights_sha256"] = source_sha
    doc["weights_sha256"] = sha256_file(tmp / store.WEIGHTS_FILE)
    atomic_write_text(tmp / CALIBRATION_FILE, json.dumps(doc, indent=2) + "\n")


def _check_sizes(entry: Entry, others: tuple[Entry, ...], max_model: int, max_total: int) -> None:
    """:class:`InputError` when ``entry`` is over the per-model limit or all models together
    over the total."""
    mib = 2**20
    if entry.bytes > max_model:
        fix = "leave model.onnx out" if entry.dtype == "float16" else "store it as float16"
        raise InputError(
            f"{entry.bytes / mib:.1f} MiB, over the limit of {max_model / mib:.0f} MiB a "
            f"pretrained model ({fix})",
            entry.name,
        )
    total = entry.bytes + sum(e.bytes for e in others)
    if total > max_total:
        raise InputError(
            f"the pretrained models would hold {total / mib:.1f} MiB, over the limit of "
            f"{max_total / mib:.0f} MiB for all of them",
            entry.name,
        )
