"""Pretrained models that ship inside the package, selected by name: ``pretrained:NAME``.

The weights live in ``pnvlad_service/pretrained/`` (package data: the repository checkout and
the wheel both carry them, so a fresh install needs no download), one model directory per model
(``model.json``, ``model.safetensors`` and, so that a server without torch runs it,
``model.onnx``), listed by ``catalogue.json``::

    {"format": "pnvlad-pretrained", "version": 1,
     "models": [{"name": "bev-benchmark", "kind": "submap", "encoder": "bev-netvlad",
                 "dir": "bev-benchmark", "dtype": "float16",
                 "files": {"model.json": {"sha256": "...", "bytes": 1234}, ...},
                 "trained_with": "pnvlad train -c bev ...", "data": "...",
                 "figures": {"recall@1": 97.1, ...}, "date": "2026-12-05", ...}]}

A model reference that starts with ``pretrained:`` (:data:`PREFIX`; a colon no relative path
of ours holds) names a catalogue entry: :func:`resolve` checks every file of the entry against
the catalogue's SHA-256 and returns its directory, which every command then reads as any model
directory (``store.resolve_model_dir`` calls it). ``PNVLAD_PRETRAINED`` (:data:`CATALOGUE_ENV`)
names another catalogue file (tests, a private set of models).

Stored dtype: the weights' matrices and convolution kernels are stored as float16 when the
model was packaged with ``--fp16`` (vectors, and any tensor outside float16's range, stay
float32); torch's ``load_state_dict`` and ONNX Runtime's constant folding restore float32
when the model is loaded, so the runtime computes in float32 from the rounded weights.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from pnvlad_service.errors import InputError
from pnvlad_service.fileio import atomic_write_text, sha256_file

#: How a model reference names a pretrained model instead of a directory.
PREFIX = "pretrained:"
#: Environment variable naming another catalogue file.
CATALOGUE_ENV = "PNVLAD_PRETRAINED"
CATALOGUE_FILE = "catalogue.json"
#: The catalogue of the models that ship in the package.
PACKAGE_CATALOGUE = Path(__file__).resolve().parents[1] / "pretrained" / CATALOGUE_FILE
FORMAT = "pnvlad-pretrained"
VERSION = 1
#: The kinds of query a model is trained for.
KINDS = ("submap", "scan")
#: A model's files together at most (every file stays below GitHub's 50 MiB warning).
MAX_MODEL_BYTES = 48 * 2**20
#: All pretrained models together at most (the wheel stays far below PyPI's 100 MiB cap).
MAX_TOTAL_BYTES = 64 * 2**20
#: Names: lower-case letters, digits and dashes (a directory name on every system).
NAME_RE = re.compile(r"^[a-z0-9][a-z0-9-]{0,63}$")

#: sha256 of files already checked in this process: (path, size, mtime_ns) -> hex.
_VERIFIED: dict[tuple[str, int, int], str] = {}

__all__ = [
    "CATALOGUE_ENV",
    "MAX_MODEL_BYTES",
    "MAX_TOTAL_BYTES",
    "PACKAGE_CATALOGUE",
    "PREFIX",
    "SERVING_FILES",
    "Catalogue",
    "Entry",
    "FileRecord",
    "default_catalogue",
    "is_pretrained",
    "make_serving_only",
    "refuse_pretrained",
    "resolve",
]


def default_catalogue() -> Path:
    """The catalogue file in use: ``$PNVLAD_PRETRAINED`` when set, else the package's own."""
    env = os.environ.get(CATALOGUE_ENV)
    if env:
        return Path(env)
    return PACKAGE_CATALOGUE


def is_pretrained(ref: str | Path) -> bool:
    """Whether the model reference ``ref`` names a pretrained model (``pretrained:NAME``)."""
    return str(ref).startswith(PREFIX)


@dataclass(frozen=True)
class FileRecord:
    """One file of a pretrained model: its SHA-256 (hex) and size in bytes."""

    sha256: str
    bytes: int


