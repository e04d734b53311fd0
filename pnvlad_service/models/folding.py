"""Batch-norm folding: a trained ``PointNetVLAD`` as the plain matrix products ``Encoder`` runs.

Every batch norm (eval mode: running statistics) is folded into the layer before it,
``W' = W * s``, ``b' = (b - mean) * s + beta`` with ``s = gamma / sqrt(var + eps)``, in float64;
:func:`cast_folded` then puts the folded parameters on the device in the dtype of the products.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import torch


@dataclass
class Dense:
    """A folded layer: ``y = x @ w + b``; w [C_in, C_out], b [C_out]."""

    w: torch.Tensor
    b: torch.Tensor


def fold_linear(lin: Any, bn: Any) -> Dense:
    """Fold ``bn`` (BatchNorm1d or Identity) into ``lin`` (Linear, bias optional), in float64."""
    import torch
    from torch import nn

    w = lin.weight.detach().double()
    b = (
        lin.bias.detach().double()
        if lin.bias is not None
        else torch.zeros(w.shape[0], dtype=w.dtype)
    )
    if isinstance(bn, nn.BatchNorm1d):
        s = bn.weight.detach().double() / torch.sqrt(bn.running_var.double() + bn.eps)
        w = w * s[:, None]
        b = (b - bn.running_mean.double()) * s + bn.bias.detach().double()
    return Dense(w.t().contiguous(), b)


def fold_tnet(tnet: Any) -> dict[str, Any]:
    """A transform net folded: its per-point and fully connected layers, and the output layer
    with the identity added to its bias (the net predicts ``T - I``)."""
    import torch

    out = fold_linear(tnet.out, None)
    out.b = out.b + torch.eye(tnet.k, dtype=out.b.dtype).reshape(-1)
    return {
        "points": [
            fold_linear(lin, bn) for lin, bn in zip(tnet.points, tnet.points_bn, strict=True)
        ],
        "fcs": [fold_linear(lin, bn) for lin, bn in zip(tnet.fcs, tnet.fcs_bn, strict=True)],
        "out": out,
        "k": tnet.k,
    }


def fold_model(model: Any) -> dict[str, Any]:
    """Every layer of a ``PointNetVLAD`` (in eval mode) with its batch norm folded in, in float64:
    transform nets, stem, trunk, the NetVLAD cluster logits, centres and head (``fc`` rows
    cluster-major, ``k*D + d``), and the gating."""
    p: dict[str, Any] = {
        "input_tnet": fold_tnet(model.input_tnet) if model.input_tnet is not None else None,
        "feature_tnet": fold_tnet(model.feature_tnet) if model.feature_tnet is not None else None,
        "stem": [fold_linear(a, b) for a, b in zip(model.stem, model.stem_bn, strict=True)],
        "trunk": [fold_linear(a, b) for a, b in zip(model.trunk, model.trunk_bn, strict=True)],
    }
    p.update(fold_head(model.pool, model.cfg.arch == "pointnetvlad"))
    return p


def fold_head(pool: Any, vlad: bool) -> dict[str, Any]:
    """The pooling head folded, in float64: for NetVLAD (``vlad``) the cluster logits (batch
    norm folded in), the centres [K, D] and the fully connected layer with its rows reordered
    cluster-major (``k*D + d``); PN_MAX's fully connected layer; the gating (or None).
    bev-netvlad's export (``onnx_export.py``) takes the same."""
    p: dict[str, Any] = {}
    if vlad:
        import torch
        from torch import nn

        wc = pool.cluster_weights.detach().double()
        if pool.bn:
            bn: nn.BatchNorm1d = pool.cluster_bn
            s = bn.weight.detach().double() / torch.sqrt(bn.running_var.double() + bn.eps)
            cluster = Dense(wc * s, bn.bias.detach().double() - bn.running_mean.double() * s)
        else:
            cluster = Dense(wc, pool.cluster_biases.detach().double())
        fc = fold_linear(pool.fc, pool.fc_bn)  # w [D*K, out], rows d-major (d*K + k)
        d, k = pool.dim, pool.clusters
        fc.w = fc.w.reshape(d, k, -1).transpose(0, 1).reshape(d * k, -1).contiguous()
        p["cluster"] = cluster
        p["centers"] = pool.centers.detach().double().t().contiguous()  # [K, D]
        p["fc"] = fc
    else:
        p["fc"] = fold_linear(pool.fc, None)
    gating = pool.gating
    p["gate"] = fold_linear(gating.gate, gating.gate_bn) if gating is not None else None
    return p


def cast_folded(p: dict[str, Any], dtype: str, device: torch.device) -> dict[str, Any]:
    """:func:`fold_model`'s parameters on ``device``: the per-point products' weights in
    ``dtype`` (``"float32"`` or ``"bfloat16"``; key ``mm``), biases, the transform nets' fully
    connected layers, cluster centres and the gating in float32, the head as the float32 or
    bfloat16 product wants it."""
    import torch

    mm = torch.bfloat16 if dtype == "bfloat16" else torch.float32
    f32 = torch.float32
    dev = device

    def dense(x: Dense | None, wdt: torch.dtype = mm) -> Dense | None:
        if x is None:
            return None
        return Dense(x.w.to(dev, wdt).contiguous(), x.b.to(dev, f32))

    def tnet(t: dict[str, Any] | None) -> dict[str, Any] | None:
        if t is None:
            return None
        return {
            "points": [dense(x) for x in t["points"]],
            "fcs": [dense(x, f32) for x in t["fcs"]],
            "out": dense(t["out"], f32),
            "k": t["k"],
        }

    q: dict[str, Any] = {
        "mm": mm,
        "input_tnet": tnet(p["input_tnet"]),
        "feature_tnet": tnet(p["feature_tnet"]),
        "stem": [dense(x) for x in p["stem"]],
        "trunk": [dense(x) for x in p["trunk"]],
        # float32: the head as F.linear wants it, w [out, in] - a batch of 1-8 pooled vectors
        # reads the 64 MB paper head about twice as fast as against [in, out]. bfloat16 keeps
        # [in, out]: torch 2.13's bfloat16 F.linear of [24, 65536] x [256, 65536]^T dies with
        # SIGFPE on this CPU (oneDNN), while the [in, out] product does not.
        "fc": Dense(p["fc"].w.t().to(dev, mm).contiguous(), p["fc"].b.to(dev, f32))
        if mm == torch.float32
        else dense(p["fc"], mm),
        "gate": dense(p["gate"], f32),
    }
    if "cluster" in p:
        q["cluster"] = dense(p["cluster"])
        q["centers"] = p["centers"].to(dev, f32)
    return q
