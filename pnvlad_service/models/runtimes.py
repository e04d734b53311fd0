"""Which runtime embeds with a model directory: torch (:class:`~.inference.Encoder`) or ONNX
Runtime (:class:`~.onnx_encoder.OnnxEncoder`, ``model.onnx`` beside the weights).

``runtime="auto"`` takes torch when it is installed, else ONNX Runtime when the directory has
``model.onnx`` (and ONNX Runtime for a serving-only directory, which has no weights for torch:
``store.is_serving_only``); ``"torch"`` and ``"onnx"`` insist. A choice that cannot be had is an
error that says what to install or export. This module imports neither runtime at module level.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pnvlad_service.errors import InputError, MissingDependencyError
from pnvlad_service.models.onnx_encoder import ONNX_FILE

if TYPE_CHECKING:
    from pnvlad_service.models.store import ModelIdentity

#: The values ``runtime`` takes (``--runtime``, ``PNVLAD_RUNTIME``).
RUNTIMES = ("auto", "torch", "onnx")


def torch_installed() -> bool:
    """Whether torch can be imported here (without importing it)."""
    try:
        return importlib.util.find_spec("torch") is not None
    except (ValueError, ImportError):  # a stub in sys.modules (tests block torch so)
        return False


def choose_runtime(directory: str | Path, runtime: str = "auto") -> str:
    """``"torch"`` or ``"onnx"`` for the model directory ``directory`` (resolved already)."""
    if runtime not in RUNTIMES:
        raise InputError(f"runtime must be one of {list(RUNTIMES)}, got {runtime!r}", "runtime")
    from pnvlad_service.models.store import is_serving_only

    has_onnx = (Path(directory) / ONNX_FILE).is_file()
    auto_torch = runtime == "auto" and torch_installed() and not is_serving_only(directory)
    if runtime == "torch" or auto_torch:
        if not torch_installed():
            raise MissingDependencyError("torch", "torch", "the torch runtime")
        return "torch"
    if not has_onnx:
        if runtime == "auto":
            raise InputError(
                f"torch is not installed and the model directory has no {ONNX_FILE}: export it "
                f"where torch is (pnvlad model export {directory}), or install pnvlad[torch]",
                directory,
            )
        raise InputError(
            f"no {ONNX_FILE} in this model directory: pnvlad model export {directory}",
            directory,
        )
    return "onnx"


def open_encoder(
    directory: str | Path,
    *,
    runtime: str = "auto",
    device: str | None = None,
    weights_sha256: str | None = None,
    threads: int | None = None,
) -> Any:
    """The encoder of the model directory ``directory`` on the runtime :func:`choose_runtime`
    picks. ``device`` is torch's (ONNX Runtime runs on the CPU: another device is an error);
    ``threads``: ONNX Runtime's (torch's are process-wide, ``set_threads``)."""
    from pnvlad_service.models.store import resolve_model_dir

    directory = resolve_model_dir(directory)
    chosen = choose_runtime(directory, runtime)
    if chosen == "onnx":
        if device not in (None, "cpu"):
            raise InputError(f"the ONNX runtime runs on the CPU, not on {device!r}", "device")
        from pnvlad_service.models.onnx_encoder import OnnxEncoder

        return OnnxEncoder.from_checkpoint(
            directory, weights_sha256=weights_sha256, threads=threads
        )
    from pnvlad_service.models.inference import Encoder

    return Encoder.from_checkpoint(directory, device=device, weights_sha256=weights_sha256)


def load_encoder(
    model: str | Path,
    device: str | None = None,
    identity: ModelIdentity | None = None,
    *,
    runtime: str = "auto",
    threads: int | None = None,
) -> Any:
    """The encoder of a model directory or of the training run that made it: the one door every
    stage that embeds goes through (the index builder, the localizer, the benchmarks).

    :func:`open_encoder` on ``runtime`` (``auto``: torch when installed, else ONNX Runtime with
    ``model.onnx``); ``identity``, when the caller has it, spares hashing the weights again;
    ``threads``: ONNX Runtime's."""
    sha = identity.weights_sha256 if identity is not None else None
    return open_encoder(model, runtime=runtime, device=device, weights_sha256=sha, threads=threads)


def describe(encoder: Any) -> str:
    """One line naming the runtime of ``encoder`` and its version (logs, /readyz)."""
    runtime = getattr(encoder, "runtime", None)
    if runtime == "onnx":
        return encoder.describe()
    if runtime == "torch":
        import torch

        from pnvlad_service.models.inference import on_torch_thread

        # Asked on the thread that embeds: OpenMP keeps a count per thread, and a thread that
        # registered with small_gicp or ran a cloud worker may hold another than the encoder's.
        on_cpu = getattr(getattr(encoder, "device", None), "type", "cpu") == "cpu"
        threads = on_torch_thread(torch.get_num_threads) if on_cpu else torch.get_num_threads()
        return f"torch {torch.__version__}, {threads} threads"
    return type(encoder).__name__
