"""The encoder as an ONNX graph, built operator by operator from its folded parameters.

:func:`build_graph` writes the network that :class:`~.inference.Encoder` runs (the fast
inference path: batch norms folded, max before bias, the per-point L2 norm applied to the
logits and the assignment weights instead of the features, the feature transform folded into
the next layer's weights) as an ONNX model with one input, ``points`` float32 [B, N, 3], and one
output, ``descriptor`` float32 [B, out], both with a dynamic batch size B and point count N.
It needs the ``onnx`` package and numpy only: the parameters come in as float64 arrays from
``folding.py`` (``onnx_export.py`` does that part, with torch).

PointNet (PN_VLAD, PN_MAX): a ``Loop`` over the clouds of the batch runs the per-point network
one cloud at a time, and inside it a ``Loop`` over tiles of ``point_tile`` points computes the
widest layers (each transform net's last per-point layer with its max, and the last trunk layer
with NetVLAD's sums), so that the [tile, 1024] activations stay in cache instead of a
[B * N, 1024] tensor going through memory several times (the encoder does the same with its
tiles). The fully connected head then runs on the whole batch as one product.

bev-netvlad: the bird's-eye histogram (``ScatterElements`` with ``reduction="add"``), the
convolutions (batch norm folded into each), the cells as NetVLAD's points and the same head, all
on the whole batch.

``canonical_heading`` (``heading.py``): the dominant angle of each cloud from its bilinear
64 x 64 histogram, two blurs and Sobel gradients, as in torch, except that the per-cell
``cos 4θ`` and ``sin 4θ`` weighted by the squared gradient come from the gradients themselves
(``((gx² - gy²)² - 4 gx² gy²) / r²`` and ``4 gx gy (gx² - gy²) / r²``: no per-cell arctangent;
ONNX has none) and the one ``atan2`` per cloud is ``Atan`` with its quadrants.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

#: Opset of the graphs written (ONNX Runtime 1.12 and later run it).
OPSET = 17

#: Cells a side of the heading's histogram (``heading.GRID``; a test keeps them equal).
HEADING_GRID = 64


class _Builder:
    """Nodes of the graph being written (a Loop body pushes its own list) and the model's
    initializers (every constant lives in the main graph: bodies read them from the outer
    scope)."""

    def __init__(self) -> None:
        self.initializers: list[Any] = []
        self.stack: list[list[Any]] = [[]]
        self.count = 0

    def name(self, hint: str) -> str:
        self.count += 1
        return f"{hint}_{self.count}"

    def const(self, value: Any, hint: str = "c", dtype: Any = np.float32) -> str:
        from onnx import numpy_helper

        name = self.name(hint)
        arr = np.ascontiguousarray(np.asarray(value, dtype=dtype))
        self.initializers.append(numpy_helper.from_array(arr, name))
        return name

    def i64(self, *values: int, hint: str = "i") -> str:
        """A constant int64 vector."""
        return self.const(list(values), hint, np.int64)

    def scalar_i64(self, value: int, hint: str = "n") -> str:
        return self.const(value, hint, np.int64)

    def op(self, op_type: str, *inputs: str, hint: str | None = None, **attrs: Any) -> str:
        return self.ops(op_type, list(inputs), 1, hint=hint, **attrs)[0]

    def ops(
        self, op_type: str, inputs: list[str], outputs: int, hint: str | None = None, **attrs: Any
    ) -> list[str]:
        from onnx import helper

        names = [self.name(hint or op_type.lower()) for _ in range(outputs)]
        self.stack[-1].append(helper.make_node(op_type, inputs, names, **attrs))
        return names

    # -- small compositions -------------------------------------------------------------------

    def dense(self, x: str, w: np.ndarray | str, b: np.ndarray, relu: bool, hint: str) -> str:
        """``relu?(x @ w + b)``; ``w`` a constant [C_in, C_out] or a value of the graph."""
        wn = w if isinstance(w, str) else self.const(w, f"{hint}_w")
        y = self.op("Add", self.op("MatMul", x, wn), self.const(b, f"{hint}_b"), hint=hint)
        return self.op("Relu", y) if relu else y

    def normalize(self, x: str, axis: int) -> str:
        """``F.normalize(x, dim=axis)``: x / max(|x|, 1e-12)."""
        n = self.op("ReduceL2", x, axes=[axis], keepdims=1)
        return self.op("Div", x, self.op("Max", n, self.const(1e-12)))

    def loop(
        self,
        trip: str,
        carried: list[tuple[str, str]],
        scans: int,
        body: Any,
        hint: str,
    ) -> list[str]:
        """A ``Loop`` of ``trip`` iterations. ``carried``: (initial value, hint) of each
        loop-carried float tensor; ``body(i, values) -> (new values, scan outputs)`` adds the
        body's nodes (``i``: the iteration, an int64 scalar). Returns the final carried values,
        then the scan outputs (each stacked along a new first axis)."""
        from onnx import TensorProto, helper

        it = self.name(f"{hint}_iter")
        cond_in = self.name(f"{hint}_cond")
        ins = [self.name(f"{hint}_{h}_in") for _, h in carried]
        self.stack.append([])
        outs, scan_outs = body(it, ins)
        nodes = self.stack.pop()
        cond_out = self.name(f"{hint}_cond_out")
        nodes.append(helper.make_node("Identity", [cond_in], [cond_out]))
        f = TensorProto.FLOAT
        graph = helper.make_graph(
            nodes,
            self.name(f"{hint}_body"),
            [
                helper.make_tensor_value_info(it, TensorProto.INT64, []),
                helper.make_tensor_value_info(cond_in, TensorProto.BOOL, []),
                *(helper.make_tensor_value_info(n, f, None) for n in ins),
            ],
            [
                helper.make_tensor_value_info(cond_out, TensorProto.BOOL, []),
                *(helper.make_tensor_value_info(n, f, None) for n in [*outs, *scan_outs]),
            ],
        )
        return self.ops(
            "Loop",
            [trip, "", *(v for v, _ in carried)],
            len(carried) + scans,
            hint=hint,
            body=graph,
        )

    def tiles(
        self,
        h: str,
        tile: int,
        carried: list[tuple[str, str]],
        step: Any,
        hint: str,
    ) -> list[str]:
        """``step(h_tile, values) -> new values`` over the rows of ``h`` [n, C], ``tile`` at a
        time (all at once when ``tile`` is 0); returns the final values."""
        if tile <= 0:
            return step(h, [v for v, _ in carried])
        n = self.op("Gather", self.op("Shape", h), self.scalar_i64(0), axis=0)
        t = self.scalar_i64(tile)
        trip = self.op("Div", self.op("Add", n, self.scalar_i64(tile - 1)), t)
        zero, one = self.i64(0), self.i64(1)

        def body(i: str, values: list[str]) -> tuple[list[str], list[str]]:
            # (the iteration number is a scalar or a [1] tensor, as runtimes pass it)
            start = self.op("Reshape", self.op("Mul", i, t), one)
            end = self.op("Add", start, self.i64(tile))
            part = self.op("Slice", h, start, end, zero)
            return step(part, values), []

        return self.loop(trip, carried, 0, body, hint)


def build_graph(
    cfg: Any,
    params: dict[str, Any],
    *,
    point_tile: int = 512,
    metadata: dict[str, str] | None = None,
) -> Any:
    """The ``onnx.ModelProto`` of the encoder ``cfg`` (a ``ModelConfig``) with ``params``:
    for PointNet :func:`~.folding.fold_model`'s dictionary, for bev-netvlad
    :func:`bev_params`' (every tensor float64 numpy or torch, cast to float32 here).
    ``point_tile``: points a tile of the widest layers (0: no tiling). ``metadata``: the
    model's ``metadata_props``."""
    from onnx import TensorProto, checker, helper

    if cfg.local_k:
        raise ValueError(
            "local shape features (local_k > 0) need a k-nearest-neighbour search, which the "
            "ONNX graph does not have: serve such a model with torch"
        )
    g = _Builder()
    points = "points"
    x = g.op("Slice", points, g.i64(0), g.i64(3), g.i64(2), hint="xyz")
    if cfg.canonical_heading:
        x = _canonical_heading(g, x)
    if cfg.arch == "bev-netvlad":
        out = _bev(g, cfg, _as_numpy(params), x)
    else:
        out = _pointnet(g, cfg, _as_numpy(params), x, point_tile)
    g.stack[-1].append(helper.make_node("Identity", [out], ["descriptor"]))
    graph = helper.make_graph(
        g.stack[0],
        f"pnvlad-{cfg.arch}",
        [helper.make_tensor_value_info(points, TensorProto.FLOAT, ["batch", "points", 3])],
        [helper.make_tensor_value_info("descriptor", TensorProto.FLOAT, ["batch", cfg.output_dim])],
        initializer=g.initializers,
    )
    model = helper.make_model(
        graph,
        opset_imports=[helper.make_opsetid("", OPSET)],
        producer_name="pnvlad",
        doc_string=f"pnvlad {cfg.arch} encoder: points [B, N, 3] -> unit descriptors [B, "
        f"{cfg.output_dim}]",
    )
    model.ir_version = 8  # ONNX Runtime 1.12 and later read it
    if metadata:
        helper.set_model_props(model, dict(metadata))
    checker.check_model(model)
    return model


