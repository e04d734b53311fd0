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

import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

from pnvlad_service.errors import InputError
from pnvlad_service.models.store import WEIGHTS_FILE, ModelIdentity

FORMAT = "pnvlad-index"
VERSION = 1
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
#: Keys a manifest may have: how the bundle was built (processes, embedding seconds).
OPTIONAL_KEYS = ("build",)
_MODEL_KEYS = ("checkpoint", "weights_sha256", "config_sha256", "config")


def sha256_file(path: str | Path, chunk: int = 1 << 22) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


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
class Manifest:
    """``manifest.json`` of a bundle, one field per key (see :data:`KEYS`).

    ``dim`` is the descriptor dimension, ``count`` the number of vectors, ``metric`` ``"l2"``
    and ``distance`` ``"euclidean"`` (the distances a search returns); ``search_params`` the
    FAISS search-time parameters applied on load; ``recall_at_1_vs_exact`` recall@1 of an
    approximate key against exact search (``None`` for exact keys); ``indexed`` one entry per
    build or add (root, layout, datasets, runs, count, added); ``created`` / ``modified`` ISO
    8601 UTC; ``files`` maps each file name to its sha256; ``build`` (optional) how it was
    built. ``extra`` keeps keys this version does not know, so :meth:`to_json` writes back
    what was read. ``path`` is the bundle directory the manifest belongs to (not in the file).
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
        if doc.get("version") != VERSION:
            raise InputError(
                f"bundle format version {doc.get('version')} is not supported (want {VERSION})",
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
        extra = {k: v for k, v in doc.items() if k not in KEYS and k not in OPTIONAL_KEYS}
        path = None if bundle_dir is None else Path(bundle_dir)
        return cls(**known, extra=extra, path=path)

    def to_json(self) -> dict[str, Any]:
        """The JSON object of ``manifest.json``: the keys in the file's order."""
        doc = {k: _thaw(getattr(self, k)) for k in KEYS}
        doc["model"] = self.model.to_json()
        if self.build is not None:
            doc["build"] = _thaw(self.build)
        doc.update(_thaw(self.extra))
        return doc

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
