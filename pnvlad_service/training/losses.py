"""Metric-learning losses of PointNetVLAD: (lazy) triplet and (lazy) quadruplet.

All distances are squared Euclidean between descriptors. For a tuple ``b`` with query q,
positives p_j, negatives n_i and one extra negative o (not close to q nor to any n_i)::

    d_pos        = min_j |q - p_j|^2           ("best positive", as the published code;
                                                 ``hardest_positive=True`` takes the max)
    triplet_b    = AGG_i [alpha + d_pos - |q - n_i|^2]_+
    second_b     = AGG_i [beta  + d_pos - |o - n_i|^2]_+
    triplet      = mean_b triplet_b
    quadruplet   = mean_b triplet_b + mean_b second_b

AGG is the sum over negatives for the plain losses and the max for the *lazy* ones; alpha = 0.5,
beta = 0.2 by default. This mirrors ``triplet_loss``, ``lazy_triplet_loss``, ``quadruplet_loss``
and ``lazy_quadruplet_loss`` of the published TensorFlow code (mikacuy/pointnetvlad), including
the mean over the batch; ``ignore_zero_loss=True`` divides by the number of tuples with a
non-zero loss instead (an option of the PyTorch port).

Shapes: query float [B, D], positives [B, P, D], negatives [B, Nn, D], other_neg [B, D].
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from pnvlad_service.errors import InputError

if TYPE_CHECKING:
    import torch

ALPHA = 0.5
BETA = 0.2


def _check(
    query: torch.Tensor,
    positives: torch.Tensor,
    negatives: torch.Tensor,
    other_neg: torch.Tensor | None = None,
) -> None:
    if query.dim() != 2:
        raise InputError(f"query must be [B, D], got {list(query.shape)}", "query")
    b, d = query.shape
    for name, t in (("positives", positives), ("negatives", negatives)):
        if t.dim() != 3 or t.shape[0] != b or t.shape[2] != d or t.shape[1] < 1:
            raise InputError(f"{name} must be [{b}, >=1, {d}], got {list(t.shape)}", name)
    if other_neg is not None and tuple(other_neg.shape) != (b, d):
        raise InputError(f"other_neg must be [{b}, {d}], got {list(other_neg.shape)}", "other_neg")


def positive_distance(
    query: torch.Tensor, positives: torch.Tensor, hardest: bool = False
) -> torch.Tensor:
    """Squared distance [B] from each query to its closest positive (farthest if ``hardest``)."""
    d = ((positives - query.unsqueeze(1)) ** 2).sum(dim=2)  # [B, P]
    return d.amax(dim=1) if hardest else d.amin(dim=1)


def _reduce(per_tuple: torch.Tensor, ignore_zero_loss: bool) -> torch.Tensor:
    if ignore_zero_loss:
        hard = (per_tuple > 1e-16).sum()
        return per_tuple.sum() / (hard + 1e-16)
    return per_tuple.mean()


def _hinge_term(
    anchor: torch.Tensor,
    d_pos: torch.Tensor,
    negatives: torch.Tensor,
    margin: float,
    lazy: bool,
) -> torch.Tensor:
    """Per tuple [B]: AGG_i [margin + d_pos - |anchor - n_i|^2]_+ (AGG = max if lazy else sum)."""
    d_neg = ((negatives - anchor.unsqueeze(1)) ** 2).sum(dim=2)  # [B, Nn]
    hinge = (margin + d_pos.unsqueeze(1) - d_neg).clamp(min=0.0)
    return hinge.amax(dim=1) if lazy else hinge.sum(dim=1)


def triplet_loss(
    query: torch.Tensor,
    positives: torch.Tensor,
    negatives: torch.Tensor,
    other_neg: torch.Tensor | None = None,
    *,
    margin: float = ALPHA,
    second_margin: float = BETA,
    lazy: bool = False,
    hardest_positive: bool = False,
    ignore_zero_loss: bool = False,
) -> torch.Tensor:
    """Triplet loss (scalar): mean over tuples of the sum (``lazy``: max) over negatives of
    ``[margin + d(q, best positive) - d(q, n_i)]_+``. ``other_neg`` and ``second_margin`` are
    accepted and ignored so every loss here takes the same arguments."""
    _check(query, positives, negatives)
    d_pos = positive_distance(query, positives, hardest_positive)
    return _reduce(_hinge_term(query, d_pos, negatives, margin, lazy), ignore_zero_loss)


def quadruplet_loss(
    query: torch.Tensor,
    positives: torch.Tensor,
    negatives: torch.Tensor,
    other_neg: torch.Tensor | None = None,
    *,
    margin: float = ALPHA,
    second_margin: float = BETA,
    lazy: bool = False,
    hardest_positive: bool = False,
    ignore_zero_loss: bool = False,
) -> torch.Tensor:
    """Quadruplet loss (scalar): the triplet loss plus the mean over tuples of the sum (``lazy``:
    max) over negatives of ``[second_margin + d(q, best positive) - d(other_neg, n_i)]_+``."""
    if other_neg is None:
        raise InputError("the quadruplet loss needs other_neg [B, D]", "other_neg")
    _check(query, positives, negatives, other_neg)
    d_pos = positive_distance(query, positives, hardest_positive)
    first = _hinge_term(query, d_pos, negatives, margin, lazy)
    second = _hinge_term(other_neg, d_pos, negatives, second_margin, lazy)
    return _reduce(first, ignore_zero_loss) + _reduce(second, ignore_zero_loss)


def lazy_triplet_loss(
    query: torch.Tensor,
    positives: torch.Tensor,
    negatives: torch.Tensor,
    other_neg: torch.Tensor | None = None,
    **kwargs: object,
) -> torch.Tensor:
    """:func:`triplet_loss` with the max over negatives (the hardest negative per tuple)."""
    return triplet_loss(query, positives, negatives, other_neg, lazy=True, **kwargs)  # type: ignore[arg-type]


def lazy_quadruplet_loss(
    query: torch.Tensor,
    positives: torch.Tensor,
    negatives: torch.Tensor,
    other_neg: torch.Tensor | None = None,
    **kwargs: object,
) -> torch.Tensor:
    """:func:`quadruplet_loss` with the max over negatives: the paper's training loss."""
    return quadruplet_loss(query, positives, negatives, other_neg, lazy=True, **kwargs)  # type: ignore[arg-type]


LossFn = Callable[..., "torch.Tensor"]

#: Losses by name, all called as ``fn(query, positives, negatives, other_neg, **options)``.
LOSSES: dict[str, LossFn] = {
    "triplet": triplet_loss,
    "lazy_triplet": lazy_triplet_loss,
    "quadruplet": quadruplet_loss,
    "lazy_quadruplet": lazy_quadruplet_loss,
}


def get_loss(name: str) -> LossFn:
    """The loss called ``name`` (one of :data:`LOSSES`); raises InputError naming the choices."""
    try:
        return LOSSES[name]
    except KeyError:
        raise InputError(
            f"unknown loss {name!r}; choose one of {', '.join(sorted(LOSSES))}", "loss"
        ) from None