def _as_numpy(p: Any) -> Any:
    """``p`` with every tensor as a numpy array (torch tensors converted; structure kept)."""
    if isinstance(p, dict):
        return {k: _as_numpy(v) for k, v in p.items()}
    if isinstance(p, list | tuple):
        return type(p)(_as_numpy(v) for v in p)
    if hasattr(p, "w") and hasattr(p, "b"):  # folding.Dense
        return type(p)(_as_numpy(p.w), _as_numpy(p.b))
    if hasattr(p, "detach"):
        return p.detach().cpu().numpy()
    return p


# --------------------------------------------------------------------------------------------
# PointNet: PN_VLAD and PN_MAX
# --------------------------------------------------------------------------------------------


def _max_layer(
    g: _Builder, h: str, w: np.ndarray | str, b: np.ndarray, tile: int, hint: str
) -> str:
    """``max over points of h @ w, + b`` [1, C_out] of one cloud's h [n, C_in], a tile at a
    time (bias after the max, which it commutes with)."""
    wn = w if isinstance(w, str) else g.const(w, f"{hint}_w")
    width = int(b.shape[-1])
    start = g.const(np.full((1, width), -np.inf), f"{hint}_start")

    def step(part: str, values: list[str]) -> list[str]:
        m = g.op("ReduceMax", g.op("MatMul", part, wn), axes=[0], keepdims=1)
        return [g.op("Max", values[0], m)]

    (m,) = g.tiles(h, tile, [(start, "max")], step, hint)
    return g.op("Add", m, g.const(b.reshape(1, -1), f"{hint}_b"))


