"""The folders a prepare call writes: claimed before the first submap, resumable after a crash.

Each layout folder of a run (``pointcloud_20m_10overlap/`` ...) has its parameters recorded in
``<run>/.prepare-<folder>.json`` and its frame rows journalled in
``<run>/.prepare-<folder>.frames.jsonl`` as they are written (:func:`recorded_frames` reads
them back for a resumed run). Claiming a folder either refuses (it already holds submaps
and neither resume nor overwrite is asked for; resume with other parameters), or makes it
ready: the old submaps removed (overwrite), the locations CSV removed (it is rewritten last, so
a CSV on disk always describes a finished run) and the parameters recorded.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from pnvlad_service.data.frames import SubmapFrame, frames_path, read_frames_csv, read_journal
from pnvlad_service.errors import InputError
from pnvlad_service.fileio import atomic_write_text

log = logging.getLogger(__name__)


def manifest_path(out: Path, folder: Path) -> Path:
    """Where the parameters of ``folder`` (a layout folder of run ``out``) are recorded."""
    return out / f".prepare-{folder.name}.json"


def journal_path(csv: Path, folder: Path) -> Path:
    """Where the frame rows of ``folder`` (whose locations CSV is ``csv``) are journalled as
    they are written, one JSON line each, so that a resumed run keeps them; the name starts
    with ``.prepare-`` like the folder's manifest."""
    return csv.with_name(f".prepare-{folder.name}.frames.jsonl")


def recorded_frames(csv: Path, folder: Path) -> list[SubmapFrame]:
    """The frame rows an earlier prepare call recorded for ``folder``: its finished sidecar
    (ignored with a warning when it cannot be read), then the journal of an interrupted run."""
    side = frames_path(csv)
    rows: list[SubmapFrame] = []
    if side.is_file():
        try:
            rows = read_frames_csv(side)
        except InputError as exc:
            log.warning("ignoring the old frame sidecar: %s", exc)
    if journal_path(csv, folder).is_file():
        rows += read_journal(journal_path(csv, folder))
    return rows


def claim_folders(
    targets: Sequence[tuple[Path, Path]],
    manifests: Sequence[dict[str, Any]],
    out: Path,
    *,
    resume: bool,
    overwrite: bool,
) -> None:
    """Claim every ``(folder, csv)`` of ``targets`` with its manifest: all are checked before
    any is touched, so nothing changes on disk when one of them refuses."""
    for check_only in (True, False):
        for (folder, csv), manifest in zip(targets, manifests, strict=True):
            claim_folder(
                folder,
                csv,
                manifest,
                out,
                resume=resume,
                overwrite=overwrite,
                check_only=check_only,
            )


def claim_folder(
    folder: Path,
    csv: Path,
    manifest: dict[str, Any],
    out: Path,
    *,
    resume: bool,
    overwrite: bool,
    check_only: bool = False,
) -> None:
    """Check (resume) or reset (overwrite) a layout folder and record the run's parameters.

    The parameters go to ``<out>/.prepare-<folder>.json``; ``resume`` refuses to continue a
    folder made with other parameters (:class:`InputError`), and without ``resume`` or
    ``overwrite`` a folder that holds submaps or a CSV is refused (``FileExistsError``).
    ``check_only`` refuses the same way but changes nothing.
    """
    record = manifest_path(out, folder)
    existing = sorted(folder.glob("*.bin")) if folder.is_dir() else []
    if resume:
        if record.is_file():
            try:
                old = json.loads(record.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                old = None
            if isinstance(old, dict) and old != manifest:
                diff = sorted(
                    k for k in manifest.keys() | old.keys() if old.get(k) != manifest.get(k)
                )
                raise InputError(
                    f"cannot resume: {folder} was prepared with other parameters "
                    f"({', '.join(diff)}); pass the same options or --overwrite",
                    record,
                )
        elif existing and not check_only:
            log.warning("%s: no record of the previous parameters; resuming anyway", folder)
    elif (existing or csv.exists()) and not overwrite:
        raise FileExistsError(
            f"{folder}: already holds {len(existing)} submaps or {csv.name} exists (pass "
            "--resume to finish an interrupted run or --overwrite to start again)"
        )
    if check_only:
        return
    if not resume:
        for f in existing:
            f.unlink()
    if csv.exists():  # rewritten at the end; until then no CSV describes the folder
        csv.unlink()
    frames_path(csv).unlink(missing_ok=True)  # its frame sidecar likewise
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_text(record, json.dumps(manifest, indent=2, sort_keys=True) + "\n")


def _prepare_record(run_dir: Path, folder: str) -> dict[str, Any] | None:
    """A layout folder's ``.prepare-<folder>.json`` as a dict; ``None`` where there is none.
    :class:`InputError` naming the record when it cannot be read."""
    record = manifest_path(Path(run_dir), Path(folder))
    if not record.is_file():
        return None
    try:
        doc = json.loads(record.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read the prepare record: {exc}", record) from None
    return doc if isinstance(doc, dict) else None


def recorded_g_config(run_dir: Path, folder: str) -> dict[str, Any] | None:
    """The filter G settings a prepare call recorded for a layout folder of a run (its
    ``.prepare-<folder>.json``), as JSON; ``None`` where none is recorded (trees from
    elsewhere). :class:`InputError` naming the record when it cannot be read."""
    doc = _prepare_record(run_dir, folder)
    g = doc.get("g_config") if doc is not None else None
    return dict(g) if isinstance(g, dict) else None


#: How prepare laid each scan into a window (its options), as an accumulated query must too.
ACCUMULATION_KEYS = ("max_points_per_scan", "max_range_m", "min_scan_spacing_m", "box_m")


def recorded_accumulation(run_dir: Path, folder: str) -> dict[str, Any] | None:
    """How the scans of a layout folder's windows were laid (:data:`ACCUMULATION_KEYS`, as
    its prepare record says); ``None`` where none is recorded. A window asked about must keep
    the same points a scan (``max_points_per_scan``): a window of whole scans is as far from
    the map's submaps as another place (docs/SCANS.md); and the same box (``box_m``, where the
    submaps were cut to one)."""
    doc = _prepare_record(run_dir, folder)
    if doc is None:
        return None
    return {k: doc.get(k) for k in ACCUMULATION_KEYS if doc.get(k) is not None}


def recorded_utm_zone(run_dir: Path, folder: str) -> str | None:
    """The UTM zone a prepare call recorded for a layout folder of a run (``--utm-zone``,
    canonical, :mod:`pnvlad_service.io.utm`); ``None`` where none is recorded.
    :class:`InputError` naming the record when it holds a malformed zone."""
    from pnvlad_service.io.utm import normalize_zone

    doc = _prepare_record(run_dir, folder)
    zone = doc.get("utm_zone") if doc is not None else None
    if not zone:
        return None
    return normalize_zone(str(zone), str(manifest_path(Path(run_dir), Path(folder))))
