"""The fused operations of :class:`~pnvlad_service.models.pointnetvlad.PointNetVLAD`'s fast
forward pass (``pointnetvlad.fast_forward``: training and eval mode, with autograd), numerically
the modules' own forward (``reference_forward``). They take layers and the NetVLAD head as
arguments and know nothing of the encoder that composes them.

What the fast pass does differently from the layer-by-layer reference:

- **Max-pooled layers** (the last per-point layer of each transform net, and of PN_MAX's trunk)
  never materialise their [B*N, C_out] output for autograd. ``BN(x W + b)`` followed by ReLU
  and a max over the points is ``max_n (x W' + t)`` with ``W' = W * s``, ``t`` per channel
  (``s = gamma / sigma``). In training mode the batch statistics come from the [C_in, C_in]
  covariance of the inputs (``mean = x̄ W + b``, ``var_c = w_c^T S w_c``) rather than from the
  [B*N, C_out] outputs, and autograd differentiates those few small products. The product
  ``x W' + t`` then runs one cloud at a time and keeps only the max and its point index
  (:class:`LinearMax`); its backward touches one point per cloud and channel. For the
  128 -> 1024 layers this removes the two backward products (2 x 2·N·128·1024 multiply-adds a
  cloud) and five [B*N, 1024] tensors a transform net.
- **Per-point L2 normalisation before NetVLAD** is folded into the K logits and the assignment
  weights (``logits = (h Wc) / |h|``, ``v = (a / |h|)^T h``), so the normalised [B*N, D]
  features never exist; the residual sums are one batched product with the centre term as its
  added input (``baddbmm``), never a [B, N, K, D] tensor.
- **An affine last layer** (the port's configuration: no ReLU after it, no per-point
  normalisation) never forms its [B*N, D] output: NetVLAD's logits and residual sums are taken
  from its C-wide input (``affine_netvlad_forward``); the encoder does the same
  (``inference.py``).
- **ReLU in place** where autograd allows it (after batch norm and after a product).
- **Transforms folded**: ``(x T) W`` as ``x (T W)`` per cloud for the layer after each
  transform (one [C, C] product instead of a pass over every point).
"""

from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from pnvlad_service.models.netvlad import NetVLAD


class LinearMax(torch.autograd.Function):
    """``out[b, o] = act(max_n (x[b, n] @ w + t)[o])`` with ``act`` ReLU or the identity.

    x float32 [B, N, C], w [C, O], t [O] -> [B, O]. The [N, O] product is computed one cloud
    at a time and only its max and argmax are kept; the backward pass sends each (cloud,
    channel) gradient to its argmax point (ties: the first point; the reference's ``amax``
    splits it, a measure-zero difference that a ReLU'd zero max makes moot).
    """

    @staticmethod
    def forward(ctx: Any, x: torch.Tensor, w: torch.Tensor, t: torch.Tensor, relu: bool):  # type: ignore[override]
        b, _, _ = x.shape
        o = w.shape[1]
        vals = x.new_empty(b, o, dtype=torch.promote_types(x.dtype, w.dtype))
        idx = torch.empty(b, o, dtype=torch.long, device=x.device)
        wt = w.t()
        for i in range(b):  # [O, N]: the max runs along contiguous rows (2x faster than [N, O])
            v, j = torch.mm(wt, x[i].t()).max(1)  # bfloat16 under autocast
            vals[i], idx[i] = v, j
        vals += t  # the same for every point: added to the max, not to the [O, N] product
        if relu:
            vals.relu_()
        ctx.relu, ctx.t_dtype = relu, t.dtype
        ctx.save_for_backward(x, w, idx, vals)
        return vals

    @staticmethod
    def backward(ctx: Any, g: torch.Tensor):  # type: ignore[override]
        x, w, idx, vals = ctx.saved_tensors
        p = g * (vals > 0) if ctx.relu else g  # [B, O]
        c = x.shape[2]
        rows = idx.unsqueeze(2).expand(-1, -1, c)  # [B, O, C]
        dx = dw = dt = None
        if ctx.needs_input_grad[0]:
            contrib = (p.unsqueeze(2) * w.t().unsqueeze(0)).to(x.dtype)  # [B, O, C]
            dx = torch.zeros_like(x).scatter_add_(1, rows, contrib)
        if ctx.needs_input_grad[1]:
            xg = torch.gather(x, 1, rows)  # [B, O, C]: the argmax points' inputs
            dw = torch.einsum("boc,bo->co", xg.to(p.dtype), p).to(w.dtype)
        if ctx.needs_input_grad[2]:
            dt = p.sum(0).to(ctx.t_dtype)
        return dx, dw, dt, None


