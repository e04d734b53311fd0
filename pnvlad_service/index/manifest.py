"""The manifest of an index bundle (``manifest.json``), typed and frozen.

It records what the bundle is (format, version, dimension, metric, FAISS key, vector count,
search parameters, recall@1 against exact search), the model it was built with (weights and
config sha256), the preprocessing config (filter G), what was indexed, when, and the sha256 of
each file. :meth:`Manifest.check_model` is the one answer to "was this bundle built with these
weights?"; :meth:`Manifest.verify_files` checks the files against their recorded hashes.

A :class:`Manifest` is immutable all the way down: its mappings are read-only views and its
lists tuples; :meth:`Manifest.to_json` gives back plain JSON values, exactly the file's content.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

from pnvlad_service.errors import InputError
from pnvlad_service.fileio import sha256_file
from pnvlad_service.index.smoothing import Smoothing
from pnvlad_service.models.store import WEIGHTS_FILE, ModelIdentity

FORMAT = "pnvlad-index"
#: The bundle format a manifest declares: 1, or 2 for a map whose descriptors were smoothed
#: (``map.smoothing``). A reader that predates smoothing refuses version 2 rather than read
#: the bundle as a plain map (its ``index add`` would append unsmoothed entries and drop the
#: record).
VERSION = 1
SMOOTHED_VERSION = 2
VERSIONS = (VERSION, SMOOTHED_VERSION)
INDEX_FILE = "index.faiss"
METADATA_FILE = "metadata.npz"
MANIFEST_FILE = "manifest.json"

#: Keys every manifest has, in the order ``manifest.json`` lists them.
KEYS = (
    "format",
    "version",
    "dim",
    "metric",
    "distance",
    "index_key",
    "count",
    "search_params",
    "recall_at_1_vs_exact",
    "model",
    "preprocess",
    "indexed",
    "created",
    "modified",
    "files",
)
#: Keys a manifest may have: how the bundle was built (processes, embedding seconds), the
#: database submaps' points (:class:`GeometryRecord`; bundles without it have no ``geometry``)
#: and what kind of map it is (:class:`MapRecord`; bundles without it hold 20 m submaps).
OPTIONAL_KEYS = ("build", "geometry", "map")

#: The kinds of map entry a bundle can hold: accumulated submaps, or keyframes (single scans).
MAP_KINDS = ("submap", "keyframe")
#: The kinds of query: a preprocessed 4096-point cloud, one raw scan in its sensor frame, or
#: raw scans accumulated over the last stretch of a drive (metres, a local frame).
QUERY_KINDS = ("submap", "scan", "window")
#: What each map kind answers: a keyframe map holds single scans, whose crop a window does
#: not match (accumulated windows go to a submap map).
ACCEPTS: dict[str, tuple[str, ...]] = {
    "submap": ("submap", "scan", "window"),
    "keyframe": ("submap", "scan"),
}
_MODEL_KEYS = ("checkpoint", "weights_sha256", "config_sha256", "config")
#: The keys of the ``geometry`` entry, in the file's order.
GEOMETRY_KEYS = (
    "points_file",
    "table_file",
    "count",
    "points",
    "dtype",
    "bytes",
    "digest",
    "table_sha256",
    "points_sha256",
)


def _freeze(value: Any) -> Any:
    """A read-only copy of a JSON value: dicts become read-only mappings, lists tuples."""
    if isinstance(value, Mapping):
        return MappingProxyType({k: _freeze(v) for k, v in value.items()})
    if isinstance(value, (list, tuple)):
        return tuple(_freeze(v) for v in value)
    return value


def _thaw(value: Any) -> Any:
    """The plain JSON value of what :func:`_freeze` made: mappings become dicts, tuples lists."""
    if isinstance(value, Mapping):
        return {k: _thaw(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_thaw(v) for v in value]
    return value


@dataclass(frozen=True)
class ModelRecord:
    """The manifest's ``model`` entry: the model directory the bundle was built with (``None``
    when not recorded), the sha256 of its weights file and of its config, and the config."""

    checkpoint: str | None
    weights_sha256: str
    config_sha256: str
    config: Mapping[str, Any]

    def __post_init__(self) -> None:
        object.__setattr__(self, "config", _freeze(self.config))

    @classmethod
    def from_identity(cls, identity: ModelIdentity) -> ModelRecord:
        """The record of a model (:func:`pnvlad_service.models.store.model_identity`)."""
        return cls(
            identity.checkpoint, identity.weights_sha256, identity.config_sha256, identity.config
        )

    @classmethod
    def from_json(cls, doc: Any, source: str | Path | None = None) -> ModelRecord:
        """Parse the ``model`` entry; :class:`InputError` naming ``source`` when malformed."""
        if not isinstance(doc, Mapping):
            raise InputError("manifest's model entry is not an object", source=source)
        missing = [k for k in _MODEL_KEYS if k not in doc]
        if missing:
            raise InputError(f"manifest's model entry lacks the keys {missing}", source=source)
        ckpt, weights, config_sha, config = (doc[k] for k in _MODEL_KEYS)
        if not (ckpt is None or isinstance(ckpt, str)) or not isinstance(config, Mapping):
            raise InputError("manifest's model entry has values of the wrong type", source)
        if not isinstance(weights, str) or not isinstance(config_sha, str):
            raise InputError("manifest's model sha256s are not strings", source=source)
        return cls(ckpt, weights, config_sha, config)

    def to_json(self) -> dict[str, Any]:
        return {
            "checkpoint": self.checkpoint,
            "weights_sha256": self.weights_sha256,
            "config_sha256": self.config_sha256,
            "config": _thaw(self.config),
        }


@dataclass(frozen=True)
class GeometryRecord:
    """The manifest's ``geometry`` entry (:mod:`pnvlad_service.index.geometry`).

    ``points_file`` (``geometry.f16``) holds ``count`` rows of ``points`` x 3 coordinates of
    type ``dtype`` (``"<f2"``), ``bytes`` in all; ``table_file`` (``geometry.npz``) the
    per-row origin, centre, scale and ``digest`` (``"blake2b-64"``: an 8-byte BLAKE2b of each
    row's bytes). ``table_sha256`` is the table's sha256; ``points_sha256`` the points file's,
    or ``None`` when it was too big to hash at every start-up (rows are then checked against
    their digests: a sample at start-up, each one when fetched).
    """

    points_file: str
    table_file: str
    count: int
    points: int
    dtype: str
    bytes: int
    digest: str
    table_sha256: str
    points_sha256: str | None

    @classmethod
    def from_json(cls, doc: Any, source: str | Path | None = None) -> GeometryRecord:
        """Parse the ``geometry`` entry; :class:`InputError` naming ``source`` when malformed."""
        if not isinstance(doc, Mapping):
            raise InputError("manifest's geometry entry is not an object", source=source)
        missing = [k for k in GEOMETRY_KEYS if k not in doc]
        if missing:
            raise InputError(f"manifest's geometry entry lacks the keys {missing}", source)
        ints = ("count", "points", "bytes")
        strs = ("points_file", "table_file", "dtype", "digest", "table_sha256")
        wrong = [k for k in ints if not isinstance(doc[k], int) or isinstance(doc[k], bool)]
        wrong += [k for k in strs if not isinstance(doc[k], str)]
        if not (doc["points_sha256"] is None or isinstance(doc["points_sha256"], str)):
            wrong.append("points_sha256")
        if wrong:
            raise InputError(f"manifest's geometry keys of the wrong type: {wrong}", source)
        return cls(**{k: doc[k] for k in GEOMETRY_KEYS})

    def to_json(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in GEOMETRY_KEYS}


@dataclass(frozen=True)
class MapRecord:
    """The manifest's ``map`` entry: ``kind`` of the entries (:data:`MAP_KINDS`), the layout
    they came from (``train``, ``test`` or ``keyframe``), and ``turns``: the headings a quarter
    turn apart each entry is embedded at (the index holds ``turns`` vectors an entry, entry
    ``i``'s at ``i * turns ...``; 4 for a model that turns clouds to their own heading);
    ``accumulation``: how the map's windows laid each scan (``data.run_folder.
    ACCUMULATION_KEYS``: the points kept a scan, its range), which an accumulated query must
    follow (:meth:`~pnvlad_service.data.accumulate.WindowAccumulator.for_map`); ``None`` where
    the tree recorded none. ``alignment``: the sha256 of the ``align_report.json`` of the tree
    that ``pnvlad map align`` wrote, when every run indexed is of it (the map's drives agree,
    and a prior registers to any of them: docs/TRACKING.md); ``None`` otherwise.
    ``smoothing``: how the entries' descriptors were blended along their drives
    (:mod:`~pnvlad_service.index.smoothing`, ``pnvlad index build --smooth``); ``None`` for
    none."""

    kind: str = "submap"
    layout: str = "test"
    turns: int = 1
    accumulation: Mapping[str, Any] | None = None
    alignment: str | None = None
    smoothing: Smoothing | None = None

    @property
    def aligned(self) -> bool:
        """Whether the map's drives were aligned together (``pnvlad map align``)."""
        return self.alignment is not None

    @classmethod
    def from_json(cls, doc: Any, source: str | Path | None = None) -> MapRecord:
        """Parse the ``map`` entry; :class:`InputError` naming ``source`` when malformed."""
        if not isinstance(doc, Mapping) or doc.get("kind") not in MAP_KINDS:
            raise InputError(f"manifest's map entry needs a kind of {list(MAP_KINDS)}", source)
        if not isinstance(doc.get("layout", "test"), str):
            raise InputError("manifest's map layout is not a string", source)
        turns = doc.get("turns", 1)
        if turns not in (1, 2, 4) or isinstance(turns, bool):
            raise InputError(f"manifest's map turns must be 1, 2 or 4, got {turns!r}", source)
        acc = doc.get("accumulation")
        if acc is not None and not (
            isinstance(acc, Mapping)
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in acc.values())
        ):
            raise InputError("manifest's map accumulation must map names to numbers", source)
        alignment = doc.get("alignment")
        if alignment is not None and not (
            isinstance(alignment, str)
            and len(alignment) == 64
            and all(c in "0123456789abcdef" for c in alignment)
        ):
            raise InputError("manifest's map alignment must be a sha256 (64 hex digits)", source)
        smoothing = doc.get("smoothing")
        return cls(
            str(doc["kind"]),
            str(doc.get("layout", "test")),
            int(turns),
            None if acc is None else MappingProxyType(dict(acc)),
            alignment,
            None if smoothing is None else Smoothing.from_json(smoothing, source),
        )

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"kind": self.kind, "layout": self.layout, "turns": self.turns}
        if self.accumulation is not None:
            out["accumulation"] = dict(self.accumulation)
        if self.alignment is not None:
            out["alignment"] = self.alignment
        if self.smoothing is not None:
            out["smoothing"] = self.smoothing.to_json()
        return out

    def accepts(self, query_kind: str) -> bool:
        """Whether a query of ``query_kind`` (:data:`QUERY_KINDS`) meets its own kind here."""
        return query_kind in ACCEPTS[self.kind]


