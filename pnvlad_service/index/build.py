"""Building bundles: list a tree's database submaps, embed them, write or extend a bundle.

:func:`build_bundle` embeds every submap of one layout of a benchmark tree and writes a new
bundle; under ``torchrun`` each rank embeds a contiguous shard and rank 0 gathers them (gloo).
:func:`add_to_bundle` appends new runs to a bundle built with the same weights.

Geometry (:mod:`pnvlad_service.index.geometry`): with ``geometry="auto"`` a bundle stores the
database submaps' points when every run indexed has a frame sidecar, and is built without them
(one log line naming the runs) otherwise; ``"required"`` refuses such runs, ``"off"`` stores
none (and drops an existing bundle's on add).

``torch`` is imported inside the functions that need it.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.index.bundle import IndexBundle, Metadata, now, write_bundle
from pnvlad_service.index.geometry import database_frames, geometry_writer
from pnvlad_service.index.keys import (
    DEFAULT_MEMORY_BUDGET,
    apply_search_params,
    choose_index_key,
    default_search_params,
    is_exact,
    make_index,
    recall_at_1,
)
from pnvlad_service.index.manifest import Manifest, MapRecord, ModelRecord
from pnvlad_service.index.smoothing import Smoothing
from pnvlad_service.index.tree_records import (
    tree_accumulation,
    tree_alignment,
    tree_preprocess_config,
    tree_utm_zone,
)
from pnvlad_service.io.readers import read_points
from pnvlad_service.models.config import map_turns
from pnvlad_service.models.embedding import Embedder, embed_in_chunks, turned_embedder
from pnvlad_service.models.runtimes import load_encoder
from pnvlad_service.models.store import model_identity

if TYPE_CHECKING:
    from pnvlad_service.data.frames import SubmapFrame
    from pnvlad_service.data.tree import Submap

log = logging.getLogger(__name__)

#: What ``geometry=`` may be (``--geometry``): store it when the tree has it, insist, or not.
GEOMETRY_MODES = ("auto", "required", "off")
#: The tree layouts a bundle can hold, and the kind of map each makes.
LAYOUT_KINDS = {"test": "submap", "train": "submap", "keyframe": "keyframe"}


# --------------------------------------------------------------------------------------------
# Submaps: which go into the database, reading and embedding them
# --------------------------------------------------------------------------------------------


def list_database_submaps(
    root: str | Path,
    datasets: Sequence[str] | None = None,
    runs: Sequence[str] | None = None,
    layout: str = "test",
) -> list[Submap]:
    """Every submap of role ``layout`` ("test": ``pointcloud_20m`` / ``pointcloud_25m_25``;
    "train": the 10 m ones; "keyframe": the keyframe maps, single scans) of the benchmark
    tree at ``root``.

    ``datasets`` and ``runs`` restrict by folder name. Order: datasets and runs sorted, CSV
    rows in file order (:class:`pnvlad_service.data.tree.BenchmarkTree`'s order). Raises
    :class:`InputError` when nothing matches or a named run is missing.
    """
    from pnvlad_service.data.tree import BenchmarkTree

    if layout not in LAYOUT_KINDS:
        raise InputError(f"layout must be one of {list(LAYOUT_KINDS)}, got {layout!r}", "layout")
    tree = BenchmarkTree(root)
    wanted_runs = set(runs) if runs else None
    seen_runs: set[str] = set()
    records: list[Submap] = []
    for dataset in tree.datasets:
        if datasets and dataset not in datasets:
            continue
        for run in tree.runs(dataset):
            if wanted_runs is not None and run not in wanted_runs:
                continue
            if not tree.has(dataset, run, layout):  # type: ignore[arg-type]
                continue
            seen_runs.add(run)
            records.extend(tree.submaps(dataset, run, layout))  # type: ignore[arg-type]
    if wanted_runs is not None and wanted_runs - seen_runs:
        raise InputError(f"runs not found: {sorted(wanted_runs - seen_runs)}", source=root)
    if not records:
        raise InputError(f"no {layout}-layout submaps found", source=root)
    return records


def embed_submaps(
    encoder: Embedder,
    root: str | Path,
    records: Sequence[Submap],
    batch_size: int = 32,
    progress: bool = True,
    turns: int = 1,
) -> np.ndarray:
    """Descriptors of ``records`` in order: float32 [len(records) * turns, encoder.dim],
    embedded ``batch_size`` submaps (read from ``root / record.path``) at a time; with
    ``turns`` each record's descriptors at that many headings a quarter turn apart follow each
    other (:func:`~pnvlad_service.models.embedding.turned_embedder`)."""
    root = Path(root)
    if not records:
        return np.empty((0, encoder.dim), dtype=np.float32)

    def load(start: int, stop: int) -> np.ndarray:
        clouds = [read_points(root / r.path, "benchmark") for r in records[start:stop]]
        return np.stack(clouds).astype(np.float32)

    embed = turned_embedder(encoder.embed, turns)
    desc = embed_in_chunks(
        embed, len(records), load, chunk=batch_size, progress=progress, desc="embedding"
    )
    return desc.reshape(len(records) * turns, -1)


def with_zone(records: Sequence[Submap], zone: str) -> list[Submap]:
    """``records`` tagged with UTM zone ``zone``."""
    return [replace(r, utm_zone=zone) for r in records]


# --------------------------------------------------------------------------------------------
# Sharded embedding under torchrun
# --------------------------------------------------------------------------------------------


@contextlib.contextmanager
def _maybe_distributed() -> Iterator[tuple[int, int]]:
    """(rank, world size) under ``torchrun`` (gloo process group), else (0, 1)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        yield 0, 1
        return
    import torch.distributed as dist

    created = False
    if not dist.is_initialized():
        dist.init_process_group("gloo")
        created = True
    try:
        yield dist.get_rank(), dist.get_world_size()
    finally:
        if created:
            dist.barrier()
            dist.destroy_process_group()


def _embed_sharded(
    encoder: Embedder,
    root: Path,
    records: Sequence[Submap],
    batch_size: int,
    progress: bool,
    rank: int,
    world: int,
    turns: int = 1,
) -> np.ndarray | None:
    """Rank ``rank`` embeds its contiguous shard; rank 0 gets all descriptors in order
    (float32 [len(records) * turns, dim]), the other ranks ``None``."""
    if world == 1:
        return embed_submaps(encoder, root, records, batch_size, progress, turns)
    import torch
    import torch.distributed as dist

    n = len(records)
    bounds = [n * r // world for r in range(world + 1)]
    mine = embed_submaps(
        encoder,
        root,
        records[bounds[rank] : bounds[rank + 1]],
        batch_size,
        progress and rank == 0,
        turns,
    )
    width = max(bounds[r + 1] - bounds[r] for r in range(world)) * turns
    padded = torch.zeros((width, encoder.dim), dtype=torch.float32)
    padded[: len(mine)] = torch.from_numpy(mine)
    gathered = [torch.zeros_like(padded) for _ in range(world)] if rank == 0 else None
    dist.gather(padded, gathered, dst=0)
    if rank != 0:
        return None
    assert gathered is not None
    return np.concatenate(
        [gathered[r][: (bounds[r + 1] - bounds[r]) * turns].numpy() for r in range(world)]
    ).astype(np.float32)


# --------------------------------------------------------------------------------------------
# Build and add
# --------------------------------------------------------------------------------------------


@dataclass
class BuildReport:
    """What a build did: counts, timings (seconds), throughput (clouds/s), recall@1 and the
    manifest written (``path`` and ``manifest`` are ``None`` on a non-zero torchrun rank)."""

    path: Path | None
    count: int
    index_key: str
    embed_seconds: float
    index_seconds: float
    clouds_per_second: float
    recall_at_1: float | None
    manifest: Manifest | None = None


def build_bundle(
    out: str | Path,
    model: str | Path,
    root: str | Path,
    *,
    datasets: Sequence[str] | None = None,
    runs: Sequence[str] | None = None,
    layout: str = "test",
    index_key: str = "Flat",
    memory_budget: int = DEFAULT_MEMORY_BUDGET,
    batch_size: int = 32,
    recall_sample: int = 1000,
    overwrite: bool = False,
    progress: bool = True,
    encoder: Embedder | None = None,
    preprocess: dict[str, Any] | None = None,
    geometry: str = "auto",
    utm_zone: str | None = None,
    smoothing: Smoothing | None = None,
) -> BuildReport:
    """Embed every ``layout`` submap of the tree at ``root`` and write a bundle to ``out``.

    ``model`` is a model directory or the training run that made it. ``index_key`` is a FAISS
    factory string or ``"auto"`` (:func:`~pnvlad_service.index.keys.choose_index_key`, within
    ``memory_budget`` bytes). Under ``torchrun`` (``WORLD_SIZE`` > 1) each rank embeds a
    contiguous shard, rank 0 gathers them (gloo) and writes the same bundle a single process
    would; other ranks return a report with ``path=None``. ``encoder`` defaults to the
    model's, ``preprocess`` to the default filter G config. ``geometry`` (see the module
    docstring): rank 0 writes it from the tree, never from the shards. ``utm_zone``: the zone
    of the tree's coordinates, which every answer carries (:func:`tree_utm_zone`).
    ``smoothing``: blend each entry with its drive's neighbours (:mod:`.smoothing`).
    """
    out = Path(out)
    root = Path(root)
    if out.exists() and not overwrite:
        raise InputError("bundle already exists (use --overwrite to replace it)", source=out)
    records = list_database_submaps(root, datasets, runs, layout)
    records = with_zone(records, tree_utm_zone(root, records, utm_zone))
    frames = _frames_for(root, records, geometry)
    identity = model_identity(model)
    record = ModelRecord.from_identity(identity)
    turns = map_turns(identity.config)
    enc = encoder if encoder is not None else load_encoder(model, identity=identity)
    with _maybe_distributed() as (rank, world):
        t0 = time.perf_counter()
        desc = _embed_sharded(enc, root, records, batch_size, progress, rank, world, turns)
        t_embed = time.perf_counter() - t0
        if desc is None:
            return BuildReport(None, len(records), index_key, t_embed, 0.0, 0.0, None)
        t1 = time.perf_counter()
        if smoothing is not None:
            if layout == "keyframe":
                log.warning("smoothing a keyframe map: single scans gained nothing from it")
            desc = smoothing.apply_to_entries(desc, records)
        index, index_key, params = _index_of(desc, index_key, memory_budget)
        t_index = time.perf_counter() - t1
        recall = None if is_exact(index_key) else recall_at_1(index, desc, recall_sample)
        if recall is not None:
            log.info("recall@1 of %s against exact search: %.4f", index_key, recall)
        manifest = write_bundle(
            out,
            index,
            Metadata.from_records(records),
            index_key=index_key,
            model=record,
            indexed=[_indexed_entry(root, layout, records)],
            preprocess=preprocess
            if preprocess is not None
            else tree_preprocess_config(root, records),
            search_params=params,
            recall=recall,
            overwrite=overwrite,
            build={"processes": world, "embed_seconds": round(t_embed, 3)},
            geometry=None if frames is None else geometry_writer(root, records, frames),
            map_record=_map_record(root, layout, records, turns, smoothing),
        )
    rate = len(records) / t_embed if t_embed > 0 else float("inf")
    return BuildReport(out, len(records), index_key, t_embed, t_index, rate, recall, manifest)


def _map_record(
    root: Path, layout: str, records: Sequence[Submap], turns: int, smoothing: Smoothing | None
) -> MapRecord:
    """The manifest's ``map`` entry of a new bundle of ``records``."""
    kind = LAYOUT_KINDS[layout]
    # windows go to submap maps only (a keyframe map refuses them)
    accumulation = tree_accumulation(root, records) if kind == "submap" else None
    return MapRecord(kind, layout, turns, accumulation, tree_alignment(root, records), smoothing)


def _frames_for(
    root: Path, records: Sequence[Submap], mode: str, has_geometry: bool | None = None
) -> list[SubmapFrame] | None:
    """The frame sidecar rows of ``records`` when their geometry is to be stored, else
    ``None``. ``has_geometry``: adding to a bundle that has geometry (``True``), has none
    (``False``), or building (``None``). :class:`InputError` naming the runs without a sidecar
    when the geometry cannot be left out."""
    if mode not in GEOMETRY_MODES:
        raise InputError(
            f"geometry must be one of {list(GEOMETRY_MODES)}, got {mode!r}", "geometry"
        )
    if mode == "off":
        return None
    if has_geometry is False:
        if mode == "required":
            raise InputError(
                "the bundle has no geometry (built without it): rebuild it to store geometry",
                source=root,
            )
        return None
    frames, missing = database_frames(root, records)
    if frames is not None:
        return frames
    runs = ", ".join(missing[:5]) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
    sidecar = "no frame sidecar (<locations csv stem>.frames.csv)"
    if has_geometry:
        raise InputError(
            f"the bundle has geometry but {runs} {'has' if len(missing) == 1 else 'have'} "
            f"{sidecar}; pass --geometry off to drop the bundle's geometry",
            source=root,
        )
    if mode == "required":
        raise InputError(
            f"--geometry required, but {runs} {'has' if len(missing) == 1 else 'have'} {sidecar}",
            source=root,
        )
    verb = "has" if len(missing) == 1 else "have"
    log.warning("building without geometry: %s %s %s", runs, verb, sidecar)
    return None


def _index_of(
    desc: np.ndarray, index_key: str, memory_budget: int
) -> tuple[Any, str, dict[str, int]]:
    """(FAISS index of ``desc`` float32 [N, D] with its search parameters set, the key,
    the parameters); ``index_key`` ``"auto"`` is chosen within ``memory_budget`` bytes."""
    if index_key == "auto":
        index_key = choose_index_key(len(desc), desc.shape[1], memory_budget)
        log.info("index key auto -> %s (%d vectors, d=%d)", index_key, *desc.shape)
    index = make_index(desc, index_key)
    params = default_search_params(index_key)
    apply_search_params(index, params)
    return index, index_key, params


def _indexed_entry(root: Path, layout: str, records: Sequence[Submap]) -> dict[str, Any]:
    """The manifest's ``indexed`` entry of one build or add."""
    return {
        "root": str(root.resolve()),
        "layout": layout,
        "datasets": sorted({r.dataset for r in records}),
        "runs": sorted({r.run for r in records}),
        "count": len(records),
        "added": now(),
    }


def _bundle_zone(bundle: IndexBundle, zone: str) -> str:
    """The zone of runs added to ``bundle`` (theirs, ``zone``, or the bundle's where they
    record none); :class:`InputError` when both are known and differ."""
    have = sorted({str(z) for z in bundle.metadata.utm_zone.tolist() if z})
    if zone and have and have != [zone]:
        raise InputError(
            f"the runs were prepared in {zone}, the bundle is in {have[0]}", "utm_zone"
        )
    return zone or (have[0] if len(have) == 1 else "")


def _adopt_zone(metadata: Metadata, zone: str) -> Metadata:
    """``metadata`` with its entries of no zone in ``zone``: runs that record a zone, added to
    a bundle built without one, give it to the whole map (a map is in one zone, and a mix of
    zoned and unknown entries would answer with or without it by the match)."""
    blank = metadata.utm_zone == ""
    if not zone or not blank.any():
        return metadata
    log.info("the bundle had no UTM zone: its %d entries take the added runs' zone, %s",
             int(blank.sum()), zone)  # fmt: skip
    return replace(metadata, utm_zone=np.where(blank, zone, metadata.utm_zone))


def _added_alignment(record: MapRecord | None, added: str | None) -> MapRecord | None:
    """The map record of a bundle that gains runs of alignment ``added``: still aligned only
    when they are of the same alignment (a warning when that ends it)."""
    if record is None or record.alignment is None or record.alignment == added:
        return record
    log.warning(
        "the runs added are not of the alignment the bundle's map was made of: the bundle is "
        "no longer recorded as aligned (priors register to one drive at a time)"
    )
    return replace(record, alignment=None)


def _check_new(bundle: IndexBundle, records: Sequence[Submap], source: Path) -> None:
    """:class:`InputError` naming ``source`` for submaps already in the bundle, and for a
    smoothed map's drives it already holds (their entries were blended without these)."""
    present = set(bundle.metadata.submap_id.tolist())
    dup = [r.submap_id for r in records if r.submap_id in present]
    if dup:
        raise InputError(
            f"{len(dup)} submaps are already in the bundle, e.g. {dup[0]}", source=source
        )
    smoothing = bundle.manifest.map_record.smoothing
    if smoothing is not None:
        have = zip(bundle.metadata.dataset, bundle.metadata.run, strict=True)
        smoothing.check_new_drives({f"{d}/{r}" for d, r in have}, records, source)


def add_to_bundle(
    bundle_dir: str | Path,
    model: str | Path,
    root: str | Path,
    *,
    datasets: Sequence[str] | None = None,
    runs: Sequence[str] | None = None,
    layout: str = "test",
    batch_size: int = 32,
    progress: bool = True,
    encoder: Embedder | None = None,
    geometry: str = "auto",
) -> BuildReport:
    """Append the submaps of new runs to an existing bundle (rewritten atomically).

    Refuses a model whose weights differ from the bundle's
    (:meth:`~pnvlad_service.index.manifest.Manifest.check_model`) and submaps already in it.
    A bundle with geometry keeps it (old rows copied, each checked against its digest) and
    gains the new submaps'; runs without a frame sidecar are refused unless ``geometry`` is
    ``"off"``, which drops the bundle's geometry. Runs that record a UTM zone give it to a
    bundle without one (every entry); runs of another zone than the bundle's are refused.
    """
    bundle_dir = Path(bundle_dir)
    root = Path(root)
    bundle = IndexBundle.load(bundle_dir)
    identity = model_identity(model)
    bundle.manifest.check_model(identity)
    kind = bundle.manifest.map_record.kind
    if LAYOUT_KINDS.get(layout) != kind:
        raise InputError(
            f"the bundle holds {kind}s; add {kind}s to it (layout {layout!r} holds "
            f"{LAYOUT_KINDS.get(layout, 'something else')}s)",
            "layout",
        )
    records = list_database_submaps(root, datasets, runs, layout)
    zone = _bundle_zone(bundle, tree_utm_zone(root, records))
    records = with_zone(records, zone)
    _check_new(bundle, records, bundle_dir)
    m = bundle.manifest
    smoothing = m.map_record.smoothing
    base = bundle.geometry
    frames = _frames_for(root, records, geometry, has_geometry=base is not None)
    if geometry == "off" and base is not None:
        log.warning("dropping the bundle's geometry (--geometry off)")
    enc = encoder if encoder is not None else load_encoder(model, identity=identity)
    t0 = time.perf_counter()
    desc = embed_submaps(enc, root, records, batch_size, progress, bundle.turns)
    t_embed = time.perf_counter() - t0
    t1 = time.perf_counter()
    if smoothing is not None:
        desc = smoothing.apply_to_entries(desc, records)
    bundle.index.add(np.ascontiguousarray(desc, dtype=np.float32))
    t_index = time.perf_counter() - t1
    manifest = write_bundle(
        bundle_dir,
        bundle.index,
        _adopt_zone(bundle.metadata, zone).concat(Metadata.from_records(records)),
        index_key=m.index_key,
        model=m.model,
        indexed=[*m.indexed, _indexed_entry(root, layout, records)],
        preprocess=m.preprocess,
        search_params=m.search_params,
        recall=m.recall_at_1_vs_exact,
        created=m.created,
        overwrite=True,
        build=m.build,
        extra=m.extra,
        geometry=None if frames is None else geometry_writer(root, records, frames, base),
        map_record=_added_alignment(m.map, tree_alignment(root, records)),
    )
    if base is not None:
        base.close()
    rate = len(desc) / t_embed if t_embed > 0 else float("inf")
    return BuildReport(
        bundle_dir, len(records), m.index_key, t_embed, t_index, rate, None, manifest
    )
