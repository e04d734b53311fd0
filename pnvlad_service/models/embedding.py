"""One way to turn many clouds into descriptors: the embedder protocol and chunked embedding.

Training (validation and the hard-negative cache), evaluation and index building all embed
more clouds than fit in memory at once; each reads a chunk, embeds it and fills its rows of one
float32 [N, D] array through :func:`embed_in_chunks`. :func:`module_embedder` turns a
``torch.nn.Module`` into an embedder (eval mode while embedding, inference mode, batches).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

if TYPE_CHECKING:
    import torch

#: ``embed(points float32 [B, N, 3]) -> float32 [B, D]``, rows of unit L2 norm.
EmbedFn = Callable[[np.ndarray], np.ndarray]


def over_scales(
    forward: Callable[[Any], Any], x: Any, scales: tuple[float, ...], l2: Callable[[Any], Any]
) -> Any:
    """``forward(x)``, or with ``scales`` (``ModelConfig.embed_scales``) the sum of
    ``forward(x * s)`` over them made a unit row again by ``l2``: the descriptors of one batch
    ``x`` [B, N, 3] (numpy or torch, as ``forward`` takes) averaged over the scales."""
    if not scales:
        return forward(x)
    total = forward(x * scales[0])
    for s in scales[1:]:
        total = total + forward(x * s)
    return l2(total)


def unit_rows(a: np.ndarray) -> np.ndarray:
    """``a`` [B, D] with each row divided by its L2 norm (at least 1e-12)."""
    return a / np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)


class Embedder(Protocol):
    """What embeds clouds (``models.inference.Encoder`` fits)."""

    dim: int

    def embed(self, points: np.ndarray) -> np.ndarray:
        """float [B, N, 3] -> float32 [B, dim], rows of unit L2 norm."""
        ...


def embed_in_chunks(
    embed: EmbedFn,
    count: int,
    load: Callable[[int, int], np.ndarray],
    *,
    chunk: int = 256,
    progress: bool = False,
    desc: str = "embedding",
) -> np.ndarray:
    """float32 [count, D]: rows ``start:stop`` are ``embed(load(start, stop))``.

    ``load(start, stop)`` returns the clouds float32 [stop - start, N, 3]; memory holds one
    chunk of clouds and the descriptors, never all the clouds. ``count == 0`` gives [0, 0].
    """
    from pnvlad_service.progress import tqdm

    out: np.ndarray | None = None
    with tqdm(total=count, desc=desc, unit="cloud", disable=not progress) as bar:
        for start in range(0, count, chunk):
            stop = min(start + chunk, count)
            desc_chunk = np.asarray(embed(load(start, stop)), dtype=np.float32)
            if out is None:
                out = np.empty((count, desc_chunk.shape[1]), dtype=np.float32)
            out[start:stop] = desc_chunk
            bar.update(stop - start)
    return out if out is not None else np.zeros((0, 0), dtype=np.float32)


def quarter_turn(points: np.ndarray, k: int) -> np.ndarray:
    """``points`` float [..., 3+] turned about z by ``k`` quarter turns, exactly (x, y) ->
    (-y, x) per quarter: no rounding, so turn 0 is the points themselves."""
    k %= 4
    if k == 0:
        return points
    out = np.array(points, copy=True)
    x, y = points[..., 0], points[..., 1]
    out[..., 0], out[..., 1] = {1: (-y, x), 2: (-x, -y), 3: (y, -x)}[k]
    return out


def turned_embedder(embed: EmbedFn, turns: int) -> EmbedFn:
    """An embed function whose row for each cloud holds its descriptors at ``turns`` headings
    a quarter turn apart (1, 2 or 4), side by side: float32 [B, turns * D], the first D the
    cloud as it is. A map is embedded so when its model turns each cloud to its own dominant
    direction (``ModelConfig.canonical_heading``), which a scan from another heading meets
    within a quarter turn (:func:`pnvlad_service.models.config.map_turns`). The function
    carries ``turns`` as an attribute."""
    if turns not in (1, 2, 4):
        raise ValueError(f"turns must be 1, 2 or 4, got {turns}")
    if turns == 1:
        return embed

    def fn(points: np.ndarray) -> np.ndarray:
        x = np.asarray(points)
        step = 4 // turns
        desc = np.asarray(
            embed(np.concatenate([quarter_turn(x, k * step) for k in range(turns)])),
            dtype=np.float32,
        )
        b = len(x)
        return desc.reshape(turns, b, -1).transpose(1, 0, 2).reshape(b, -1)

    fn.turns = turns  # type: ignore[attr-defined]
    return fn


def module_embedder(
    model: torch.nn.Module,
    device: torch.device | str = "cpu",
    *,
    batch: int = 64,
    amp_dtype: Any = None,
) -> EmbedFn:
    """An embed function from a ``torch.nn.Module``: eval mode while embedding (the caller's
    mode is restored), inference mode, ``batch`` clouds at a time, autocast to ``amp_dtype``
    when given; returns float32 on the host."""
    import torch

    device = torch.device(device)

    def embed(points: np.ndarray | torch.Tensor) -> np.ndarray:
        was = model.training
        model.eval()
        out = []
        try:
            with torch.inference_mode():
                for s in range(0, len(points), batch):
                    x = torch.as_tensor(points[s : s + batch], dtype=torch.float32)
                    x = x.to(device, non_blocking=True)
                    with torch.autocast(
                        device.type, dtype=amp_dtype, enabled=amp_dtype is not None
                    ):
                        out.append(model(x).float().cpu().numpy())
        finally:
            model.train(was)
        if not out:
            return np.zeros((0, 0), dtype=np.float32)
        return np.concatenate(out).astype(np.float32, copy=False)

    return embed
