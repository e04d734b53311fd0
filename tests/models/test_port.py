"""Importing PointNetVlad-Pytorch weights.

The port's parameter names and shapes are written down here from reading its models/
PointNetVlad.py (``PointNetVlad(num_points=4096, global_feat=True, feature_transform=True,
max_pool=False, output_dim=256)``); its code is not used. ``port_forward`` recomputes the port's
forward pass (eval mode) in plain torch straight from those names.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from pnvlad_service.errors import InputError
from pnvlad_service.models.inference import Encoder
from pnvlad_service.models.port import convert_port_state, import_port, port_config
from pnvlad_service.models.store import load_model

D, K = 1024, 64


def port_shapes(output_dim: int = 256) -> dict[str, tuple[int, ...]]:
    """Every tensor of the port's PointNetVlad state dict, with its shape."""
    s: dict[str, tuple[int, ...]] = {}

    def bn(prefix: str, c: int) -> None:
        for p in ("weight", "bias", "running_mean", "running_var"):
            s[f"{prefix}.{p}"] = (c,)
        s[f"{prefix}.num_batches_tracked"] = ()

    for stn, k, cin, kw in (("stn", 3, 1, 3), ("feature_trans", 64, 64, 1)):
        pre = f"point_net.{stn}"
        s[f"{pre}.conv1.weight"], s[f"{pre}.conv1.bias"] = (64, cin, 1, kw), (64,)
        s[f"{pre}.conv2.weight"], s[f"{pre}.conv2.bias"] = (128, 64, 1, 1), (128,)
        s[f"{pre}.conv3.weight"], s[f"{pre}.conv3.bias"] = (1024, 128, 1, 1), (1024,)
        s[f"{pre}.fc1.weight"], s[f"{pre}.fc1.bias"] = (512, 1024), (512,)
        s[f"{pre}.fc2.weight"], s[f"{pre}.fc2.bias"] = (256, 512), (256,)
        s[f"{pre}.fc3.weight"], s[f"{pre}.fc3.bias"] = (k * k, 256), (k * k,)
    for i, (cout, cin, kw) in enumerate(
        [(64, 1, 3), (64, 64, 1), (64, 64, 1), (128, 64, 1), (1024, 128, 1)], start=1
    ):
        s[f"point_net.conv{i}.weight"] = (cout, cin, 1, kw)
        s[f"point_net.conv{i}.bias"] = (cout,)
        bn(f"point_net.bn{i}", cout)
    s["net_vlad.cluster_weights"] = (D, K)
    s["net_vlad.cluster_weights2"] = (1, D, K)
    s["net_vlad.hidden1_weights"] = (K * D, output_dim)
    bn("net_vlad.bn1", K)
    bn("net_vlad.bn2", output_dim)
    s["net_vlad.context_gating.gating_weights"] = (output_dim, output_dim)
    bn("net_vlad.context_gating.bn1", output_dim)
    return s