@dataclass(frozen=True)
class Entry:
    """One catalogue entry (see the module doc for the fields)."""

    name: str
    kind: str
    encoder: str
    dir: str
    dtype: str
    files: dict[str, FileRecord]
    trained_with: str = ""
    data: str = ""
    figures: dict[str, Any] = field(default_factory=dict)
    date: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def bytes(self) -> int:
        """The model's files together."""
        return sum(f.bytes for f in self.files.values())

    def to_json(self) -> dict[str, Any]:
        """The entry as the catalogue stores it (``extra``'s keys at the top level)."""
        doc = asdict(self)
        doc.pop("extra")
        doc.update(self.extra)
        return doc

    @classmethod
    def from_json(cls, doc: Any, source: Path) -> Entry:
        """An entry from its JSON object; :class:`InputError` naming ``source`` and the field."""
        if not isinstance(doc, dict):
            raise InputError("a catalogue entry is not an object", source)
        name = doc.get("name")
        if not isinstance(name, str) or not NAME_RE.match(name):
            raise InputError(f"catalogue entry with a bad 'name': {name!r}", source)
        for key in ("kind", "encoder", "dir", "dtype"):
            if not isinstance(doc.get(key), str):
                raise InputError(f"catalogue entry {name}: missing or bad {key!r}", source)
        if doc["kind"] not in KINDS:
            raise InputError(f"catalogue entry {name}: 'kind' must be one of {KINDS}", source)
        files = doc.get("files")
        if not isinstance(files, dict) or not files:
            raise InputError(f"catalogue entry {name}: missing or bad 'files'", source)
        try:
            records = {
                str(k): FileRecord(sha256=str(v["sha256"]), bytes=int(v["bytes"]))
                for k, v in files.items()
            }
        except (TypeError, KeyError, ValueError):
            raise InputError(
                f"catalogue entry {name}: each of 'files' needs 'sha256' and 'bytes'", source
            ) from None
        known = {f for f in cls.__dataclass_fields__ if f != "extra"}
        return cls(
            name=name,
            kind=doc["kind"],
            encoder=doc["encoder"],
            dir=doc["dir"],
            dtype=doc["dtype"],
            files=records,
            trained_with=str(doc.get("trained_with", "")),
            data=str(doc.get("data", "")),
            figures=dict(doc.get("figures") or {}),
            date=str(doc.get("date", "")),
            extra={k: v for k, v in doc.items() if k not in known},
        )


@dataclass(frozen=True)
class Catalogue:
    """The catalogue file at ``path`` and its entries in file order."""

    path: Path
    entries: tuple[Entry, ...]

    @property
    def root(self) -> Path:
        """The folder the entries' ``dir`` are relative to: the catalogue's own."""
        return self.path.parent

    @property
    def names(self) -> list[str]:
        """The entries' names, in file order."""
        return [e.name for e in self.entries]

    @property
    def bytes(self) -> int:
        """All entries' files together."""
        return sum(e.bytes for e in self.entries)

    @classmethod
    def read(cls, path: str | Path | None = None) -> Catalogue:
        """The catalogue at ``path`` (default :func:`default_catalogue`). A missing package
        catalogue is an empty one; a missing file named by ``path`` or ``$PNVLAD_PRETRAINED``,
        or a malformed one, is an :class:`InputError` naming it."""
        explicit = path is not None or bool(os.environ.get(CATALOGUE_ENV))
        path = Path(path) if path is not None else default_catalogue()
        if not path.is_file():
            if explicit:
                raise InputError("no such pretrained catalogue file", path)
            return cls(path, ())
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise InputError(f"unreadable pretrained catalogue ({exc})", path) from None
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            raise InputError(f"not a {FORMAT} catalogue (missing or wrong 'format')", path)
        if doc.get("version") != VERSION:
            raise InputError(
                f"unsupported catalogue version {doc.get('version')!r} (this pnvlad reads "
                f"version {VERSION})",
                path,
            )
        models = doc.get("models")
        if not isinstance(models, list):
            raise InputError("'models' must be a list", path)
        entries = tuple(Entry.from_json(m, path) for m in models)
        names = [e.name for e in entries]
        if len(set(names)) != len(names):
            raise InputError("the same model name twice in the catalogue", path)
        return cls(path, entries)

    def to_json(self) -> dict[str, Any]:
        """The catalogue file's document."""
        return {
            "format": FORMAT,
            "version": VERSION,
            "models": [e.to_json() for e in self.entries],
        }

    def get(self, name: str) -> Entry:
        """The entry ``name``; :class:`InputError` listing the known names otherwise."""
        for entry in self.entries:
            if entry.name == name:
                return entry
        known = ", ".join(self.names) if self.entries else "none ship with this install"
        raise InputError(
            f"unknown pretrained model; known: {known} (pnvlad model list)", f"{PREFIX}{name}"
        )

    def directory(self, entry: Entry) -> Path:
        """The model directory of ``entry``."""
        return self.root / entry.dir

    def problems(self, entry: Entry) -> list[str]:
        """What is wrong with ``entry``'s files on disk (missing, other size, other SHA-256),
        one line each naming the file; empty when every file verifies."""
        out = []
        directory = self.directory(entry)
        for fname, rec in entry.files.items():
            path = directory / fname
            try:
                st = path.stat()
            except OSError:
                out.append(f"{path}: missing")
                continue
            if st.st_size != rec.bytes:
                out.append(f"{path}: {st.st_size} bytes, the catalogue records {rec.bytes}")
                continue
            if _sha256(path, st) != rec.sha256:
                out.append(f"{path}: SHA-256 differs from the catalogue's")
        return out


