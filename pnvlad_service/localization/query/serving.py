"""The map in service, and swapping it for a new one while it serves.

:class:`ServingMap` holds the :class:`~.localizer.Localizer` that answers. A caller takes a
*lease* (:meth:`ServingMap.lease`) for the whole of one query, and every step of that query
(embed, search, verify, answer) runs on the localiser the lease gave: an answer comes from one
bundle and names it (``Localizer.info``), never a mix of two.

:meth:`ServingMap.reload` loads the new bundle beside the old one (a new ``Localizer``: the
bundle's checks, the model identity check, its own micro-batcher and verification child; the
encoder is shared when the model is the same, else loaded and warmed up), then swaps it in
under a lock, so that the next lease gets the new one, waits for the old one's leases to end
and closes it. A bundle that fails its checks raises before anything is swapped: the old one
keeps serving. Reloads run one at a time (a second one while one is in progress is refused:
:class:`ReloadInProgress`).

No HTTP here: the server's admin route and its SIGHUP handler call :meth:`reload`; a library
user with many threads can hold a ``ServingMap`` the same way.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pnvlad_service.errors import InputError, NotReadyError, PnvladError
from pnvlad_service.localization.query.localizer import Localizer

log = logging.getLogger(__name__)

#: (index, model, encoder to reuse or None) -> a loaded, not yet serving Localizer.
Loader = Callable[[Path, Path, Any], Localizer]


class ReloadInProgress(PnvladError):
    """Another reload is running."""


@dataclass(frozen=True)
class Reload:
    """What a reload did: the bundle before and after (``LocalizerInfo`` JSON), whether the
    encoder was reused, the seconds spent loading, swapping, and draining the old one."""

    previous: dict[str, Any]
    current: dict[str, Any]
    index: str
    encoder_reused: bool
    load_s: float
    drain_s: float

    def to_json(self) -> dict[str, Any]:
        return {
            "previous": self.previous,
            "current": self.current,
            "index_path": self.index,
            "encoder_reused": self.encoder_reused,
            "load_s": round(self.load_s, 3),
            "drain_s": round(self.drain_s, 3),
        }


class _Slot:
    """One localiser in service and the leases on it."""

    def __init__(self, localizer: Localizer, index: Path) -> None:
        self.localizer = localizer
        self.index = index
        self.users = 0


class ServingMap:
    """The localiser in service (see the module doc). ``loader(index, model, encoder)`` makes
    a new one for :meth:`reload`; ``index`` is where the first one's bundle was loaded from
    (a reload without a path reads it again: ``pnvlad index add`` rewrites a bundle in place,
    atomically); ``drain_s``: how long a reload waits for the old localiser's queries before it
    closes it anyway."""

    def __init__(
        self,
        localizer: Localizer,
        index: str | Path,
        loader: Loader,
        *,
        drain_s: float = 30.0,
        on_swap: Callable[[Localizer], None] | None = None,
    ) -> None:
        self._slot = _Slot(localizer, Path(index))
        self._loader = loader
        self._lock = threading.Condition()
        self._reloading = threading.Lock()
        self._closed = False
        self.drain_s = drain_s
        self.on_swap = on_swap
        self.reloads = 0

    @property
    def current(self) -> Localizer:
        """The localiser a new lease would get (a snapshot)."""
        return self._slot.localizer

    @property
    def index(self) -> Path:
        """Where the serving bundle was loaded from."""
        return self._slot.index

    @contextlib.contextmanager
    def lease(self) -> Iterator[Localizer]:
        """The localiser in service, kept open until the block ends (a reload waits for it
        before closing the localiser it replaced)."""
        with self._lock:
            if self._closed:
                raise NotReadyError("the service is shutting down")
            slot = self._slot
            slot.users += 1
        try:
            yield slot.localizer
        finally:
            with self._lock:
                slot.users -= 1
                self._lock.notify_all()

    def reload(self, index: str | Path | None = None, model: str | Path | None = None) -> Reload:
        """Load the bundle at ``index`` (default: the serving one's path, read again) with
        ``model`` (default: the serving model), swap it in, close the old one. The loader's
        errors (an ``InputError`` naming the file for a missing, corrupt or truncated bundle or
        one built with other weights) propagate and nothing changes.
        :class:`ReloadInProgress` while another reload runs."""
        if not self._reloading.acquire(blocking=False):
            raise ReloadInProgress("a reload is already in progress; try again when it is done")
        try:
            old = self._slot
            path = Path(index) if index is not None else old.index
            t0 = time.perf_counter()
            serving_model = Path(old.localizer.identity.checkpoint)
            model_path = serving_model if model is None else Path(model)
            same_model = model_path.resolve() == serving_model.resolve()
            reuse = old.localizer.encoder if same_model else None
            try:
                new = self._loader(path, model_path, reuse)
            except PnvladError:
                raise
            except (OSError, RuntimeError, ValueError) as exc:  # e.g. FAISS on a broken file
                raise InputError(f"cannot load this bundle: {exc}", path) from exc
            if new.encoder is not reuse:
                reuse = None
            load_s = time.perf_counter() - t0
            with self._lock:
                if self._closed:
                    new.owns_encoder = reuse is None
                    new.close()
                    raise NotReadyError("the service is shutting down")
                self._slot = _Slot(new, path)
                self.reloads += 1
            if self.on_swap is not None:
                self.on_swap(new)
            log.info(
                "serving bundle %s (%s, %d vectors) from %s; was %s",
                new.info.index.id,
                new.info.index.key,
                new.info.index.count,
                path,
                old.localizer.info.index.id,
            )
            drain_s = self._retire(old, keep_encoder=reuse is not None)
            return Reload(
                previous=old.localizer.info.to_json(),
                current=new.info.to_json(),
                index=str(path),
                encoder_reused=reuse is not None,
                load_s=load_s,
                drain_s=drain_s,
            )
        finally:
            self._reloading.release()

    def _retire(self, slot: _Slot, keep_encoder: bool) -> float:
        """Wait for ``slot``'s leases to end (at most ``drain_s``), then close its localiser
        (not the encoder it hands on). Seconds waited."""
        t0 = time.perf_counter()
        deadline = time.monotonic() + self.drain_s
        with self._lock:
            while slot.users > 0:
                left = deadline - time.monotonic()
                if left <= 0:
                    log.warning(
                        "%d queries still on bundle %s after %.0f s; closing it",
                        slot.users,
                        slot.localizer.info.index.id,
                        self.drain_s,
                    )
                    break
                self._lock.wait(left)
        if keep_encoder:
            slot.localizer.owns_encoder = False
        slot.localizer.close()
        return time.perf_counter() - t0

    def close(self) -> None:
        """Stop serving: new leases are refused; the localiser in service is closed."""
        with self._reloading, self._lock:  # not in the middle of a swap
            self._closed = True
            slot = self._slot
        slot.localizer.close()
