"""Submaps made elsewhere, in metres, imported as a benchmark run that verification can use.

A user's own submaps (from another mapping pipeline, not from ``pnvlad data prepare``) are
clouds in metres, one file a submap, with a CSV of their positions. Run through G and written
as the benchmark's files they can be searched, but a map needs more to verify an answer by
registration: where each submap's normalised points sit in metres. :func:`import_submaps`
writes, per submap, what G did (``centre``, ``scale``) and the submap's frame into the frame
sidecar (:mod:`.frames`), exactly as prepare does for the submaps it cuts, so that
``pnvlad index build`` stores the geometry and answers carry a metric pose::

    SRC/<timestamp>.<ext>     one submap in metres (any format io.readers reads), axes east,
                              north, up; origin at its CSV position (``origin="position"``) or
                              at UTM zero (``origin="utm"``: absolute coordinates)
    CSV                       timestamp,northing,easting (the benchmark's columns)
 -> OUT/<folder>/<timestamp>.bin, OUT/<csv name>, OUT/<csv stem>.frames.csv

The folder and CSV names are the layout's for ``kind`` (``test`` by default, the database a
bundle indexes); G's settings are recorded in ``OUT/.prepare-<folder>.json`` as prepare records
them, so that raw queries to the bundle go through the same G.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from pnvlad_service.data.drive import snap_m
from pnvlad_service.data.frames import SubmapFrame, frames_path, write_frames_csv
from pnvlad_service.data.run_folder import claim_folders
from pnvlad_service.data.tree import LAYOUTS, Kind, read_locations_csv, write_locations_csv
from pnvlad_service.errors import InputError
from pnvlad_service.io.readers import read_points
from pnvlad_service.io.submap import write_submap
from pnvlad_service.preprocess.filter_g import GConfig, apply_g

log = logging.getLogger(__name__)

Origin = Literal["position", "utm"]


@dataclass
class ImportResult:
    """What :func:`import_submaps` wrote: the folder, the CSV, and the submaps written and
    skipped (G could not make one: too few points left)."""

    folder: Path
    csv: Path
    written: int
    skipped: list[int]


def _source_file(src: Path, stamp: int) -> Path:
    hits = sorted(p for p in src.glob(f"{stamp}.*") if p.is_file())
    if not hits:
        raise InputError(f"no submap file {stamp}.* for this CSV row", src)
    if len(hits) > 1:
        raise InputError(f"several files for timestamp {stamp}: {[p.name for p in hits]}", src)
    return hits[0]


def import_submaps(
    src: str | Path,
    locations: str | Path,
    out_run_dir: str | Path,
    *,
    layout: str = "oxford",
    kind: Kind = "test",
    reader: str | None = None,
    origin: Origin = "position",
    height: float = 0.0,
    g_config: GConfig | None = None,
    seed: int = 0,
    overwrite: bool = False,
    progress: bool = True,
) -> ImportResult:
    """Import the metric submaps of ``src`` listed in ``locations`` into ``out_run_dir``.

    ``origin``: where the submaps' coordinates start: ``position`` (at the CSV row's
    northing/easting, ``height`` up) or ``utm`` (absolute UTM coordinates; each submap is moved
    to its CSV position in float64 before G). Submap ``k`` of the CSV uses G's ``seed`` + k.
    Every file is checked before anything is written (a missing file, a bad CSV:
    :class:`InputError` naming it); a submap G cannot make is skipped, logged and left out of
    the CSV. The CSV and its sidecar are written last, atomically.
    """
    from pnvlad_service.progress import tqdm

    src, out = Path(src), Path(out_run_dir)
    if layout not in LAYOUTS:
        raise InputError(f"unknown layout {layout!r} ({', '.join(LAYOUTS)})", "layout")
    if origin not in ("position", "utm"):
        raise InputError(f"must be position or utm, got {origin!r}", "origin")
    if not src.is_dir():
        raise InputError("not a folder of submaps", src)
    loc = read_locations_csv(locations)
    if len(loc) == 0:
        raise InputError("no rows", locations)
    files = [_source_file(src, int(t)) for t in loc.timestamp]
    cfg = g_config or GConfig()
    names = LAYOUTS[layout]
    folder, csv = out / names.folder(kind), out / names.csv(kind)
    manifest = {
        "format": "pnvlad-prepare",
        "version": 1,
        "drive": str(src),
        "kind": kind,
        "layout": layout,
        "imported": True,
        "origin": origin,
        "seed": seed,
        "g_config": cfg.model_dump(mode="json"),
    }
    claim_folders([(folder, csv)], [manifest], out, resume=False, overwrite=overwrite)
    rows, frames, skipped = [], [], []
    bar = tqdm(total=len(files), desc=f"import {out.name}", unit="submap", disable=not progress)
    for k, (path, (stamp, north, east)) in enumerate(zip(files, loc.rows(), strict=True)):
        position = snap_m(np.array([east, north, height]))
        pts = np.asarray(read_points(path, reader), dtype=np.float64)[:, :3]
        if origin == "utm":
            pts = pts - position
        try:
            g = apply_g(pts, cfg, seed=seed + k)
        except InputError as exc:
            log.warning("submap %d (%s) skipped: %s", stamp, path.name, exc.detail)
            skipped.append(stamp)
            bar.update()
            continue
        write_submap(folder / f"{stamp}.bin", g.points)
        frames.append(SubmapFrame(stamp, position, g.centre, g.scale, "enu"))
        rows.append((stamp, north, east))
        bar.update()
    bar.close()
    write_frames_csv(frames_path(csv), frames)
    write_locations_csv(csv, rows)
    log.info("%s: %d submaps imported (%d skipped) -> %s", folder, len(rows), len(skipped), csv)
    return ImportResult(folder, csv, len(rows), skipped)
