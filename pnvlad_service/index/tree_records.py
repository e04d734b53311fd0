"""What a tree's runs recorded that a bundle built from them copies: the filter G their
entries went through, how their windows laid each scan, their UTM zone, and whether ``pnvlad
map align`` wrote the tree (their drives agree). Each is read from the runs' prepare records
(``data.run_folder``) and must agree across the runs indexed."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pnvlad_service.errors import InputError
from pnvlad_service.fileio import sha256_file

if TYPE_CHECKING:
    from pnvlad_service.data.tree import Submap

log = logging.getLogger(__name__)


def default_preprocess_config(layout: str = "test") -> dict[str, Any]:
    """The default filter G configuration as JSON (what raw scans go through): G with the
    single-scan range crop for keyframe maps, plain G for submaps."""
    from pnvlad_service.preprocess.filter_g import GConfig, scan_config

    return (scan_config() if layout == "keyframe" else GConfig()).model_dump(mode="json")


def _recorded_by_runs(
    root: Path, records: Sequence[Submap], read: Any
) -> tuple[dict[str, Any] | None, str | None]:
    """What ``read(run_dir, folder)`` finds in the prepare records of the runs indexed: the
    value the runs that record one agree on (``None`` where none does) and the first run that
    records another (``None`` where they all agree)."""
    found: dict[str, Any] | None = None
    folder = records[0].path.rsplit("/", 2)[1]
    for run in dict.fromkeys(r.path.rsplit("/", 2)[0] for r in records):
        value = read(root.joinpath(*run.split("/")), folder)
        if value is not None and found is not None and value != found:
            return found, run
        found = value if value is not None else found
    return found, None


def tree_preprocess_config(root: Path, records: Sequence[Submap]) -> dict[str, Any]:
    """The G that the records' map entries went through, as the tree's prepare records say
    (so that a raw query meets its own kind), else the layout's default. :class:`InputError`
    when the runs indexed record different settings."""
    from pnvlad_service.data.run_folder import recorded_g_config

    found, differs = _recorded_by_runs(root, records, recorded_g_config)
    if differs is not None:
        raise InputError(
            f"the runs indexed went through different filter G settings ({differs} differs); "
            "index them into separate bundles",
            root,
        )
    return found if found is not None else default_preprocess_config(records[0].kind)


def tree_accumulation(root: Path, records: Sequence[Submap]) -> dict[str, Any] | None:
    """How the runs' windows laid each scan (their prepare records), for accumulated queries
    to do the same; ``None`` where the tree recorded nothing (made elsewhere) or where the runs
    laid theirs differently (a warning: the bundle then cannot say how to lay a window)."""
    from pnvlad_service.data.run_folder import recorded_accumulation

    found, differs = _recorded_by_runs(root, records, recorded_accumulation)
    if differs is not None:
        log.warning(
            "the runs indexed laid their windows' scans differently (%s differs): the bundle "
            "records none, and accumulated queries keep their scans whole",
            differs,
        )
        return None
    return found


def tree_utm_zone(root: Path, records: Sequence[Submap], given: str | None = None) -> str:
    """The UTM zone of the records' coordinates: ``given`` (``--utm-zone``) or the one the
    runs' prepare records agree on; ``""`` where neither says. :class:`InputError` when the
    runs record different zones, or one other than ``given``, or a zone is malformed."""
    from pnvlad_service.data.run_folder import recorded_utm_zone
    from pnvlad_service.io.utm import normalize_zone

    zone = normalize_zone(given, "--utm-zone")
    found, differs = _recorded_by_runs(root, records, recorded_utm_zone)
    if differs is not None:
        raise InputError(
            f"run {differs} records another UTM zone than {found}: a map is in one zone",
            "utm_zone",
        )
    if zone and found and zone != found:
        raise InputError(f"{zone} given, but the runs were prepared in {found}", "--utm-zone")
    return zone or found or ""


#: What ``pnvlad map align`` writes into its tree (``mapping.align.REPORT`` and
#: ``mapping.relay.ALIGNED_POSES``; this stage may not import that one).
ALIGN_REPORT = "align_report.json"
ALIGNED_POSES = "aligned_poses.csv"


def tree_alignment(root: Path, records: Sequence[Submap]) -> str | None:
    """The sha256 of ``root``'s ``align_report.json`` when ``pnvlad map align`` wrote the tree
    and every run of ``records`` is of it (has its ``aligned_poses.csv``): the map's drives
    agree. ``None`` otherwise (a warning naming a run the alignment lacks)."""
    report = root / ALIGN_REPORT
    if not report.is_file():
        return None
    for run in dict.fromkeys(r.path.rsplit("/", 2)[0] for r in records):
        if not root.joinpath(*run.split("/"), ALIGNED_POSES).is_file():
            log.warning(
                "run %s has no %s: it was not aligned with the others, so the bundle is not "
                "recorded as aligned (priors register to one drive at a time)",
                run,
                ALIGNED_POSES,
            )
            return None
    return sha256_file(report)