def _tnet(g: _Builder, h: str, t: dict[str, Any], tile: int, hint: str) -> str:
    """One cloud's transform matrix [k, k] from its features h [n, c]."""
    layers = t["points"]
    for j, layer in enumerate(layers[:-1]):
        h = g.dense(h, layer.w, layer.b, True, f"{hint}_p{j}")
    last = layers[-1]
    v = g.op("Relu", _max_layer(g, h, last.w, last.b, tile, f"{hint}_max"))
    for j, layer in enumerate(t["fcs"]):
        v = g.dense(v, layer.w, layer.b, True, f"{hint}_fc{j}")
    v = g.dense(v, t["out"].w, t["out"].b, False, f"{hint}_out")
    k = int(t["k"])
    return g.op("Reshape", v, g.i64(k, k))


def _vlad_sums(
    g: _Builder, cfg: Any, p: dict[str, Any], h: str, w: np.ndarray | str, b: np.ndarray, tile: int
) -> tuple[str, str]:
    """The last trunk layer and NetVLAD's sums of one cloud: (sum_n a[n, k] x[n, d] [K, D],
    sum_n a[n, k] [1, K]) with x the (normalised) features, a the soft assignment."""
    k, d = cfg.cluster_size, cfg.feature_dim
    wn = w if isinstance(w, str) else g.const(w, "last_w")
    bn = g.const(b, "last_b")
    cw, cb = g.const(p["cluster"].w, "cluster_w"), g.const(p["cluster"].b, "cluster_b")
    relu, l2 = cfg.last_relu, cfg.point_l2_norm

    def step(part: str, values: list[str]) -> list[str]:
        vlad, total = values
        xt = g.op("Add", g.op("MatMul", part, wn), bn)
        if relu:
            xt = g.op("Relu", xt)
        logits = g.op("MatMul", xt, cw)
        inv = None
        if l2:
            norm = g.op("ReduceL2", xt, axes=[1], keepdims=1)
            inv = g.op("Reciprocal", g.op("Max", norm, g.const(1e-12)))
            logits = g.op("Mul", logits, inv)
        a = g.op("Softmax", g.op("Add", logits, cb), axis=-1)
        total = g.op("Add", total, g.op("ReduceSum", a, g.i64(0), keepdims=1))
        if inv is not None:
            a = g.op("Mul", a, inv)
        vlad = g.op("Add", vlad, g.op("MatMul", g.op("Transpose", a, perm=[1, 0]), xt))
        return [vlad, total]

    zeros = [(g.const(np.zeros((k, d)), "vlad0"), "vlad"), (g.const(np.zeros((1, k)), "a0"), "a")]
    vlad, total = g.tiles(h, tile, zeros, step, "vlad")
    return vlad, total


