"""The strict protocol of the replay on aligned maps: a held-out run's map aligned without it.

``pnvlad map align`` over all five runs of an area lets the held-out run's own fixes and scans
shape the map it is then followed on. :func:`aligned_without` makes, for one held-out run, a
tree of links to the area's other recorded runs (nothing copied, the recorded tree only read)
and aligns it with the documented command, ``pnvlad map align TREE -o ALIGNED``; the aligned
tree is kept and reused (``align_report.json`` marks it whole). The held-out drive itself is
cast again from the recorded tree's ``synth.json``: its GNSS/INS poses are the odometry, the
simulator's truth the truth, nothing of the alignment in it.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from pathlib import Path

log = logging.getLogger(__name__)

#: The files beside a tree's runs that the aligned tree carries (``synth.json`` casts drives
#: again; the splits and regions are copied as they are).
PLAIN_FILES = ("synth.json", "splits.json", "splits_keyframes.json")


def linked_tree(root: Path, dest: Path, area: str, runs: list[str]) -> Path:
    """``dest``: a tree holding ``area``'s ``runs`` of the tree at ``root`` as symbolic links
    (and links to its plain files), made again from nothing each time."""
    import shutil

    if dest.exists():
        shutil.rmtree(dest)
    (dest / area).mkdir(parents=True)
    for name in PLAIN_FILES:
        if (root / name).is_file():
            os.symlink((root / name).resolve(), dest / name)
    for p in (root / area).iterdir():
        if p.is_file():
            os.symlink(p.resolve(), dest / area / p.name)
    for run in runs:
        os.symlink((root / area / run).resolve(), dest / area / run, target_is_directory=True)
    return dest


def aligned_without(
    root: Path,
    work: Path,
    area: str,
    held_out: str,
    invoke: Callable[[list[str], str], object],
) -> tuple[Path, float | None]:
    """The tree of ``area``'s runs of ``root`` but ``held_out``, aligned by ``pnvlad map align``
    (run through ``invoke``), under ``work/aligned/AREA/HELD_OUT``; and the seconds the
    alignment took (``None`` when an earlier one was reused)."""
    from pnvlad_service.data.tree import BenchmarkTree

    aligned = work / "aligned" / area / held_out
    if (aligned / "align_report.json").is_file():
        return aligned, None
    others = [r for r in BenchmarkTree(root).runs(area) if r != held_out]
    if held_out not in BenchmarkTree(root).runs(area) or len(others) < 2:
        raise SystemExit(f"{area}/{held_out}: not a run of an area with others in {root}")
    links = linked_tree(root, work / "recorded" / area / held_out, area, others)
    log.info("aligning %s without %s (%d runs)", area, held_out, len(others))
    t0 = time.perf_counter()
    invoke(["map", "align", str(links), "-o", str(aligned), "--overwrite"],
           f"aligning {area} without {held_out}")  # fmt: skip
    return aligned, time.perf_counter() - t0
