"""models.netvlad: the NetVLAD head against a loop over clusters and points, as published."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from pnvlad_service.models.netvlad import NetVLAD


def netvlad_reference(x: torch.Tensor, pool: NetVLAD) -> torch.Tensor:
    """NetVLAD of one cloud x [N, D] with loops over clusters and points (eval-mode BN)."""
    n, d = x.shape
    k = pool.clusters
    bn = pool.cluster_bn
    logits = x.double() @ pool.cluster_weights.double()
    logits = (logits - bn.running_mean.double()) / torch.sqrt(bn.running_var.double() + bn.eps)
    logits = logits * bn.weight.double() + bn.bias.double()
    a = torch.softmax(logits, dim=1)
    v = torch.zeros(d, k, dtype=torch.float64)
    for j in range(k):
        for i in range(n):
            v[:, j] += a[i, j] * (x[i].double() - pool.centers[:, j].double())
        v[:, j] /= v[:, j].norm()
    flat = torch.stack([v[dd, j] for dd in range(d) for j in range(k)])  # d-major, as published
    return flat / flat.norm()


def test_netvlad_matches_loop_reference() -> None:
    torch.manual_seed(0)
    pool = NetVLAD(dim=8, clusters=3, out=5, bn=True, gating=True)
    with torch.no_grad():  # batch norms with non-trivial statistics and affine parameters
        for bn in (pool.cluster_bn, pool.fc_bn, pool.gating.gate_bn):
            bn.running_mean.uniform_(-0.5, 0.5)
            bn.running_var.uniform_(0.5, 2.0)
            bn.weight.uniform_(0.5, 1.5)
            bn.bias.uniform_(-0.3, 0.3)
    pool.eval()
    x = torch.rand(2, 7, 8)
    with torch.no_grad():
        got = pool(x)
        for b in range(2):
            flat = netvlad_reference(x[b], pool)
            y = F.linear(flat.float().unsqueeze(0), pool.fc.weight)
            y = pool.fc_bn(y)
            gates = torch.sigmoid(pool.gating.gate_bn(pool.gating.gate(y)))
            assert torch.allclose(got[b], (y * gates)[0], atol=1e-5)