def _pointnet(g: _Builder, cfg: Any, p: dict[str, Any], x: str, tile: int) -> str:
    """PN_VLAD / PN_MAX: the per-point network cloud by cloud (a Loop), the head batched."""
    vlad = cfg.arch == "pointnetvlad"
    b = g.op("Gather", g.op("Shape", x), g.scalar_i64(0), axis=0)

    def cloud(i: str, _values: list[str]) -> tuple[list[str], list[str]]:
        h = g.op("Gather", x, g.op("Reshape", i, g.i64()), axis=0)  # [n, 3]
        if p["input_tnet"] is not None:
            h = g.op("MatMul", h, _tnet(g, h, p["input_tnet"], tile, "itnet"))
        for j, layer in enumerate(p["stem"]):
            h = g.dense(h, layer.w, layer.b, True, f"stem{j}")
        trunk = [(layer.w, layer.b) for layer in p["trunk"]]
        if p["feature_tnet"] is not None:
            t = _tnet(g, h, p["feature_tnet"], tile, "ftnet")
            trunk[0] = (g.op("MatMul", t, g.const(trunk[0][0], "ft_w")), trunk[0][1])
        for j, (w, bias) in enumerate(trunk[:-1]):
            h = g.dense(h, w, bias, True, f"trunk{j}")
        w, bias = trunk[-1]
        if not vlad:
            m = _max_layer(g, h, w, bias, tile, "trunk_max")
            return [], [g.op("Relu", m) if cfg.last_relu else m]
        sums, total = _vlad_sums(g, cfg, p, h, w, bias, tile)
        return [], [sums, total]

    outs = g.loop(b, [], 2 if vlad else 1, cloud, "clouds")
    if vlad:
        sums, total = outs  # [B, K, D], [B, 1, K]
        total = g.op("Transpose", total, perm=[0, 2, 1])  # [B, K, 1]
        return _vlad_head(g, cfg, p, sums, total)
    pooled = g.op("Reshape", outs[0], g.i64(0, -1))  # [B, D]
    return _fc_gate(g, p, pooled)


def _vlad_head(g: _Builder, cfg: Any, p: dict[str, Any], sums: str, total: str) -> str:
    """NetVLAD's normalisations, the fully connected layer and the gating, batched: ``sums``
    [B, K, D], ``total`` [B, K, 1] -> descriptors [B, out]."""
    k, d = cfg.cluster_size, p["centers"].shape[1]
    v = g.op("Sub", sums, g.op("Mul", total, g.const(p["centers"], "centers")))
    v = g.normalize(v, 2)  # intra-normalisation over D for every cluster
    v = g.normalize(g.op("Reshape", v, g.i64(0, k * d)), 1)
    return _fc_gate(g, p, v)