def _sha256(path: Path, st: Any) -> str:
    """``sha256_file(path)``, remembered for this process while size and mtime stay."""
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    if key not in _VERIFIED:
        _VERIFIED[key] = sha256_file(path)
    return _VERIFIED[key]


def resolve(ref: str | Path, catalogue: str | Path | None = None) -> Path:
    """The model directory of ``pretrained:NAME`` after checking its files against the
    catalogue. :class:`InputError` listing the known names for an unknown one, and naming the
    file for one that is missing or corrupt (reinstall pnvlad)."""
    name = str(ref)[len(PREFIX) :] if is_pretrained(ref) else str(ref)
    cat = Catalogue.read(catalogue)
    entry = cat.get(name)
    problems = cat.problems(entry)
    if problems:
        first = problems[0]
        path, _, why = first.partition(": ")
        raise InputError(
            f"pretrained model {name}: {why} (corrupt or changed install: reinstall pnvlad)",
            path,
        )
    return cat.directory(entry)


#: The files a model needs where it only serves, with ONNX Runtime (no torch).
SERVING_FILES = ("model.json", "model.onnx")


def make_serving_only(catalogue: str | Path | None = None) -> list[Path]:
    """Leave every model of the catalogue with only :data:`SERVING_FILES`, for an install that
    embeds with ONNX Runtime alone (the server image, which has no torch to read the weights):
    the catalogue is rewritten (atomically) without the other files' records, then those files
    are deleted. Returns the deleted paths. Every file is checked first; a model without
    ``model.onnx``, or any file that does not verify, is an :class:`InputError` naming it, and
    nothing changes. The models then load as serving-only directories
    (``store.is_serving_only``)."""
    cat = Catalogue.read(catalogue)
    for entry in cat.entries:
        missing = [f for f in SERVING_FILES if f not in entry.files]
        if missing:
            raise InputError(
                f"pretrained model {entry.name} has no {missing[0]}: it cannot serve without torch",
                cat.directory(entry),
            )
        problems = cat.problems(entry)
        if problems:
            path, _, why = problems[0].partition(": ")
            raise InputError(f"pretrained model {entry.name}: {why}", path)
    slim = tuple(
        replace(e, files={k: v for k, v in e.files.items() if k in SERVING_FILES})
        for e in cat.entries
    )
    dropped = [
        cat.directory(e) / fname
        for e in cat.entries
        for fname in e.files
        if fname not in SERVING_FILES
    ]
    atomic_write_text(cat.path, json.dumps(Catalogue(cat.path, slim).to_json(), indent=2) + "\n")
    for path in dropped:
        path.unlink(missing_ok=True)
    return dropped


def refuse_pretrained(ref: str | Path) -> None:
    """:class:`InputError` when ``ref`` names a pretrained model, for the functions that would
    write into the model directory (its files are checked against the catalogue)."""
    if is_pretrained(ref):
        raise InputError(
            "a pretrained model's files are checked against its catalogue and are not "
            "rewritten: copy its directory (pnvlad model info shows it) and use the copy",
            str(ref),
        )


def hint(path: str | Path) -> str:
    """`` (did you mean pretrained:NAME?)`` when ``path`` is a bare pretrained name; else
    empty. For the error of a model directory that does not exist."""
    text = str(path)
    if not NAME_RE.match(text):
        return ""
    try:
        names = Catalogue.read().names
    except InputError:
        return ""
    return f" (did you mean {PREFIX}{text}?)" if text in names else ""
