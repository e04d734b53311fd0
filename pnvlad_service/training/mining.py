"""Choosing what a training step looks at: tuples, hard negatives, in-batch mining.

Tuple mode (the paper): a tuple is 1 anchor, P positives, Nn negatives and 1 "other negative"
(a submap that is not a neighbour of any cloud of the tuple). Once a descriptor cache of the
whole training set exists, ``hard`` of the negatives are the closest (squared Euclidean distance
of cached descriptors) among ``sampled`` random negatives of the anchor; the rest are random.

In-batch mode: a batch of anchors plus one positive each; every pair of the batch is labelled
positive / negative from the training set, and for each anchor the hardest positive and the
closest negatives of the batch form its tuple, so every embedding of the step is reused.

Everything here works on indices and NumPy / torch arrays under ``no_grad``; the losses live in
``losses.py``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from pnvlad_service.data.dataset import TrainingSet
from pnvlad_service.errors import InputError

log = logging.getLogger(__name__)


def closest(anchor: np.ndarray, candidates: np.ndarray, k: int) -> np.ndarray:
    """Positions (int64 [min(k, C)]) of the ``k`` rows of ``candidates`` float32 [C, D] closest
    to ``anchor`` float32 [D] in squared Euclidean distance, closest first (ties: lower index)."""
    d2 = ((candidates.astype(np.float64) - anchor.astype(np.float64)) ** 2).sum(axis=1)
    return np.argsort(d2, kind="stable")[:k]


def pick_negatives(
    rng: np.random.Generator,
    ts: TrainingSet,
    anchor: int,
    count: int,
    *,
    cache: np.ndarray | None = None,
    hard: int = 0,
    sampled: int = 3000,
) -> np.ndarray:
    """int64 [count] negatives of ``anchor``: without a cache, random ones; with a cache
    (float32 [N, D]), the ``hard`` closest to the anchor's cached descriptor among ``sampled``
    random negatives, then random ones from the rest of the sample. Repeats only when the anchor
    has fewer than ``count`` negatives."""
    if cache is None or hard == 0:
        neg = ts.sample_negatives(rng, anchor, count)
    else:
        pool = ts.sample_negatives(rng, anchor, max(sampled, count))
        order = closest(cache[anchor], cache[pool], hard)
        rest = np.setdiff1d(np.arange(len(pool)), order, assume_unique=True)
        fill = rng.permutation(rest)[: count - len(order)]
        neg = pool[np.concatenate([order, fill])]
    if len(neg) == 0:
        raise ValueError(f"submap {anchor} has no negatives")
    if len(neg) < count:
        neg = np.concatenate([neg, rng.choice(neg, count - len(neg))])
    return neg.astype(np.int64)


def pick_other_negative(
    rng: np.random.Generator,
    ts: TrainingSet,
    anchor: int,
    positives: np.ndarray,
    negatives: np.ndarray,
    tries: int = 16,
) -> int:
    """A random negative of the anchor that is neither in the tuple nor a positive of the anchor
    or of any of its negatives (the published rule). Where no submap qualifies (a small tree),
    the last condition is dropped: a random negative of the anchor outside the tuple."""
    banned = {anchor, *positives.tolist(), *negatives.tolist(), *ts.positives[anchor].tolist()}
    in_tuple = set(banned)
    for n in np.unique(negatives):
        banned.update(ts.positives[int(n)].tolist())
    for _ in range(tries):  # cheap: most negatives qualify on a real benchmark
        for c in ts.sample_negatives(rng, anchor, 16).tolist():
            if c not in banned:
                return int(c)
    everyone = rng.permutation(len(ts))
    cand = everyone[ts.negative_mask(anchor, everyone)]
    for pool in (banned, in_tuple):
        ok = [c for c in cand.tolist() if c not in pool]
        if ok:
            return int(ok[0])
    raise ValueError(f"submap {anchor} has no negative outside its tuple")


def negative_counts(ts: TrainingSet, indices: np.ndarray, block: int = 256) -> np.ndarray:
    """int64 [len(indices)]: how many negatives each of the submaps ``indices`` has in ``ts``
    (the other submaps that :meth:`TrainingSet.negative_mask` accepts)."""
    indices = np.asarray(indices, dtype=np.int64)
    n = len(ts)
    if ts.near is not None:
        return np.array(
            [n - len(np.unique(np.append(ts.near[i], i))) for i in indices.tolist()],
            dtype=np.int64,
        )
    out = np.empty(len(indices), dtype=np.int64)
    north, east = ts.positions[:, 0], ts.positions[:, 1]
    for s in range(0, len(indices), block):  # [block, N] distances at a time
        rows = ts.positions[indices[s : s + block]]
        d2 = (rows[:, :1] - north[None, :]) ** 2 + (rows[:, 1:] - east[None, :]) ** 2
        out[s : s + block] = (d2 > ts.negative_radius**2).sum(axis=1)
    return out


def fit_negatives(
    ts: TrainingSet, anchors: np.ndarray, negatives: int, hard: int
) -> tuple[int, int]:
    """(negatives, hard negatives) a tuple takes on this training set: the configured ones, or
    fewer where an anchor has too few negatives to fill a tuple and still leave one submap out
    of it for the other negative (a warning says so). Raises :class:`InputError` naming the
    option when an anchor has fewer than 2 negatives (no tuple can be built)."""
    if len(anchors) == 0:
        return negatives, hard
    counts = negative_counts(ts, anchors)
    worst = int(np.argmin(counts))
    fewest = int(counts[worst])
    room = fewest - 1  # one negative stays outside the tuple: the other negative
    if room >= negatives:
        return negatives, hard
    anchor = int(anchors[worst])
    if room < 1:
        raise InputError(
            f"the training set is too small for tuple mining: submap {anchor} has "
            f"{fewest} negative(s), a tuple needs at least 2 (a negative and the other "
            "negative); use a larger tree or --mining in_batch",
            source="train.mining",
        )
    log.warning(
        "train.negatives %d is more than this training set holds: submap %d has only %d "
        "negatives and a tuple also needs an other negative; using %d negatives a tuple "
        "(%d hard). Set train.negatives to %d or fewer in the config to silence this.",
        negatives,
        anchor,
        fewest,
        room,
        min(hard, room),
        room,
    )
    return room, min(hard, room)


@dataclass
class TupleBatch:
    """Indices of one step in tuple mode: ``anchors`` [B], ``positives`` [B, P],
    ``negatives`` [B, Nn], ``others`` [B] (all int64 indices into the training set)."""

    anchors: np.ndarray
    positives: np.ndarray
    negatives: np.ndarray
    others: np.ndarray

    def table(self) -> np.ndarray:
        """int64 [B, 1 + P + Nn + 1]: each tuple's clouds in order anchor, positives,
        negatives, other."""
        return np.concatenate(
            [self.anchors[:, None], self.positives, self.negatives, self.others[:, None]], axis=1
        )


def weighted_anchors(
    ts: TrainingSet, anchors: np.ndarray, weights: dict[str, float], seed: int
) -> np.ndarray:
    """The anchors an epoch walks when datasets are weighted (``data.dataset_weights``): each
    anchor of a dataset of weight w repeated int(w) times, and a seeded share w - int(w) of
    them once more; datasets not named keep weight 1. Raises :class:`InputError` naming the
    field for a name that is not one of the training set's datasets or a negative weight."""
    if not weights:
        return anchors
    names = [name for name, _, _ in ts.datasets]
    for name, w in weights.items():
        if name not in names:
            raise InputError(
                f"no training dataset {name!r} (have: {', '.join(names) or 'none'})",
                source="data.dataset_weights",
            )
        if not w >= 0:
            raise InputError(f"{name}: weight {w} is not >= 0", source="data.dataset_weights")
    rng = np.random.default_rng(seed)
    out = []
    for name, first, stop in ts.datasets:
        mine = anchors[(anchors >= first) & (anchors < stop)]
        w = float(weights.get(name, 1.0))
        whole, share = int(w), w - int(w)
        extra = round(share * len(mine))
        out += [mine] * whole
        if share > 0 and len(mine):
            out.append(np.sort(rng.choice(mine, extra, replace=False)))
        log.info(
            "dataset %s: %d anchors, weight %g: %d a epoch",
            name,
            len(mine),
            w,
            whole * len(mine) + extra,
        )
    return np.concatenate(out).astype(np.int64) if out else anchors[:0]