def _fc_gate(g: _Builder, p: dict[str, Any], v: str) -> str:
    fc = p["fc"]
    y = g.dense(v, fc.w, fc.b, False, "fc")
    if p["gate"] is not None:
        gate = p["gate"]
        y = g.op("Mul", y, g.op("Sigmoid", g.dense(y, gate.w, gate.b, False, "gate")))
    return g.normalize(y, 1)


# --------------------------------------------------------------------------------------------
# bev-netvlad
# --------------------------------------------------------------------------------------------


def bev_params(model: Any) -> dict[str, Any]:
    """A ``BEVNetVLAD``'s parameters (eval mode) for :func:`build_graph`, in float64: each
    convolution with the batch norm after it folded in (``convs``: weight, bias, stride, relu),
    and the NetVLAD head (:func:`~.folding.fold_head`)."""
    import torch
    from torch import nn

    from pnvlad_service.models.folding import fold_head

    convs: list[dict[str, Any]] = []
    layers = list(model.cnn)
    i = 0
    while i < len(layers):
        conv = layers[i]
        assert isinstance(conv, nn.Conv2d)
        w = conv.weight.detach().double()
        b = (
            conv.bias.detach().double()
            if conv.bias is not None
            else torch.zeros(w.shape[0], dtype=torch.float64)
        )
        i += 1
        if i < len(layers) and isinstance(layers[i], nn.BatchNorm2d):
            bn = layers[i]
            s = bn.weight.detach().double() / torch.sqrt(bn.running_var.double() + bn.eps)
            w = w * s[:, None, None, None]
            b = (b - bn.running_mean.double()) * s + bn.bias.detach().double()
            i += 1
        relu = i < len(layers) and isinstance(layers[i], nn.ReLU)
        i += relu
        convs.append(
            {
                "w": w,
                "b": b,
                "stride": int(conv.stride[0]),
                "pad": int(conv.padding[0]),
                "relu": relu,
            }
        )
    return {"convs": convs, **fold_head(model.pool, True)}


def _bev(g: _Builder, cfg: Any, p: dict[str, Any], x: str) -> str:
    """bev-netvlad on the whole batch: the histogram, the CNN, the cells through the head."""
    img = _bev_image(g, cfg, x)
    for j, c in enumerate(p["convs"]):
        k = int(c["w"].shape[-1])
        img = g.op(
            "Conv",
            img,
            g.const(c["w"], f"conv{j}_w"),
            g.const(c["b"], f"conv{j}_b"),
            kernel_shape=[k, k],
            strides=[c["stride"]] * 2,
            pads=[c["pad"]] * 4,
        )
        if c["relu"]:
            img = g.op("Relu", img)
    d = cfg.bev_feature_dim
    cells = g.op("Transpose", g.op("Reshape", img, g.i64(0, d, -1)), perm=[0, 2, 1])  # [B, M, D]
    if cfg.point_l2_norm:
        cells = g.normalize(cells, 2)
    logits = g.op(
        "Add",
        g.op("MatMul", cells, g.const(p["cluster"].w, "cluster_w")),
        g.const(p["cluster"].b, "cluster_b"),
    )
    a = g.op("Softmax", logits, axis=-1)  # [B, M, K]
    sums = g.op("MatMul", g.op("Transpose", a, perm=[0, 2, 1]), cells)  # [B, K, D]
    total = g.op("Transpose", g.op("ReduceSum", a, g.i64(1), keepdims=1), perm=[0, 2, 1])
    return _vlad_head(g, cfg, p, sums, total)