def random_port_state(output_dim: int = 256, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    state = {}
    for name, shape in port_shapes(output_dim).items():
        if name.endswith("num_batches_tracked"):
            state[name] = torch.tensor(7)
        elif name.endswith("running_var") or (name.endswith(".weight") and len(shape) == 1):
            state[name] = torch.rand(shape, generator=g) + 0.5  # variances and BN gammas
        else:
            fan_in = math.prod(shape[1:]) if len(shape) > 1 else shape[0]
            std = 1.0 / math.sqrt(fan_in)
            if name == "net_vlad.hidden1_weights":
                std = 1.0 / math.sqrt(D)
            if ".fc3." in name:
                std = 0.02  # a transform near the identity, as after training
            state[name] = torch.randn(shape, generator=g) * std
    return state


def port_forward(sd: dict[str, torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """The port's PointNetVlad forward, eval mode, for points x [B, N, 3] -> [B, out]."""

    def conv(h: torch.Tensor, name: str) -> torch.Tensor:  # h [B, N, C_in], 1xk conv
        w = sd[f"{name}.weight"]
        return h @ w.reshape(w.shape[0], -1).T + sd[f"{name}.bias"]

    def bn(h: torch.Tensor, name: str) -> torch.Tensor:  # channels last
        mean, var = sd[f"{name}.running_mean"], sd[f"{name}.running_var"]
        return (h - mean) / torch.sqrt(var + 1e-5) * sd[f"{name}.weight"] + sd[f"{name}.bias"]

    def stn(h: torch.Tensor, name: str, k: int) -> torch.Tensor:  # use_bn=False in the port
        h = torch.relu(conv(h, f"{name}.conv1"))
        h = torch.relu(conv(h, f"{name}.conv2"))
        h = torch.relu(conv(h, f"{name}.conv3"))
        h = h.max(dim=1).values
        h = torch.relu(h @ sd[f"{name}.fc1.weight"].T + sd[f"{name}.fc1.bias"])
        h = torch.relu(h @ sd[f"{name}.fc2.weight"].T + sd[f"{name}.fc2.bias"])
        h = h @ sd[f"{name}.fc3.weight"].T + sd[f"{name}.fc3.bias"]
        return (h + torch.eye(k).reshape(1, -1)).reshape(-1, k, k)

    pn = "point_net"
    x = torch.matmul(x, stn(x, f"{pn}.stn", 3))
    h = torch.relu(bn(conv(x, f"{pn}.conv1"), f"{pn}.bn1"))
    h = torch.relu(bn(conv(h, f"{pn}.conv2"), f"{pn}.bn2"))
    h = torch.matmul(h, stn(h, f"{pn}.feature_trans", 64))
    h = torch.relu(bn(conv(h, f"{pn}.conv3"), f"{pn}.bn3"))
    h = torch.relu(bn(conv(h, f"{pn}.conv4"), f"{pn}.bn4"))
    h = bn(conv(h, f"{pn}.conv5"), f"{pn}.bn5")  # no ReLU: the port returns here
    nv = "net_vlad"
    act = torch.softmax(bn(h @ sd[f"{nv}.cluster_weights"], f"{nv}.bn1"), dim=-1)  # [B, N, K]
    a = act.sum(dim=1, keepdim=True) * sd[f"{nv}.cluster_weights2"]  # [B, D, K]
    vlad = torch.matmul(act.transpose(2, 1), h).transpose(2, 1) - a
    vlad = torch.nn.functional.normalize(vlad, dim=1)
    vlad = torch.nn.functional.normalize(vlad.reshape(vlad.shape[0], -1), dim=1)
    y = bn(vlad @ sd[f"{nv}.hidden1_weights"], f"{nv}.bn2")
    gates = torch.sigmoid(
        bn(y @ sd[f"{nv}.context_gating.gating_weights"], f"{nv}.context_gating.bn1")
    )
    return y * gates


@pytest.fixture(scope="module")
def port_state() -> dict[str, torch.Tensor]:
    return random_port_state()


@pytest.fixture(scope="module")
def port_ckpt(tmp_path_factory: pytest.TempPathFactory, port_state) -> Path:
    """A checkpoint as the port's training script writes it."""
    path = tmp_path_factory.mktemp("port") / "checkpoint.pth.tar"
    opt_state = {
        "state": {0: {"step": torch.tensor(3.0), "exp_avg": torch.zeros(3)}},
        "param_groups": [{"lr": 5e-5, "params": [0]}],
    }
    torch.save({"epoch": 4, "iter": 1234, "state_dict": port_state, "optimizer": opt_state}, path)
    return path


def test_import_matches_port_forward(tmp_path: Path, port_ckpt: Path, port_state) -> None:
    out, cfg = import_port(port_ckpt, tmp_path / "model")
    assert cfg.output_dim == 256 and cfg.cluster_size == 64 and cfg.feature_transform
    x = torch.rand(2, 512, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1
    with torch.no_grad():
        want = torch.nn.functional.normalize(port_forward(port_state, x), dim=1)
    model, _ = load_model(out)
    with torch.no_grad():
        got = model(x)
    assert torch.allclose(got, want, atol=1e-5), (got - want).abs().max()
    enc = Encoder.from_checkpoint(out)
    assert np.abs(enc.embed(x) - want.numpy()).max() < 1e-5
    doc = json.loads((out / "model.json").read_text())
    assert doc["source"]["epoch"] == 4 and doc["source"]["iter"] == 1234
    assert doc["source"]["file"] == "checkpoint.pth.tar"


def test_every_tensor_lands_in_its_place(port_state) -> None:
    cfg = port_config(port_state)
    ours = convert_port_state(port_state, cfg)
    assert torch.equal(ours["stem.0.weight"], port_state["point_net.conv1.weight"][:, 0, 0, :])
    assert torch.equal(ours["trunk.2.weight"], port_state["point_net.conv5.weight"][:, :, 0, 0])
    assert torch.equal(ours["trunk_bn.2.running_var"], port_state["point_net.bn5.running_var"])
    assert torch.equal(ours["input_tnet.out.bias"], port_state["point_net.stn.fc3.bias"])
    assert torch.equal(
        ours["feature_tnet.points.0.weight"],
        port_state["point_net.feature_trans.conv1.weight"][:, :, 0, 0],
    )
    assert torch.equal(ours["pool.centers"], port_state["net_vlad.cluster_weights2"][0])
    assert torch.equal(ours["pool.fc.weight"], port_state["net_vlad.hidden1_weights"].T)
    assert torch.equal(
        ours["pool.gating.gate.weight"], port_state["net_vlad.context_gating.gating_weights"].T
    )
    # Each port tensor is used exactly once: the totals agree.
    assert sum(t.numel() for t in ours.values()) == sum(t.numel() for t in port_state.values())


def test_bare_and_dataparallel_state_dicts(tmp_path: Path, port_state) -> None:
    small = random_port_state(output_dim=16, seed=3)
    bare = tmp_path / "bare.pth"
    torch.save(small, bare)
    dp = tmp_path / "dp.pth"
    torch.save({"state_dict": {f"module.{k}": v for k, v in small.items()}}, dp)
    _, cfg = import_port(bare, tmp_path / "a")
    import_port(dp, tmp_path / "b")
    assert cfg.output_dim == 16
    ma, _ = load_model(tmp_path / "a")
    mb, _ = load_model(tmp_path / "b")
    for (ka, va), (kb, vb) in zip(ma.state_dict().items(), mb.state_dict().items(), strict=True):
        assert ka == kb and torch.equal(va, vb)
    # Checkpoints of old PyTorch versions lack the num_batches_tracked counters.
    old = {k: v for k, v in small.items() if not k.endswith("num_batches_tracked")}
    torch.save(old, tmp_path / "old.pth")
    import_port(tmp_path / "old.pth", tmp_path / "c")


def test_mismatch_is_refused_with_the_list(tmp_path: Path) -> None:
    state = random_port_state(output_dim=16, seed=4)
    del state["point_net.bn3.running_mean"]
    state["net_vlad.extra"] = torch.zeros(3)
    state["point_net.conv4.weight"] = torch.zeros(128, 32, 1, 1)
    path = tmp_path / "bad.pth"
    torch.save(state, path)
    with pytest.raises(InputError) as err:
        import_port(path, tmp_path / "out")
    msg = str(err.value)
    assert "missing 1: point_net.bn3.running_mean" in msg
    assert "unexpected 1: net_vlad.extra" in msg
    assert "point_net.conv4.weight (128, 32, 1, 1) -> trunk.1.weight expects (128, 64)" in msg
    assert not (tmp_path / "out").exists()


class NotATensor:
    pass


def test_unsafe_and_unreadable_files_are_refused(tmp_path: Path) -> None:
    evil = tmp_path / "evil.pth"
    torch.save({"state_dict": {"x": torch.zeros(1)}, "extra": NotATensor()}, evil)
    with pytest.raises(InputError, match=r"refusing to load.*NotATensor"):
        import_port(evil, tmp_path / "out")
    junk = tmp_path / "junk.pth"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="torch checkpoint"):
        import_port(junk, tmp_path / "out")
    torch.save({"epoch": 1}, tmp_path / "nostate.pth")
    with pytest.raises(InputError, match="no state dict"):
        import_port(tmp_path / "nostate.pth", tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_cli_import_and_info(tmp_path: Path) -> None:
    from pnvlad_cli.main import app

    state = random_port_state(output_dim=16, seed=5)
    ckpt = tmp_path / "ckpt.pth"
    torch.save({"epoch": 1, "state_dict": state}, ckpt)
    runner = CliRunner()
    res = runner.invoke(app, ["model", "import", str(ckpt), "--out", str(tmp_path / "m")])
    assert res.exit_code == 0, res.output
    assert "imported" in res.output and (tmp_path / "m" / "model.safetensors").is_file()
    res = runner.invoke(app, ["model", "import", str(ckpt), "--out", str(tmp_path / "m")])
    assert res.exit_code == 2 and "already exists" in res.output
    res = runner.invoke(app, ["model", "info", str(tmp_path / "m"), "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.output)
    assert doc["model"]["output_dim"] == 16 and doc["model"]["trunk_batch_norm"] is True
    buffers = ("running_mean", "running_var", "num_batches_tracked")
    assert doc["parameters"] == sum(v.numel() for k, v in state.items() if not k.endswith(buffers))
    # a training run directory names its final model, as in every command that takes a model
    shutil.copytree(tmp_path / "m", tmp_path / "run" / "model")
    res = runner.invoke(app, ["model", "info", str(tmp_path / "run"), "--json"])
    assert res.exit_code == 0, res.output
    doc_run = json.loads(res.output)
    assert doc_run["dir"] == str(tmp_path / "run" / "model")
    assert doc_run["weights_sha256"] == doc["weights_sha256"]
    del state["net_vlad.cluster_weights"]
    torch.save(state, ckpt)
    res = runner.invoke(app, ["model", "import", str(ckpt), "--out", str(tmp_path / "m2")])
    assert res.exit_code == 2 and "net_vlad.cluster_weights" in res.output