def _update_running(bn: nn.BatchNorm1d, mean: torch.Tensor, var: torch.Tensor, m: int) -> None:
    """What ``BatchNorm1d`` does to its running statistics in a training-mode call over ``m``
    rows with batch ``mean`` and biased ``var``."""
    if not bn.track_running_stats or bn.running_mean is None or bn.running_var is None:
        return
    with torch.no_grad():
        assert bn.num_batches_tracked is not None
        bn.num_batches_tracked.add_(1)
        mom = bn.momentum if bn.momentum is not None else 1.0 / float(bn.num_batches_tracked)
        bn.running_mean.mul_(1 - mom).add_(mean.detach(), alpha=mom)
        unbiased = var.detach() * (m / max(m - 1, 1))
        bn.running_var.mul_(1 - mom).add_(unbiased, alpha=mom)


class BatchStats(torch.autograd.Function):
    """The batch mean and biased variance of ``x @ w + b`` over the rows of x, from x's
    covariance: x float [M, C], w [C, O], b [O] -> (mean [O], var [O]) in w's dtype.

    ``mean = x̄ w + b`` and ``var_o = w_o^T S w_o`` (S the [C, C] covariance of x), so the
    [M, O] products are never formed. The covariance is the product of the centred rows in x's
    dtype, summed over blocks of :data:`BLOCK` rows in float64; everything of size C x C or
    C x O is float64. The backward is written out rather than differentiated through those
    steps: ``dx = (w dmean)^T / M + (2 / M) (x - x̄) (w diag(dvar) w^T)``,
    ``dw = x̄^T dmean + 2 S w diag(dvar)``, ``db = dmean``: one [M, C] x [C, C] product in x's
    dtype, where autograd through the float64 covariance took two float64 ones and the copies
    (on an AMD EPYC without fast float64 products, 15 % of the paper configuration's training
    step; docs/results/training.md).
    """

    #: Rows a block of the covariance's float32 product (its partial sums are added in float64).
    BLOCK = 4096

    @staticmethod
    def forward(ctx: Any, x: torch.Tensor, w: torch.Tensor, b: torch.Tensor):  # type: ignore[override]
        m, step = x.shape[0], BatchStats.BLOCK
        # Block sums in x's dtype, added in float64 (a float64 copy of x would be a pass of
        # its own).
        xbar = sum(x[s : s + step].sum(0).double() for s in range(0, m, step)) / m  # [C]
        xc = x - xbar.to(x.dtype)
        cov = torch.zeros(x.shape[1], x.shape[1], dtype=torch.float64, device=x.device)
        for s in range(0, m, step):
            block = xc[s : s + step]
            cov += (block.t() @ block).double()
        cov /= m
        w64 = w.double()
        sw = cov @ w64  # [C, O]
        mean = (xbar @ w64 + b.double()).to(w.dtype)
        var = (sw * w64).sum(0).clamp_min(0).to(w.dtype)
        ctx.save_for_backward(xc, xbar, w64, sw)
        ctx.dtypes = (x.dtype, w.dtype, b.dtype)
        return mean, var

    @staticmethod
    def backward(ctx: Any, dmean: torch.Tensor | None, dvar: torch.Tensor | None):  # type: ignore[override]
        xc, xbar, w64, sw = ctx.saved_tensors
        x_dtype, w_dtype, b_dtype = ctx.dtypes
        m = xc.shape[0]
        o = w64.shape[1]
        dm = (dmean if dmean is not None else xc.new_zeros(o)).double()
        dv = (dvar if dvar is not None else xc.new_zeros(o)).double()
        dx = dw = db = None
        if ctx.needs_input_grad[0]:
            g = (w64 * dv) @ w64.t() * (2.0 / m)  # [C, C]
            dx = torch.addmm(((w64 @ dm) / m).to(x_dtype), xc, g.to(x_dtype))
        if ctx.needs_input_grad[1]:
            dw = (torch.outer(xbar, dm) + 2.0 * sw * dv).to(w_dtype)
        if ctx.needs_input_grad[2]:
            db = dm.to(b_dtype)
        return dx, dw, db