def _bev_image(g: _Builder, cfg: Any, x: str) -> str:
    """``bev.bev_image``: float32 [B, Z, G, G], log(1 + points counted) per cell and slice."""
    grid, z = cfg.bev_grid, cfg.bev_height_bins
    lo, hi = cfg.bev_z_range
    shape = g.op("Shape", x)
    b = g.op("Gather", shape, g.i64(0), axis=0)  # [1]

    def coord(axis: int) -> str:
        return g.op("Squeeze", g.op("Slice", x, g.i64(axis), g.i64(axis + 1), g.i64(2)), g.i64(2))

    px, py, pz = coord(0), coord(1), coord(2)
    inside = g.op(
        "Cast",
        g.op("LessOrEqual", g.op("Max", g.op("Abs", px), g.op("Abs", py)), g.const(1.0)),
        to=1,
    )

    def cell(v: str, offset: float, scale: float, cells: int) -> str:
        u = g.op("Mul", g.op("Add", v, g.const(offset)), g.const(scale))
        u = g.op("Clip", g.op("Floor", u), g.const(0.0), g.const(float(cells - 1)))
        return g.op("Cast", u, to=7)  # int64

    ix = cell(px, 1.0, grid / 2, grid)
    iy = cell(py, 1.0, grid / 2, grid)
    iz = cell(pz, -lo, z / (hi - lo), z)
    batch = g.op(
        "Unsqueeze",
        g.op("Range", g.scalar_i64(0), g.op("Squeeze", b, g.i64(0)), g.scalar_i64(1)),
        g.i64(1),
    )  # [B, 1]
    flat = g.op("Add", g.op("Mul", batch, g.scalar_i64(z)), iz)
    flat = g.op("Add", g.op("Mul", flat, g.scalar_i64(grid)), iy)
    flat = g.op("Add", g.op("Mul", flat, g.scalar_i64(grid)), ix)
    size = g.op("Mul", b, g.i64(z * grid * grid))
    counts = g.op("ConstantOfShape", size)  # float32 zeros
    counts = g.op(
        "ScatterElements",
        counts,
        g.op("Reshape", flat, g.i64(-1)),
        g.op("Reshape", inside, g.i64(-1)),
        axis=0,
        reduction="add",
    )
    img = g.op("Log", g.op("Add", counts, g.const(1.0)))
    return g.op("Reshape", img, g.i64(-1, z, grid, grid))


# --------------------------------------------------------------------------------------------
# canonical heading
# --------------------------------------------------------------------------------------------


def _atan2(g: _Builder, y: str, x: str) -> str:
    """``atan2(y, x)`` elementwise from ``Atan`` and the quadrants (0 where both are 0)."""
    zero = g.const(0.0)
    safe_x = g.op("Where", g.op("Equal", x, zero), g.const(1.0), x)
    base = g.op("Atan", g.op("Div", y, safe_x))
    neg_x = g.op("Less", x, zero)
    y_neg = g.op("Less", y, zero)
    pi = g.const(math.pi)
    shift = g.op("Where", y_neg, g.op("Neg", pi), pi)
    angle = g.op("Where", neg_x, g.op("Add", base, shift), base)
    half = g.op("Where", y_neg, g.const(-math.pi / 2), g.const(math.pi / 2))
    on_axis = g.op("Where", g.op("Equal", y, zero), zero, half)
    return g.op("Where", g.op("Equal", x, zero), on_axis, angle)


