"""What a drive's report knows of the map it was localised on: the entries' positions (to
draw them, and to tell a scan off the map) and, for a ``pnvlad synth`` tree, the entries' true
poses (:func:`map_truth`: how far a pose is from where the map itself would put the scan)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pnvlad_service.errors import InputError


@dataclass(frozen=True)
class DriveMap:
    """A bundle's ``positions`` (:class:`~..prior.MapPositions`), ``ne`` float [M, 2] (northing,
    easting of its entries, UTM metres) and ``truth`` (:func:`map_truth`, or ``None``) of the
    bundle at ``bundle``."""

    bundle: Path
    positions: Any
    ne: np.ndarray
    truth: dict[str, tuple[np.ndarray, np.ndarray]] | None

    @classmethod
    def load(cls, bundle: str | Path, with_truth: bool = False) -> DriveMap:
        """The map of the bundle at ``bundle``; its own truth only ``with_truth``."""
        from pnvlad_service.index.bundle import METADATA_FILE, Metadata
        from pnvlad_service.localization.verify.prior import MapPositions

        bundle = Path(bundle)
        meta = Metadata.load(bundle / METADATA_FILE)
        return cls(
            bundle=bundle,
            positions=MapPositions.of_metadata(meta),
            ne=np.c_[meta.northing, meta.easting],
            truth=map_truth(bundle) if with_truth else None,
        )

    def record(self) -> Any:
        """The manifest's ``map`` entry: how the map's windows laid each scan."""
        from pnvlad_service.index.manifest import Manifest

        return Manifest.read(self.bundle).map_record.to_json()


def map_truth(bundle: str | Path) -> dict[str, tuple[np.ndarray, np.ndarray]] | None:
    """``submap_id`` -> (its pose on the map, its true pose), both float64 [4, 4] local frame ->
    UTM, for every entry of the bundle at ``bundle`` whose tree (the manifest's ``indexed``
    roots) is here and records true poses (``pnvlad synth`` trees); ``None`` when none does."""
    from pnvlad_service.data.tree import BenchmarkTree
    from pnvlad_service.index.bundle import METADATA_FILE, Metadata
    from pnvlad_service.index.manifest import Manifest

    bundle = Path(bundle)
    manifest = Manifest.read(bundle)
    meta = Metadata.load(bundle / METADATA_FILE)
    frames: dict[str, Any] = {}
    for entry in manifest.indexed:
        root = Path(str(entry.get("root", "")))
        if not root.is_dir():
            continue
        try:
            frames.update(BenchmarkTree(root).frames_by_path())
        except InputError:
            continue
    out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    roots = [Path(str(e.get("root", ""))) for e in manifest.indexed]
    for sid, rel in zip(meta.submap_id, meta.path, strict=True):
        for root in roots:
            f = frames.get(str((root / str(rel)).resolve()))
            if f is not None and f.true_pose is not None:
                out[str(sid)] = (f.map_pose, f.true_pose)
                break
    return out or None