def folded_linear_bn(
    lin: nn.Linear, bn: nn.Module, x: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(W', t)`` with ``bn(lin(x)) == x @ W' + t`` for x [M, C] (W' [C, O], t [O]), in
    either mode of ``bn`` (a ``BatchNorm1d``, or ``nn.Identity``: W' = W^T, t = bias).

    In training mode the batch mean and variance of ``lin(x)`` are taken from x's [C, C]
    covariance (:class:`BatchStats`), never from the [M, O] outputs, and the running statistics
    are updated as ``BatchNorm1d`` would; the gradients are the reference's."""
    w = lin.weight.t()  # [C, O], a view
    bias = lin.bias if lin.bias is not None else x.new_zeros(w.shape[1])
    if not isinstance(bn, nn.BatchNorm1d):
        return w, bias
    assert bn.weight is not None and bn.bias is not None
    if bn.training or bn.running_mean is None:
        mean, var = BatchStats.apply(x, w, bias)
        if bn.training:
            _update_running(bn, mean, var, x.shape[0])
    else:
        assert bn.running_var is not None
        mean, var = bn.running_mean, bn.running_var
    s = bn.weight * torch.rsqrt(var + bn.eps)
    return w * s, bn.bias + (bias - mean) * s


def linear_bn_max(lin: nn.Linear, bn: nn.Module, x: torch.Tensor, relu: bool) -> torch.Tensor:
    """``act(bn(lin(x)))`` max-pooled over the points: x [B, N, C] -> [B, O], as the reference
    ``act(bn(lin(x))).amax(1)`` (``bn`` a ``BatchNorm1d`` in either mode, or ``nn.Identity``)."""
    b, n, c = x.shape
    w, t = folded_linear_bn(lin, bn, x.reshape(b * n, c))
    return LinearMax.apply(x, w, t, relu)


def lin_act(lin: nn.Linear, bn: nn.Module, h: torch.Tensor, relu: bool) -> torch.Tensor:
    """``act(bn(lin(h)))`` on [M, C] rows, ReLU in place. (Folding the batch norm here too, with
    statistics from the input covariance, made the narrow layers slower: the float64 [C, C]
    covariance costs as much as the layer itself when C_out is no wider than C_in.)"""
    z = bn(F.linear(h, lin.weight, lin.bias))
    return z.relu_() if relu else z


def folded_linear(lin: nn.Linear, t: torch.Tensor, h: torch.Tensor, b: int, n: int) -> torch.Tensor:
    """``lin(h @ T)`` as ``h @ (T W^T) + bias`` per cloud: h [B*N, C], t [B, C, C] -> [B*N, O]."""
    wt = torch.matmul(t, lin.weight.t())  # [B, C, O]
    out = torch.baddbmm(lin.bias, h.reshape(b, n, -1), wt) if lin.bias is not None else None
    if out is None:
        out = torch.bmm(h.reshape(b, n, -1), wt)
    return out.reshape(b * n, -1)


def _vlad_head(pool: NetVLAD, vlad: torch.Tensor) -> torch.Tensor:
    """Residual sums [B, K, D] -> [B, out]: intra-normalisation (over d, each cluster), L2 of the
    d-major flattening, ``fc``, its batch norm and the gating (reference ``NetVLAD.forward``)."""
    b, k, d = vlad.shape
    vlad = F.normalize(vlad, dim=2)
    vlad = F.normalize(vlad.transpose(1, 2).reshape(b, d * k), dim=1)
    y = pool.fc_bn(pool.fc(vlad))
    return pool.gating(y) if pool.gating is not None else y


def netvlad_forward(pool: NetVLAD, h: torch.Tensor, inv: torch.Tensor | None, b: int, n: int):
    """NetVLAD of features h [B*N, D], each row to be scaled by ``inv`` [B*N, 1] (the per-point
    L2 normalisation, folded) or not (None) -> [B, out] (reference ``NetVLAD.forward``)."""
    d, k = pool.dim, pool.clusters
    logits = h @ pool.cluster_weights  # [M, K]
    if inv is not None:
        logits = logits * inv
    logits = pool.cluster_bn(logits) if pool.bn else logits + pool.cluster_biases
    a = torch.softmax(logits, dim=-1)
    aw = a * inv if inv is not None else a
    centre = a.reshape(b, n, k).sum(1).unsqueeze(2) * pool.centers.t()  # [B, K, D]
    # v[k, d] = sum_n aw[n, k] h[n, d] - (sum_n a[n, k]) c[d, k]: one batched product.
    vlad = torch.baddbmm(centre, aw.reshape(b, n, k).transpose(1, 2), h.reshape(b, n, d), beta=-1)
    return _vlad_head(pool, vlad)


class _VladLink:
    """What :class:`_VladIn` and :class:`_VladSums` share: the features h, their inverse norms
    and the assignment; and, from ``_VladSums``' backward (which autograd runs first), its
    gradient for ``_VladIn``'s."""

    h: torch.Tensor
    inv: torch.Tensor
    a: torch.Tensor | None = None
    d_sums: torch.Tensor | None = None
    inv_grad: torch.Tensor | None = None


class _VladIn(torch.autograd.Function):
    """``h = relu(z)``, ``inv = 1 / max(|h|, 1e-12)`` (per row) and the cluster logits
    ``(h @ wc) * inv`` [M, K] of the last layer's pre-activation z [M, D]; h and inv go to
    :class:`_VladSums` through ``link``. Its backward forms the gradient of z in one product
    a cloud, ``[dP | a] @ [wc^T ; dS]``, scaled by inv, plus the norm's term (a multiple of h)
    and the ReLU mask, where autograd made three [M, D] gradients (logits, sums, norm) and
    added them in as many passes."""

    @staticmethod
    def forward(ctx: Any, z: torch.Tensor, wc: torch.Tensor, link: _VladLink, b: int):  # type: ignore[override]
        h = torch.relu(z)
        norm = torch.linalg.vector_norm(h, dim=1, keepdim=True)
        inv = norm.clamp_min(1e-12).reciprocal()
        hw = h @ wc.to(h.dtype)  # [M, K]
        link.h, link.inv = h, inv
        ctx.link, ctx.b = link, b
        ctx.save_for_backward(h, inv, norm, hw, wc)
        return hw * inv

    @staticmethod
    def backward(ctx: Any, dp: torch.Tensor):  # type: ignore[override]
        h, inv, norm, hw, wc = ctx.saved_tensors
        link: _VladLink = ctx.link
        b = ctx.b
        m, d = h.shape
        n, k = m // b, wc.shape[1]
        dp = dp.to(h.dtype)
        a, d_sums = link.a, link.d_sums
        if a is None or d_sums is None:  # the sums took no gradient: logits only
            left, right = dp.reshape(b, n, k), wc.t().to(h.dtype).expand(b, k, d)
        else:
            left = torch.cat([dp, a.to(h.dtype)], dim=1).reshape(b, n, 2 * k)
            wct = wc.t().to(h.dtype).expand(b, k, d)
            right = torch.cat([wct, d_sums.to(h.dtype)], dim=1)  # [B, 2K, D]
        dh = torch.bmm(left, right).reshape(m, d).mul_(inv)
        # d inv / dh = -inv^3 h where |h| > 1e-12: the logits' and the sums' share of it.
        dinv = (dp * hw).sum(1, keepdim=True)
        if link.inv_grad is not None:
            dinv = dinv + link.inv_grad
        coef = torch.where(norm > 1e-12, -dinv * inv.pow(3), torch.zeros_like(inv))
        dh.addcmul_(h, coef)
        dz = torch.ops.aten.threshold_backward(dh, h, 0)
        dwc = None
        if ctx.needs_input_grad[1]:
            dwc = (h.t() @ (dp * inv).to(h.dtype)).to(wc.dtype)
        link.a = link.d_sums = link.inv_grad = None
        return dz, dwc, None, None


class _VladSums(torch.autograd.Function):
    """NetVLAD's weighted sums ``S_b = (a inv)_b^T h_b`` [B, K, D] of the features and inverse
    norms :class:`_VladIn` put in ``link``, for the assignment a [M, K]. Its backward returns
    a's gradient and leaves the features' (and the norms') to ``_VladIn``'s, through ``link``."""

    @staticmethod
    def forward(ctx: Any, a: torch.Tensor, link: _VladLink, b: int):  # type: ignore[override]
        h, inv = link.h, link.inv
        m, d = h.shape
        aw = (a * inv).to(h.dtype)
        ctx.link, ctx.b = link, b
        ctx.save_for_backward(a)
        return torch.bmm(aw.reshape(b, m // b, -1).transpose(1, 2), h.reshape(b, m // b, d))

    @staticmethod
    def backward(ctx: Any, ds: torch.Tensor):  # type: ignore[override]
        (a,) = ctx.saved_tensors
        link: _VladLink = ctx.link
        h, inv = link.h, link.inv
        b = ctx.b
        m, d = h.shape
        hds = torch.bmm(h.reshape(b, m // b, d), ds.to(h.dtype).transpose(1, 2))  # [B, N, K]
        hds = hds.reshape(m, -1).to(a.dtype)
        link.a, link.d_sums = a, ds
        link.inv_grad = (a * hds).sum(1, keepdim=True).to(inv.dtype)
        return hds * inv, None, None


def relu_l2_netvlad_forward(pool: NetVLAD, z: torch.Tensor, b: int, n: int) -> torch.Tensor:
    """NetVLAD of ``relu(z)`` with each row L2-normalised (the paper's per-point normalisation),
    z [B*N, D] the last layer's pre-activation -> [B, out]: :func:`netvlad_forward` of those
    features, with the gradient of z formed in one product a cloud (:class:`_VladIn`)."""
    k = pool.clusters
    link = _VladLink()
    logits = _VladIn.apply(z, pool.cluster_weights, link, b)  # [M, K]
    logits = pool.cluster_bn(logits) if pool.bn else logits + pool.cluster_biases
    a = torch.softmax(logits, dim=-1)
    sums = _VladSums.apply(a, link, b)  # [B, K, D]
    centre = a.reshape(b, n, k).sum(1).unsqueeze(2) * pool.centers.t()  # [B, K, D]
    return _vlad_head(pool, sums.to(centre.dtype) - centre)


def affine_netvlad_forward(
    pool: NetVLAD, lin: nn.Linear, bn: nn.Module, x: torch.Tensor, b: int, n: int
) -> torch.Tensor:
    """NetVLAD of ``h = bn(lin(x))`` for x [B*N, C] when nothing non-linear comes between the
    last trunk layer and the pooling (no ReLU after it, no per-point normalisation: the port's
    configuration) -> [B, out] (reference ``NetVLAD.forward`` of those features).

    Then h is affine in x, ``h = x W' + t`` (batch statistics from x's covariance, as
    :func:`folded_linear_bn`), so the [B*N, D] features are never formed: the logits are
    ``x (W' Wc) + t Wc`` and the residual sums ``(a^T x) W' + (sum_n a) (t - c)``, products of
    width C and K instead of D (for the port's 128 -> 1024 layer, about a tenth of the work).
    """
    d, k, c = pool.dim, pool.clusters, x.shape[1]
    w, t = folded_linear_bn(lin, bn, x)  # [C, D], [D]
    wc = pool.cluster_weights
    logits = torch.addmm(t @ wc, x, w @ wc)  # [M, K]
    logits = pool.cluster_bn(logits) if pool.bn else logits + pool.cluster_biases
    a = torch.softmax(logits, dim=-1).reshape(b, n, k)
    ax = torch.bmm(a.transpose(1, 2), x.reshape(b, n, c))  # [B, K, C]
    shift = a.sum(1).unsqueeze(2) * (t.unsqueeze(1) - pool.centers).t()  # [B, K, D]
    vlad = torch.baddbmm(shift, ax, w.expand(b, c, d))
    return _vlad_head(pool, vlad)
