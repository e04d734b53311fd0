"""Import weights of the PyTorch port of PointNetVLAD (cattaneod/PointNetVlad-Pytorch).

The port's model ``PointNetVlad(num_points=4096, global_feat=True, feature_transform=True,
max_pool=False, output_dim=256)`` is our ``ModelConfig.port()``; its checkpoints are
``torch.save({'epoch', 'iter', 'state_dict', 'optimizer'})`` files. They are read with
``torch.load(weights_only=True)`` only (tensors, dicts, lists and numbers): a file that needs any
other class is refused. A bare state dict and a DataParallel (``module.``-prefixed) one are
accepted too.

Name mapping (port -> ours); 1x1 convolutions [out, in, 1, k] become Linear weights [out, in*k]:

=================================================  ==========================================
``point_net.stn.conv{1,2,3}``                       ``input_tnet.points.{0,1,2}``
``point_net.stn.fc{1,2}`` / ``fc3``                 ``input_tnet.fcs.{0,1}`` / ``input_tnet.out``
``point_net.feature_trans.*``                       ``feature_tnet.*`` (same pattern)
``point_net.conv{1,2}`` / ``bn{1,2}``               ``stem.{0,1}`` / ``stem_bn.{0,1}``
``point_net.conv{3,4,5}`` / ``bn{3,4,5}``           ``trunk.{0,1,2}`` / ``trunk_bn.{0,1,2}``
``net_vlad.cluster_weights`` [D, K]                 ``pool.cluster_weights``
``net_vlad.cluster_weights2`` [1, D, K]             ``pool.centers`` [D, K]
``net_vlad.bn1``                                    ``pool.cluster_bn``
``net_vlad.hidden1_weights`` [D*K, out]             ``pool.fc.weight`` (transposed)
``net_vlad.bn2``                                    ``pool.fc_bn``
``net_vlad.context_gating.gating_weights``          ``pool.gating.gate.weight`` (transposed)
``net_vlad.context_gating.bn1``                     ``pool.gating.gate_bn``
=================================================  ==========================================
"""

from __future__ import annotations

import logging
import pickle
import re
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pnvlad_service.errors import InputError
from pnvlad_service.fileio import sha256_file
from pnvlad_service.models.config import ModelConfig

if TYPE_CHECKING:
    import torch

log = logging.getLogger(__name__)

_BN = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")
Transform = Callable[["torch.Tensor"], "torch.Tensor"]


def _conv(t: torch.Tensor) -> torch.Tensor:
    """Conv2d weight [out, in, 1, k] -> Linear weight [out, in*k]."""
    return t.reshape(t.shape[0], -1) if t.dim() == 4 else t


def _same(t: torch.Tensor) -> torch.Tensor:
    return t


def _transpose(t: torch.Tensor) -> torch.Tensor:
    return t.t().contiguous() if t.dim() == 2 else t


def _squeeze0(t: torch.Tensor) -> torch.Tensor:
    return t[0] if t.dim() == 3 and t.shape[0] == 1 else t


def port_key_map(feature_transform: bool = True) -> dict[str, tuple[str, Transform]]:
    """Port state-dict name -> (our name, tensor transform), for the port's PN_VLAD."""
    m: dict[str, tuple[str, Transform]] = {}

    def tnet(port: str, ours: str) -> None:
        for i in range(3):
            m[f"{port}.conv{i + 1}.weight"] = (f"{ours}.points.{i}.weight", _conv)
            m[f"{port}.conv{i + 1}.bias"] = (f"{ours}.points.{i}.bias", _same)
        for i in range(2):
            for p in ("weight", "bias"):
                m[f"{port}.fc{i + 1}.{p}"] = (f"{ours}.fcs.{i}.{p}", _same)
        for p in ("weight", "bias"):
            m[f"{port}.fc3.{p}"] = (f"{ours}.out.{p}", _same)

    tnet("point_net.stn", "input_tnet")
    if feature_transform:
        tnet("point_net.feature_trans", "feature_tnet")
    for i in range(5):
        ours = f"stem.{i}" if i < 2 else f"trunk.{i - 2}"
        ours_bn = f"stem_bn.{i}" if i < 2 else f"trunk_bn.{i - 2}"
        m[f"point_net.conv{i + 1}.weight"] = (f"{ours}.weight", _conv)
        m[f"point_net.conv{i + 1}.bias"] = (f"{ours}.bias", _same)
        for p in _BN:
            m[f"point_net.bn{i + 1}.{p}"] = (f"{ours_bn}.{p}", _same)
    m["net_vlad.cluster_weights"] = ("pool.cluster_weights", _same)
    m["net_vlad.cluster_weights2"] = ("pool.centers", _squeeze0)
    m["net_vlad.hidden1_weights"] = ("pool.fc.weight", _transpose)
    m["net_vlad.context_gating.gating_weights"] = ("pool.gating.gate.weight", _transpose)
    for port, ours in (
        ("net_vlad.bn1", "pool.cluster_bn"),
        ("net_vlad.bn2", "pool.fc_bn"),
        ("net_vlad.context_gating.bn1", "pool.gating.gate_bn"),
    ):
        for p in _BN:
            m[f"{port}.{p}"] = (f"{ours}.{p}", _same)
    return m