def _canonical_heading(g: _Builder, x: str) -> str:
    """``heading.canonical_heading`` of points [B, N, 3]: each cloud turned about z by minus
    its dominant angle."""
    grid = HEADING_GRID
    shape = g.op("Shape", x)
    b = g.op("Gather", shape, g.i64(0), axis=0)  # [1]
    p = g.op("Slice", x, g.i64(0), g.i64(2), g.i64(2))  # [B, N, 2]
    inside = g.op(
        "Cast",
        g.op("LessOrEqual", g.op("ReduceMax", g.op("Abs", p), axes=[2], keepdims=0), g.const(1.0)),
        to=1,
    )  # [B, N]
    u = g.op("Sub", g.op("Mul", g.op("Add", p, g.const(1.0)), g.const(grid / 2)), g.const(0.5))
    u = g.op("Clip", u, g.const(0.0), g.const(grid - 1.001))
    i0 = g.op("Floor", u)
    f = g.op("Sub", u, i0)
    i0 = g.op("Cast", i0, to=7)

    def part(t: str, axis: int) -> str:
        return g.op("Squeeze", g.op("Slice", t, g.i64(axis), g.i64(axis + 1), g.i64(2)), g.i64(2))

    fx, fy, ix, iy = part(f, 0), part(f, 1), part(i0, 0), part(i0, 1)
    one = g.const(1.0)
    batch = g.op(
        "Unsqueeze",
        g.op("Range", g.scalar_i64(0), g.op("Squeeze", b, g.i64(0)), g.scalar_i64(1)),
        g.i64(1),
    )
    base = g.op("Mul", batch, g.scalar_i64(grid * grid))  # [B, 1]
    index, weight = [], []
    for dx in (0, 1):
        for dy in (0, 1):
            wx = fx if dx else g.op("Sub", one, fx)
            wy = fy if dy else g.op("Sub", one, fy)
            row = g.op("Mul", g.op("Add", iy, g.scalar_i64(dy)), g.scalar_i64(grid))
            flat = g.op("Add", g.op("Add", base, row), g.op("Add", ix, g.scalar_i64(dx)))
            index.append(g.op("Reshape", flat, g.i64(-1)))
            weight.append(g.op("Reshape", g.op("Mul", g.op("Mul", wx, wy), inside), g.i64(-1)))
    counts = g.op("ConstantOfShape", g.op("Mul", b, g.i64(grid * grid)))
    counts = g.op(
        "ScatterElements",
        counts,
        g.op("Concat", *index, axis=0),
        g.op("Concat", *weight, axis=0),
        axis=0,
        reduction="add",
    )
    img = g.op("Reshape", g.op("Log", g.op("Add", counts, one)), g.i64(-1, 1, grid, grid))
    k = np.array([1.0, 2.0, 1.0]) / 4.0
    blur = g.const((k[:, None] * k[None, :])[None, None], "blur")
    for _ in range(2):
        img = g.op("Conv", img, blur, kernel_shape=[3, 3], pads=[1, 1, 1, 1])
    sx = np.array([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]])
    gx = g.op("Conv", img, g.const(sx[None, None], "sobel_x"), kernel_shape=[3, 3], pads=[1] * 4)
    gy = g.op("Conv", img, g.const(sx.T[None, None], "sobel_y"), kernel_shape=[3, 3], pads=[1] * 4)
    # weight * cos(4θ) and weight * sin(4θ), weight = |g|², θ the gradient's angle.
    gx2, gy2 = g.op("Mul", gx, gx), g.op("Mul", gy, gy)
    r2 = g.op("Add", gx2, gy2)
    c2 = g.op("Sub", gx2, gy2)  # r² cos 2θ
    s2 = g.op("Mul", g.op("Mul", gx, gy), g.const(2.0))  # r² sin 2θ
    zero = g.const(0.0)
    flat_r2 = g.op("Where", g.op("Equal", r2, zero), one, r2)
    re = g.op("Div", g.op("Sub", g.op("Mul", c2, c2), g.op("Mul", s2, s2)), flat_r2)
    im = g.op("Div", g.op("Mul", g.op("Mul", c2, s2), g.const(2.0)), flat_r2)
    re = g.op("ReduceSum", re, g.i64(1, 2, 3), keepdims=0)  # [B]
    im = g.op("ReduceSum", im, g.i64(1, 2, 3), keepdims=0)
    angle = g.op("Div", _atan2(g, im, re), g.const(4.0))
    quarter = g.const(math.pi / 4)
    wrap = g.op("GreaterOrEqual", angle, quarter)
    angle = g.op("Where", wrap, g.op("Sub", angle, g.const(math.pi / 2)), angle)
    a = g.op("Unsqueeze", g.op("Neg", angle), g.i64(1))  # [B, 1]
    c, s = g.op("Cos", a), g.op("Sin", a)
    px, py = part(x, 0), part(x, 1)
    nx = g.op("Sub", g.op("Mul", c, px), g.op("Mul", s, py))
    ny = g.op("Add", g.op("Mul", s, px), g.op("Mul", c, py))
    xy = g.op("Concat", g.op("Unsqueeze", nx, g.i64(2)), g.op("Unsqueeze", ny, g.i64(2)), axis=2)
    return g.op("Concat", xy, g.op("Slice", x, g.i64(2), g.i64(3), g.i64(2)), axis=2)