class AnchorSampler:
    """Walks the anchors in a fresh random order each epoch; its state is a small JSON dict, so a
    resumed run continues with exactly the same batches."""

    def __init__(self, anchors: np.ndarray, seed: int) -> None:
        if len(anchors) == 0:
            raise ValueError("no anchors (no training submap has enough positives)")
        self.anchors = np.asarray(anchors, dtype=np.int64)
        self.rng = np.random.default_rng(seed)
        self.epoch = 0
        self.pos = 0
        self.order = self.rng.permutation(self.anchors)

    def steps_per_epoch(self, batch: int) -> int:
        return max(1, len(self.anchors) // batch)

    def next(self, batch: int) -> np.ndarray:
        """int64 [batch] anchors; a new epoch starts when fewer than ``batch`` are left."""
        if self.pos + batch > len(self.order):
            self.epoch += 1
            self.pos = 0
            self.order = self.rng.permutation(self.anchors)
        if batch > len(self.order):
            raise ValueError(f"batch of {batch} but only {len(self.order)} anchors")
        out = self.order[self.pos : self.pos + batch]
        self.pos += batch
        return out

    def state(self) -> dict[str, Any]:
        return {
            "epoch": self.epoch,
            "pos": self.pos,
            "order": self.order.tolist(),
            "rng": self.rng.bit_generator.state,
        }

    def load_state(self, state: dict[str, Any]) -> None:
        self.epoch = int(state["epoch"])
        self.pos = int(state["pos"])
        self.order = np.asarray(state["order"], dtype=np.int64)
        self.rng.bit_generator.state = state["rng"]


def sample_tuples(
    rng: np.random.Generator,
    ts: TrainingSet,
    anchors: np.ndarray,
    *,
    positives: int = 2,
    negatives: int = 18,
    cache: np.ndarray | None = None,
    hard: int = 0,
    sampled: int = 3000,
) -> TupleBatch:
    """One tuple per anchor: ``positives`` random positives (with repeats only when there are
    too few), ``negatives`` negatives from :func:`pick_negatives`, one other negative."""
    pos_rows, neg_rows, others = [], [], []
    for a in anchors.tolist():
        cand = ts.positives[a]
        pos_rows.append(rng.choice(cand, positives, replace=len(cand) < positives))
        neg = pick_negatives(rng, ts, a, negatives, cache=cache, hard=hard, sampled=sampled)
        neg_rows.append(neg)
        others.append(pick_other_negative(rng, ts, a, pos_rows[-1], neg))
    return TupleBatch(
        np.asarray(anchors, dtype=np.int64),
        np.asarray(pos_rows, dtype=np.int64).reshape(len(anchors), positives),
        np.asarray(neg_rows, dtype=np.int64).reshape(len(anchors), negatives),
        np.asarray(others, dtype=np.int64),
    )


def in_batch_members(rng: np.random.Generator, ts: TrainingSet, anchors: np.ndarray) -> np.ndarray:
    """int64 [<= 2B] distinct clouds of an in-batch step: the anchors, then one random positive
    of each (skipped when already in the batch)."""
    members = list(dict.fromkeys(anchors.tolist()))
    have = set(members)
    for a in anchors.tolist():
        p = int(rng.choice(ts.positives[a]))
        if p not in have:
            members.append(p)
            have.add(p)
    return np.asarray(members, dtype=np.int64)


def pair_masks(ts: TrainingSet, members: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """bool [M, M] masks over a batch's members: ``pos[i, j]`` when j is a positive of i,
    ``neg[i, j]`` when j is a negative of i (the diagonal is neither)."""
    m = len(members)
    pos = np.zeros((m, m), dtype=bool)
    neg = np.zeros((m, m), dtype=bool)
    for i, a in enumerate(members.tolist()):
        pos[i] = np.isin(members, ts.positives[a])
        neg[i] = ts.negative_mask(a, members)
        pos[i, i] = neg[i, i] = False
    return pos, neg


def with_turned_copies(pos: np.ndarray, neg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """bool [2M, 2M] masks of a batch whose M members are followed by a turned copy of each
    (``train.turned_negatives``): a copy of a member's negative is its negative too; a copy is
    no one's positive (a place turned is still the place: not a negative of its own either)
    and no anchor (its rows hold negatives only, for :func:`in_batch_tuples`' other
    negative)."""
    m = len(pos)
    pos2 = np.zeros((2 * m, 2 * m), dtype=bool)
    neg2 = np.zeros((2 * m, 2 * m), dtype=bool)
    pos2[:m, :m] = pos
    neg2[:m, :m] = neg
    neg2[:m, m:] = neg
    neg2[m:, :m] = neg
    neg2[m:, m:] = neg
    return pos2, neg2


def in_batch_tuples(
    desc: np.ndarray, pos: np.ndarray, neg: np.ndarray, negatives: int
) -> TupleBatch | None:
    """Tuples among a batch's members from their descriptors float32 [M, D] and the masks of
    :func:`pair_masks`: for each member with a positive and a negative in the batch, its hardest
    (farthest) positive, its ``k`` closest negatives (k = min(negatives, fewest negatives any
    such member has)) and, as other negative, its closest batch member that is a negative of it
    and neither one of the chosen negatives nor a positive of them. Indices are positions in the
    batch. ``None`` when no member qualifies."""
    d2 = ((desc[:, None, :].astype(np.float64) - desc[None, :, :]) ** 2).sum(-1)
    ok = pos.any(1) & neg.any(1)
    rows = np.flatnonzero(ok)
    if len(rows) == 0:
        return None
    k = int(min(negatives, neg[rows].sum(1).min()))
    anchors, ps, ns, os_ = [], [], [], []
    for i in rows.tolist():
        p_idx = np.flatnonzero(pos[i])
        n_idx = np.flatnonzero(neg[i])
        hardest_p = p_idx[np.argmax(d2[i, p_idx])]
        chosen = n_idx[np.argsort(d2[i, n_idx], kind="stable")[:k]]
        other_ok = neg[i].copy()
        other_ok[chosen] = False
        other_ok &= ~pos[chosen].any(0)
        cand = np.flatnonzero(other_ok)
        if len(cand) == 0:
            # Too small a batch for a proper other negative: fall back to the farthest negative.
            cand = n_idx[np.argsort(-d2[i, n_idx], kind="stable")[:1]]
        other = cand[np.argmin(d2[i, cand])]
        anchors.append(i)
        ps.append([hardest_p])
        ns.append(chosen)
        os_.append(other)
    return TupleBatch(
        np.asarray(anchors, dtype=np.int64),
        np.asarray(ps, dtype=np.int64),
        np.asarray(ns, dtype=np.int64).reshape(len(anchors), k),
        np.asarray(os_, dtype=np.int64),
    )
