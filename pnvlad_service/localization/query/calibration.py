"""The verification threshold chosen for a model, kept beside its weights.

``pnvlad eval --rerank K --save-threshold`` chooses the threshold on the training layout
(:func:`pnvlad_service.evaluation.rerank.calibrate`) and writes it to ``MODEL/verification.json``; a
:class:`~..localizer.Localizer` (``pnvlad serve``, ``pnvlad localize --index``) loading that model
takes it unless a threshold is given. The threshold belongs to the model, not to a map: the
descriptors decide which candidates are registered and so the confidences it is chosen on.

The record names the sha256 of the weights it was chosen with; a record of other weights (the
directory's model was replaced) is ignored with a warning, never applied.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from pnvlad_service.errors import InputError
from pnvlad_service.fileio import atomic_write_text

log = logging.getLogger(__name__)

CALIBRATION_FILE = "verification.json"
FORMAT = "pnvlad-verification"
VERSION = 1


@dataclass(frozen=True)
class Calibration:
    """A chosen threshold and what it was chosen on: the weights' sha256, the candidates
    registered a query (K), the target precision (percent), the calibration queries and the
    figures there at the threshold (``precision``, ``pose_precision``, ``coverage``)."""

    threshold: float
    weights_sha256: str
    candidates: int
    target_precision: float
    n_queries: int
    at_threshold: dict[str, float]

    def to_json(self) -> dict[str, Any]:
        return {"format": FORMAT, "version": VERSION, **asdict(self)}

    @classmethod
    def from_report(
        cls, calibration: dict[str, Any], weights_sha256: str, candidates: int
    ) -> Calibration:
        """The record of a ``rerank`` report's ``calibration`` section."""
        at = calibration["at_threshold"]
        keep = (
            "precision",
            "pose_precision",
            "coverage",
            "n_verified",
            "off_map_accept",
            "expected_precision",
        )
        return cls(
            threshold=float(calibration["threshold"]),
            weights_sha256=weights_sha256,
            candidates=int(candidates),
            target_precision=float(calibration["target_precision"]),
            n_queries=int(calibration["n_queries"]),
            at_threshold={k: float(at[k]) for k in keep if k in at},
        )


def write_calibration(model_dir: str | Path, calibration: Calibration) -> Path:
    """Write ``MODEL/verification.json`` atomically; its path."""
    path = Path(model_dir) / CALIBRATION_FILE
    atomic_write_text(path, json.dumps(calibration.to_json(), indent=2) + "\n")
    return path


def read_calibration(model_dir: str | Path, weights_sha256: str) -> Calibration | None:
    """The model's calibration, or None when it has none or the record is of other weights
    (logged). :class:`InputError` naming the file when it is malformed."""
    path = Path(model_dir) / CALIBRATION_FILE
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"unreadable verification record: {exc}", path) from exc
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError(f"not a verification record (format is not {FORMAT!r})", path)
    if doc.get("version") != VERSION:
        raise InputError(f"verification record version {doc.get('version')!r}, not {VERSION}", path)
    try:
        cal = Calibration(
            threshold=float(doc["threshold"]),
            weights_sha256=str(doc["weights_sha256"]),
            candidates=int(doc["candidates"]),
            target_precision=float(doc["target_precision"]),
            n_queries=int(doc["n_queries"]),
            at_threshold={str(k): float(v) for k, v in dict(doc["at_threshold"]).items()},
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"verification record: bad or missing field {exc}", path) from exc
    if not 0.0 <= cal.threshold <= 1.0:
        raise InputError(f"threshold must be in [0, 1], got {cal.threshold}", path)
    if cal.weights_sha256 != weights_sha256:
        log.warning(
            "%s was chosen for other weights (sha256 %s..., these are %s...): not used",
            path,
            cal.weights_sha256[:12],
            weights_sha256[:12],
        )
        return None
    return cal