@dataclass(frozen=True)
class Manifest:
    """``manifest.json`` of a bundle, one field per key (see :data:`KEYS`).

    ``dim`` is the descriptor dimension, ``count`` the number of entries (vectors over the
    map's ``turns``), ``metric`` ``"l2"``
    and ``distance`` ``"euclidean"`` (the distances a search returns); ``search_params`` the
    FAISS search-time parameters applied on load; ``recall_at_1_vs_exact`` recall@1 of an
    approximate key against exact search (``None`` for exact keys); ``indexed`` one entry per
    build or add (root, layout, datasets, runs, count, added); ``created`` / ``modified`` ISO
    8601 UTC; ``files`` maps each file name to its sha256; ``build`` (optional) how it was
    built; ``geometry`` (optional) the database submaps' points (:class:`GeometryRecord`,
    ``None`` for a bundle without them); ``map`` the kind of its entries (:class:`MapRecord`:
    ``None`` in bundles made before keyframe maps, which hold submaps: :attr:`map_record`).
    ``extra`` keeps keys this version does not know, so
    :meth:`to_json` writes back what was read. ``path`` is the bundle directory the manifest
    belongs to (not in the file).
    """

    format: str
    version: int
    dim: int
    metric: str
    distance: str
    index_key: str
    count: int
    search_params: Mapping[str, int]
    recall_at_1_vs_exact: float | None
    model: ModelRecord
    preprocess: Mapping[str, Any] | None
    indexed: tuple[Mapping[str, Any], ...]
    created: str
    modified: str
    files: Mapping[str, str]
    build: Mapping[str, Any] | None = None
    geometry: GeometryRecord | None = None
    map: MapRecord | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)
    path: Path | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        for name in ("search_params", "preprocess", "indexed", "files", "build", "extra"):
            object.__setattr__(self, name, _freeze(getattr(self, name)))

    @classmethod
    def read(cls, bundle_dir: str | Path) -> Manifest:
        """``manifest.json`` of a bundle directory, checked for format, version and keys."""
        path = Path(bundle_dir)
        mpath = path / MANIFEST_FILE
        if not path.is_dir():
            raise InputError("index bundle directory not found", source=path)
        if not mpath.is_file():
            raise InputError("not an index bundle (no manifest.json)", source=path)
        try:
            doc = json.loads(mpath.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise InputError(f"manifest is not valid JSON: {exc}", source=mpath) from exc
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            raise InputError(f"not a {FORMAT} manifest", source=mpath)
        if doc.get("version") not in VERSIONS or isinstance(doc.get("version"), bool):
            raise InputError(
                f"bundle format version {doc.get('version')} is not supported "
                f"(this pnvlad reads {', '.join(map(str, VERSIONS))})",
                source=mpath,
            )
        return cls.from_json(doc, path)

    @classmethod
    def from_json(cls, doc: Mapping[str, Any], bundle_dir: str | Path | None = None) -> Manifest:
        """A manifest from its JSON object; :class:`InputError` for missing or mistyped keys."""
        source = None if bundle_dir is None else Path(bundle_dir) / MANIFEST_FILE
        missing = [k for k in KEYS if k not in doc]
        if missing:
            raise InputError(f"manifest lacks the keys {missing}", source=source)
        _check_types(doc, source)
        known = {k: doc[k] for k in (*KEYS, *OPTIONAL_KEYS) if k in doc}
        known["model"] = ModelRecord.from_json(doc["model"], source)
        if doc.get("geometry") is not None:
            known["geometry"] = GeometryRecord.from_json(doc["geometry"], source)
        if doc.get("map") is not None:
            known["map"] = MapRecord.from_json(doc["map"], source)
        extra = {k: v for k, v in doc.items() if k not in KEYS and k not in OPTIONAL_KEYS}
        path = None if bundle_dir is None else Path(bundle_dir)
        return cls(**known, extra=extra, path=path)

    def to_json(self) -> dict[str, Any]:
        """The JSON object of ``manifest.json``: the keys in the file's order."""
        doc = {k: _thaw(getattr(self, k)) for k in KEYS}
        doc["model"] = self.model.to_json()
        if self.build is not None:
            doc["build"] = _thaw(self.build)
        if self.geometry is not None:
            doc["geometry"] = self.geometry.to_json()
        if self.map is not None:
            doc["map"] = self.map.to_json()
        doc.update(_thaw(self.extra))
        return doc

    @property
    def map_record(self) -> MapRecord:
        """What the bundle holds (a submap map when the manifest does not say)."""
        return self.map or MapRecord()

    def check_model(self, identity: ModelIdentity) -> None:
        """Raise :class:`InputError` naming both files when the bundle was built with other
        weights than the model ``identity`` (compares the weights' sha256)."""
        built = self.model.weights_sha256
        if identity.weights_sha256 == built:
            return
        where = "" if self.path is None else f" {self.path / MANIFEST_FILE}"
        raise InputError(
            f"the index{where} was built with other weights "
            f"(sha256 {built[:16]}…) than the checkpoint "
            f"{Path(identity.checkpoint) / WEIGHTS_FILE} "
            f"(sha256 {identity.weights_sha256[:16]}…); rebuild the index or pass the "
            "checkpoint it was built with",
            source=identity.checkpoint,
        )

    def verify_files(self, bundle_dir: str | Path) -> dict[str, bool]:
        """``{file name: sha256 matches}`` for every file the manifest lists."""
        bundle_dir = Path(bundle_dir)
        result: dict[str, bool] = {}
        for name, digest in self.files.items():
            f = bundle_dir / name
            result[name] = f.is_file() and sha256_file(f) == digest
        return result


#: The JSON types of the manifest's keys (``model`` is checked by :class:`ModelRecord`).
_TYPES: dict[str, tuple[type, ...]] = {
    "dim": (int,),
    "metric": (str,),
    "distance": (str,),
    "index_key": (str,),
    "count": (int,),
    "search_params": (dict,),
    "recall_at_1_vs_exact": (int, float, type(None)),
    "preprocess": (dict, type(None)),
    "indexed": (list,),
    "created": (str,),
    "modified": (str,),
    "files": (dict,),
    "build": (dict, type(None)),
    "geometry": (dict, type(None)),
    "map": (dict, type(None)),
}


def _check_types(doc: Mapping[str, Any], source: Path | None) -> None:
    """Raise :class:`InputError` naming the keys of ``doc`` whose values have the wrong type."""
    wrong = [
        k
        for k, types in _TYPES.items()
        if k in doc and (not isinstance(doc[k], types) or isinstance(doc[k], bool))
    ]
    if wrong:
        raise InputError(f"manifest keys of the wrong type: {wrong}", source=source)


def format_version(map_record: MapRecord | None) -> int:
    """The format version a bundle of ``map_record`` declares (:data:`VERSIONS`)."""
    smoothed = map_record is not None and map_record.smoothing is not None
    return SMOOTHED_VERSION if smoothed else VERSION
