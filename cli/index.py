"""`pnvlad index`: build a FAISS index bundle of a map, append runs, inspect a bundle.

Library imports happen inside the commands so that `pnvlad --help` stays fast.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from pnvlad_cli.common import (
    model_option,
    progress_option,
    root_option,
    smooth_across_option,
    smooth_option,
    smooth_weight_option,
    user_errors,
)

if TYPE_CHECKING:
    from pnvlad_service.index.manifest import Manifest

app = typer.Typer(
    rich_markup_mode="markdown",
    help="Build and inspect FAISS index bundles (the map `pnvlad serve` searches).\n\n"
    "A bundle is a directory: index.faiss, metadata.npz (one row per submap: run, timestamp, "
    "UTM northing/easting, path), manifest.json (model and file sha256s) and, when the tree "
    "has frame sidecars, geometry.f16 + geometry.npz (each submap's points, for verification).",
    no_args_is_help=True,
)

_UNITS = {"": 1, "b": 1, "k": 1e3, "kb": 1e3, "kib": 2**10, "m": 1e6, "mb": 1e6, "mib": 2**20,
          "g": 1e9, "gb": 1e9, "gib": 2**30, "t": 1e12, "tb": 1e12, "tib": 2**40}  # fmt: skip


def parse_size(text: str) -> int:
    """'8GB', '512MiB', '1e9' -> bytes."""
    m = re.fullmatch(r"\s*([0-9.eE+]+)\s*([a-zA-Z]*)\s*", text)
    if not m or m.group(2).lower() not in _UNITS:
        raise typer.BadParameter(f"not a size: {text!r} (e.g. 8GB, 512MiB)")
    try:
        return int(float(m.group(1)) * _UNITS[m.group(2).lower()])
    except ValueError:
        raise typer.BadParameter(f"not a size: {text!r} (e.g. 8GB, 512MiB)") from None


_MODEL = model_option(..., help="The model to embed with.")
_ROOT = root_option(...)
_DATASET = typer.Option(
    None, "--dataset", "-d", help="Dataset folder to index (repeatable; default: all)."
)
_RUNS = typer.Option(None, "--run", help="Run folder to index (repeatable; default: all).")
_LAYOUT = typer.Option(
    "test",
    "--layout",
    help="Which map entries: 'test' (pointcloud_20m, 20 m submaps every 20 m: the evaluation "
    "database), 'train' (pointcloud_20m_10overlap, every 10 m) or 'keyframe' "
    "(pointcloud_keyframes: single scans every 5 m, the map for single-scan queries from a "
    "spinning LiDAR). The bundle records which kind it holds and the filter G its entries "
    "went through, which raw queries then go through too.",
)
_BATCH = typer.Option(32, "--batch-size", "-b", help="Clouds embedded per forward pass.")


def _geometry_mode(value: str) -> str:
    from pnvlad_service.index.build import GEOMETRY_MODES

    if value not in GEOMETRY_MODES:
        raise typer.BadParameter(f"{value!r} is not one of {', '.join(GEOMETRY_MODES)}")
    return value


_GEOMETRY_HELP = (
    "Store each submap's points (float16, ~24.6 KB a submap) for geometric verification: "
    "'auto' when every run has a frame sidecar (<csv stem>.frames.csv, written by pnvlad "
    "synth and pnvlad data prepare), 'required' to refuse runs without one, 'off' for none."
)


@app.command()
def build(
    model: Path = _MODEL,
    root: Path = _ROOT,
    out: Path = typer.Option(..., "--out", "-o", help="Bundle directory to write."),
    dataset: list[str] = _DATASET,
    run: list[str] = _RUNS,
    layout: str = _LAYOUT,
    index_key: str = typer.Option(
        "Flat",
        "--index-key",
        "-k",
        help="FAISS factory string: Flat (exact, default), HNSW32, IVF1024,Flat, "
        "IVF1024,PQ32, ... or 'auto' (by vector count and --memory-budget, FAISS guidelines).",
    ),
    memory_budget: str = typer.Option(
        "8GiB", "--memory-budget", help="Memory the index may use, for --index-key auto."
    ),
    batch_size: int = _BATCH,
    recall_sample: int = typer.Option(
        1000, help="Database vectors used to measure recall@1 of approximate indexes."
    ),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing bundle."),
    geometry: str = typer.Option(
        "auto", "--geometry", callback=_geometry_mode, help=_GEOMETRY_HELP
    ),
    utm_zone: str = typer.Option(
        None,
        "--utm-zone",
        help="UTM zone of the tree's coordinates (30U, 32N, 17S, 17 south), carried by every "
        "answer (default: the one the runs were prepared with, else unknown).",
    ),
    smooth: float | None = smooth_option(),
    smooth_weight: float | None = smooth_weight_option(),
    smooth_across_drives: bool = smooth_across_option(),
    progress: bool = progress_option(),
) -> None:
    """Embed every database submap of a benchmark tree and write an index bundle.

    The bundle is built in a temporary directory and renamed at the end: an interrupted build
    leaves nothing that looks complete. Prints the embedding throughput and, for approximate
    indexes, recall@1 against exact search on a sample of the map's own descriptors.

    Sharded: run under torchrun (e.g. torchrun --nproc-per-node 2 -m pnvlad_cli.main index
    build ...); each rank embeds a contiguous shard, rank 0 writes the same bundle.

    Example: pnvlad index build -m runs/model -r benchmark_datasets -d oxford -o map.index
    """
    from pnvlad_service.index.build import build_bundle
    from pnvlad_service.index.smoothing import Smoothing

    with user_errors():
        rep = build_bundle(
            out,
            model,
            root,
            datasets=dataset or None,
            runs=run or None,
            layout=layout,
            index_key=index_key,
            memory_budget=parse_size(memory_budget),
            batch_size=batch_size,
            recall_sample=recall_sample,
            overwrite=overwrite,
            geometry=geometry,
            progress=progress,
            utm_zone=utm_zone,
            smoothing=Smoothing.of(smooth, smooth_weight, smooth_across_drives),
        )
    if rep.path is None:  # a non-zero torchrun rank
        return
    typer.echo(
        f"embedded {rep.count} submaps in {rep.embed_seconds:.1f} s "
        f"({rep.clouds_per_second:.1f} clouds/s); index {rep.index_key} built in "
        f"{rep.index_seconds:.2f} s"
    )
    if rep.recall_at_1 is not None:
        typer.echo(f"recall@1 against exact search: {rep.recall_at_1:.4f}")
    assert rep.manifest is not None
    typer.echo(f"geometry: {_geometry_text(rep.manifest)}")
    typer.echo(f"wrote {rep.path}")


@app.command()
def add(
    bundle: Path = typer.Argument(..., help="Existing bundle directory (rewritten atomically)."),
    model: Path = _MODEL,
    root: Path = _ROOT,
    dataset: list[str] = _DATASET,
    run: list[str] = _RUNS,
    layout: str = _LAYOUT,
    batch_size: int = _BATCH,
    geometry: str = typer.Option(
        "auto",
        "--geometry",
        callback=_geometry_mode,
        help="'auto': a bundle with geometry keeps it and gains the new runs' (refused for runs "
        "without a frame sidecar); 'required': also refuse a bundle without geometry; 'off': "
        "drop the bundle's geometry.",
    ),
    progress: bool = progress_option(),
) -> None:
    """Append new runs to a bundle.

    The model must be the one the bundle was built with (same weights sha256); submaps
    already in the bundle are refused. A bundle with geometry keeps it: runs without a frame
    sidecar are refused unless --geometry off drops it. A map is in one UTM zone: runs that
    record one (data prepare --utm-zone) give it to a bundle built without one, every entry
    of it; runs of another zone than the bundle's are refused. A map smoothed along its drives
    (build --smooth) takes whole new runs, smoothed among themselves; one smoothed across its
    drives (--smooth-across-drives) takes none: build it again.

    Example: pnvlad index add map.index -m runs/model -r benchmark_datasets \
      --run 2015-02-03-08-45-10
    """
    from pnvlad_service.index.build import add_to_bundle

    with user_errors():
        rep = add_to_bundle(
            bundle,
            model,
            root,
            datasets=dataset or None,
            runs=run or None,
            layout=layout,
            batch_size=batch_size,
            geometry=geometry,
            progress=progress,
        )
    assert rep.manifest is not None
    typer.echo(
        f"added {rep.count} submaps ({rep.clouds_per_second:.1f} clouds/s); "
        f"{rep.manifest.count} vectors in {rep.path}"
    )


@app.command()
def info(
    bundle: Path = typer.Argument(..., help="Bundle directory."),
    as_json: bool = typer.Option(False, "--json", help="Print the whole manifest as JSON."),
) -> None:
    """Print a bundle's manifest and check every file's sha256 (and the model's, if present).

    Exits 1 when a file does not match its recorded hash.

    Example: pnvlad index info map.index
    """
    from pnvlad_service.index.manifest import Manifest

    with user_errors():
        manifest = Manifest.read(bundle)
        checks = manifest.verify_files(bundle)
        if manifest.geometry is not None:
            checks["geometry"] = _geometry_ok(bundle, manifest)
    if as_json:
        typer.echo(json.dumps({"manifest": manifest.to_json(), "files_ok": checks}, indent=2))
    else:
        rows = _info_rows(bundle, manifest, checks)
        if checks.get("metadata.npz"):
            rows.insert(4, ("utm zone", _zones(bundle)))
        width = max(len(k) for k, _ in rows)
        for k, v in rows:
            typer.echo(f"{k:<{width}}  {v}")
    if not all(checks.values()):
        typer.secho("error: some files do not match the manifest", err=True, fg="red")
        raise typer.Exit(code=1)


def _geometry_text(manifest: Manifest) -> str:
    """'none' or 'N submaps, X KB each (Y MB)'."""
    g = manifest.geometry
    if g is None:
        return "none"
    return (
        f"{g.count} submaps, {g.bytes / max(g.count, 1) / 1e3:.1f} KB each ({g.bytes / 1e6:.1f} MB)"
    )


def _geometry_ok(bundle: Path, manifest: Manifest) -> bool:
    """The start-up checks of the bundle's geometry (size, table, hash or sampled rows)."""
    import logging

    from pnvlad_service.errors import InputError
    from pnvlad_service.index.geometry import BundleGeometry

    assert manifest.geometry is not None
    try:
        BundleGeometry.open(bundle, manifest.geometry).close()
    except InputError as exc:
        logging.getLogger("pnvlad").error("%s", exc)
        return False
    return True


def _checkpoint_state(manifest: Manifest) -> str:
    """Whether the model the bundle records is still there with the same weights."""
    from pnvlad_service.errors import InputError
    from pnvlad_service.models.store import WEIGHTS_FILE, model_identity

    ckpt = manifest.model.checkpoint
    if not ckpt:
        return "not recorded"
    if not (Path(ckpt) / WEIGHTS_FILE).is_file():
        return "missing"
    try:
        identity = model_identity(ckpt)
    except InputError as exc:
        return f"unreadable ({exc.detail})"
    try:
        manifest.check_model(identity)
    except InputError:
        return "DIFFERENT weights"
    return "OK (same weights)"


def _zones(bundle: Path) -> str:
    """The UTM zones of a bundle's entries (one, where a map is made as it should be)."""
    from pnvlad_service.index.bundle import Metadata

    zones = sorted({str(z) for z in Metadata.load(bundle / "metadata.npz").utm_zone.tolist()})
    return ", ".join(z or "unknown (index build --utm-zone gives one)" for z in zones)


def _map_text(manifest: Manifest) -> str:
    """What the map holds and whether its drives were aligned together (pnvlad map align)."""
    record = manifest.map_record
    aligned = (
        f"aligned (pnvlad map align, report sha256 {record.alignment[:16]}…): a prior "
        "registers to any drive's entries"
        if record.alignment
        else "not aligned: a prior registers to one drive's entries"
    )
    sm = record.smoothing
    how = "across" if sm and sm.across_drives else "along"
    smoothed = (
        f"; smoothed {how} its drives ({sm.radius_m:g} m, weight {sm.weight:g})" if sm else ""
    )
    return f"{record.kind}s ({record.layout}), {aligned}{smoothed}"


def _info_rows(bundle: Path, manifest: Manifest, checks: dict[str, bool]) -> list[tuple[str, str]]:
    """The (label, value) lines of ``pnvlad index info``."""
    m = manifest
    rows = [
        ("bundle", str(bundle)),
        ("format", f"{m.format} v{m.version}"),
        ("index", f"{m.index_key} ({m.metric}, d={m.dim})"),
        ("vectors", str(m.count)),
        ("search params", json.dumps(dict(m.search_params))),
        ("recall@1 vs exact", str(m.recall_at_1_vs_exact)),
        ("model weights", m.model.weights_sha256),
        ("model config", m.model.config_sha256),
        ("checkpoint", f"{m.model.checkpoint} [{_checkpoint_state(m)}]"),
        ("geometry", _geometry_text(m)),
        ("map", _map_text(m)),
        ("created", m.created),
        ("modified", m.modified),
    ]
    for entry in m.indexed:
        rows.append(
            (
                "indexed",
                f"{entry['count']} {entry['layout']} submaps of "
                f"{', '.join(entry['datasets'])}: {len(entry['runs'])} runs from "
                f"{entry['root']}",
            )
        )
    for name, ok in checks.items():
        if name == "geometry":
            rows.append((name, "checks OK" if ok else "checks FAILED (see the error above)"))
        else:
            rows.append((name, "sha256 OK" if ok else "sha256 MISMATCH"))
    return rows