def read_port_checkpoint(path: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Load a port checkpoint safely: returns (state dict without ``module.``, extra info).

    Accepts ``{'state_dict': ..., 'epoch': .., ...}`` or a bare state dict. Raises
    :class:`InputError` when the file is missing, is not a torch file, needs classes beyond
    plain tensors and containers (``weights_only=True`` refuses them), or holds no state dict.
    """
    import torch

    path = Path(path)
    if not path.is_file():
        raise InputError("no such file", path)
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        found = re.search(r"Unsupported global: GLOBAL ([\w.]+)", str(exc))
        if found:
            raise InputError(
                f"refusing to load: the file needs the class {found.group(1)}, and pnvlad loads "
                "only plain tensors and containers (torch.load(weights_only=True)), never "
                "arbitrary pickled objects",
                path,
            ) from None
        raise InputError(
            "not a readable torch checkpoint (bad or unsafe pickle data)", path
        ) from None
    except (RuntimeError, EOFError, OSError, ValueError) as exc:
        raise InputError(f"not a readable torch checkpoint: {exc}", path) from None
    info: dict[str, Any] = {}
    if isinstance(obj, dict) and "state_dict" in obj:
        info = {k: v for k, v in obj.items() if k in ("epoch", "iter") and isinstance(v, int)}
        obj = obj["state_dict"]
    if (
        not isinstance(obj, dict)
        or not obj
        or not all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in obj.items())
    ):
        raise InputError("holds no state dict (a dict of parameter name -> tensor)", path)
    if all(k.startswith("module.") for k in obj):
        obj = {k[len("module.") :]: v for k, v in obj.items()}
    return dict(obj), info


def port_config(state: dict[str, torch.Tensor], feature_transform: bool = True) -> ModelConfig:
    """Our configuration for a port state dict (K and output size read from the tensors)."""
    overrides: dict[str, object] = {"feature_transform": feature_transform}
    cw = state.get("net_vlad.cluster_weights")
    hw = state.get("net_vlad.hidden1_weights")
    if cw is not None and cw.dim() == 2:
        overrides["cluster_size"] = int(cw.shape[1])
    if hw is not None and hw.dim() == 2:
        overrides["output_dim"] = int(hw.shape[1])
    return ModelConfig.port(**overrides)


def convert_port_state(
    state: dict[str, torch.Tensor], cfg: ModelConfig, source: str | Path = "state_dict"
) -> dict[str, torch.Tensor]:
    """Map a port state dict onto our names for ``cfg`` (a ``ModelConfig.port`` variant).

    Raises :class:`InputError` listing the port names that are missing, those unexpected, and
    the tensors whose shapes do not fit. ``num_batches_tracked`` counters may be absent (old
    PyTorch versions did not write them); the feature transform's tensors are skipped (with a
    log line) when ``cfg.feature_transform`` is off, since the port always creates them.
    """
    import torch

    from pnvlad_service.models.factory import build_model

    kmap = port_key_map(cfg.feature_transform)
    ours = build_model(cfg).state_dict()
    state = dict(state)
    if not cfg.feature_transform:
        skipped = [k for k in state if k.startswith("point_net.feature_trans.")]
        for k in skipped:
            del state[k]
        if skipped:
            log.info(
                "feature transform off: ignoring %d point_net.feature_trans tensors", len(skipped)
            )
    missing = sorted(k for k in kmap if k not in state and not k.endswith(".num_batches_tracked"))
    unexpected = sorted(k for k in state if k not in kmap)
    out: dict[str, torch.Tensor] = {}
    shapes: list[str] = []
    for pk, (ok, fn) in kmap.items():
        if pk not in state:
            if pk.endswith(".num_batches_tracked"):
                out[ok] = torch.zeros((), dtype=torch.long)
            continue
        t = fn(state[pk].detach().cpu())
        if ok not in ours:  # a mapping for a layer this configuration lacks
            unexpected.append(pk)
            continue
        if tuple(t.shape) != tuple(ours[ok].shape):
            shapes.append(f"{pk} {tuple(state[pk].shape)} -> {ok} expects {tuple(ours[ok].shape)}")
            continue
        out[ok] = t.to(ours[ok].dtype).contiguous()
    if missing or unexpected or shapes:
        from pnvlad_service.models.store import state_mismatch

        raise InputError(
            "not a PointNetVlad-Pytorch PointNetVlad(feature_transform="
            f"{cfg.feature_transform}, max_pool=False) state dict: "
            + state_mismatch(missing, sorted(unexpected), shapes),
            source,
        )
    return out


def import_port(
    path: str | Path,
    out_dir: str | Path,
    *,
    feature_transform: bool = True,
    overwrite: bool = False,
) -> tuple[Path, ModelConfig]:
    """Convert a port checkpoint into our model directory ``out_dir`` (atomic).

    Returns (out_dir, config). ``model.json`` records the source file's name and SHA-256 and the
    checkpoint's epoch/iteration when present.
    """
    from pnvlad_service.models.factory import build_model
    from pnvlad_service.models.store import save_model

    path = Path(path)
    state, info = read_port_checkpoint(path)
    cfg = port_config(state, feature_transform)
    converted = convert_port_state(state, cfg, path)
    model = build_model(cfg)
    model.load_state_dict(converted, strict=True)
    model.eval()
    sha = sha256_file(path)
    meta = {"source": {"kind": "PointNetVlad-Pytorch", "file": path.name, "sha256": sha, **info}}
    save_model(out_dir, model, cfg, meta, overwrite=overwrite)
    log.info("imported %s (%d tensors) into %s", path.name, len(converted), out_dir)
    return Path(out_dir), cfg
