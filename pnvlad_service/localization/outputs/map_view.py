"""The map drawn under a drive (:class:`~.step.MapView`) from an index bundle: its entries'
origins and a downsampled cloud of their points, laid together in UTM."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pnvlad_service.localization.outputs.step import MapView

#: The most points of the map's cloud (each entry gives an equal share).
MAP_POINTS = 200_000


def load_map_view(bundle: str | Path, max_points: int = MAP_POINTS) -> MapView:
    """The :class:`MapView` of the bundle at ``bundle``: its entries' origins (the geometry's,
    else the metadata's easting and northing at height 0), a cloud of at most ``max_points``
    points of its geometry (empty without geometry) and its UTM zone (the entries' first
    non-empty one; ``""`` when none has one)."""
    from pnvlad_service.index.bundle import METADATA_FILE, Metadata
    from pnvlad_service.index.geometry import BundleGeometry
    from pnvlad_service.index.manifest import Manifest

    bundle = Path(bundle)
    meta = Metadata.load(bundle / METADATA_FILE)
    zones = [str(z) for z in meta.utm_zone if str(z).strip()]
    entries = np.c_[meta.easting, meta.northing, np.zeros(len(meta.easting))].astype(np.float64)
    cloud = np.zeros((0, 3), dtype=np.float64)
    record = Manifest.read(bundle).geometry
    if record is not None and record.count:
        geometry = BundleGeometry.open(bundle, record, verify=False)
        try:
            n = geometry.count
            entries = np.asarray([geometry.map_pose(i)[:3, 3] for i in range(n)])
            each = max(1, max_points // n)
            parts = []
            for i in range(n):
                pts = geometry.metres(i)
                parts.append(pts[:: max(1, len(pts) // each)] + entries[i])
            cloud = np.concatenate(parts)
        finally:
            geometry.close()
    return MapView(entries=entries, cloud=cloud, utm_zone=zones[0] if zones else "")
