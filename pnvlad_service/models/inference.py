"""``Encoder``: fast CPU inference of a trained PN_VLAD / PN_MAX model (and bev-netvlad's).

The encoder runs the network as the matrix products it is, on plain tensors:

- every batch norm is folded into the layer before it (``W' = W * s``, ``b' = (b - mean) * s +
  beta`` with ``s = gamma / sqrt(var + eps)``; ``folding.py``);
- per-point layers are ``addmm`` on the points x channels matrix [N, C], ReLU in place;
- the feature transform is folded into the next layer's weights per cloud (``(h T) W = h (T W)``);
- max-pooled layers (transform nets, PN_MAX) take the max over points *before* the bias and ReLU
  (both commute with a per-channel max);
- the per-point L2 normalisation of the published code never materialises the normalised
  features: the norms divide the K cluster logits and the soft-assignment weights instead;
- the per-point network runs one cloud at a time and its widest layer (with the NetVLAD sums
  [K, N] x [N, D], or the max of PN_MAX) ``point_tile`` points at a time, so activations stay in
  cache; the fully connected head runs on the whole batch as one product;
- on CPU, a batch of several clouds is spread over ``cloud_workers`` threads (default: torch's
  thread count), each running whole clouds with one intra-op thread. Small products and the
  element-wise steps between them then keep every core busy instead of one core waiting for the
  other at each of the ~100 operations of a cloud (measured on 2 cores: ~20 % more clouds/s at
  batch 32). A single cloud still uses all of torch's threads - unless other work holds the
  cores (another batch in flight, or ``crowded_by``: a server's verification), when the clouds,
  the head and bev-netvlad's module all run on the single-threaded workers (``_forward``).

bev-netvlad (``models/bev.py``) is a CNN, not per-point products: the encoder runs its module in
eval mode on the whole batch (on all of torch's threads, or on one cloud worker when crowded;
``point_tile`` does not apply); ``dtype="bfloat16"`` runs its convolutions under bfloat16
autocast and its NetVLAD head in float32.

``dtype="bfloat16"`` runs the matrix products in bfloat16 (fast on CPUs with AMX / AVX512-BF16);
``dtype="auto"`` uses bfloat16 only when the CPU supports it *and* a self-check on given clouds
shows top-1 retrieval agreeing with float32 on at least 99 % of the queries.
"""

from __future__ import annotations

import copy
import hashlib
import logging
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pnvlad_service.errors import InputError
from pnvlad_service.models.config import ModelConfig
from pnvlad_service.models.embedding import over_scales
from pnvlad_service.models.folding import Dense, cast_folded, fold_model
from pnvlad_service.models.local_shape import split_inputs

if TYPE_CHECKING:
    import torch

log = logging.getLogger(__name__)

#: Share of self-check queries whose top-1 neighbour must agree for bfloat16 to be used.
BF16_MIN_AGREEMENT = 0.99

# The one thread of the process that runs torch on all of its intra-op threads.
#
# GNU OpenMP (torch's CPU runtime) gives every thread that opens a parallel region a team of
# its own. Once the process holds more OpenMP threads than there are CPUs (two server lanes,
# each with its team, on 2 cores; or the loading thread's team and a lane's), libgomp
# throttles the spinning its threads do between regions to about 100 iterations, and each of
# the ~100 parallel regions of a forward pass then waits for a futex wake-up instead: the
# paper model's batch-1 embedding took 33-38 ms against 24-25 on the same 2 cores
# (docs/results/service.md, "one OpenMP team"). So all of the Encoder's multi-threaded work -
# loading and folding the weights, single clouds, the head - runs on this thread, whichever thread
# calls; the cloud workers run on one intra-op thread each, which opens no team (and take the
# head too while the encoder is crowded: Encoder._forward).
_torch_thread: ThreadPoolExecutor | None = None
_torch_thread_lock = threading.Lock()
_on_torch_thread = threading.local()


def on_torch_thread(fn: Any, *args: Any, **kwargs: Any) -> Any:
    """``fn(*args, **kwargs)`` on the process's torch thread (started on first use), waited
    for; called from that thread it runs at once."""
    global _torch_thread
    if getattr(_on_torch_thread, "yes", False):
        return fn(*args, **kwargs)
    with _torch_thread_lock:
        if _torch_thread is None:

            def mark() -> None:
                _on_torch_thread.yes = True

            _torch_thread = ThreadPoolExecutor(
                1, thread_name_prefix="pnvlad-torch", initializer=mark
            )
    return _torch_thread.submit(fn, *args, **kwargs).result()


def bf16_supported() -> bool:
    """True when this CPU has native bfloat16 matrix instructions (AVX512-BF16 or AMX) in oneDNN."""
    import torch

    try:
        return bool(
            torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported()
        )
    except (AttributeError, RuntimeError):
        return False


def _state_sha256(model: Any) -> str:
    """SHA-256 of the model's weights serialised as ``save_model`` writes ``model.safetensors``."""
    from safetensors.torch import save

    from pnvlad_service.models.store import FORMAT

    state = {k: v.detach().to("cpu").contiguous() for k, v in model.state_dict().items()}
    return hashlib.sha256(save(state, metadata={"format": FORMAT})).hexdigest()


class Encoder:
    """Batch-norm-folded, inference-mode encoder.

    ``Encoder(model, cfg)`` or ``Encoder.from_checkpoint(dir)``; ``embed(points)`` with points
    float [B, N, 3] or [N, 3] (numpy or torch, coordinates as the model was trained on: submaps in
    [-1, 1]) returns numpy float32 [B, dim], each row of unit L2 norm.

    ``dtype``: ``"float32"`` (default), ``"bfloat16"`` (matrix products in bfloat16; refused when
    the CPU lacks it), or ``"auto"`` (bfloat16 when supported and ``check_points``, float
    [M, N, 3] with M >= 3, show top-1 leave-one-out retrieval agreeing with float32 on at least
    99 % of the M clouds; float32 otherwise). The per-point network runs one cloud at a time,
    ``point_tile`` points at a time (cache blocking); the fully connected head runs on
    ``batch_size`` clouds at a time as one product. ``cloud_workers``: threads that run the
    clouds of a batch side by side on CPU, one intra-op thread each (None: torch's thread count
    when the first batch comes; 1: one cloud at a time on all of torch's threads).
    """

    #: Which runtime embeds (``OnnxEncoder.runtime`` is ``"onnx"``; ``runtimes.py``).
    runtime = "torch"

    def __init__(
        self,
        model: torch.nn.Module,
        cfg: ModelConfig,
        *,
        device: str | None = None,
        dtype: str = "float32",
        check_points: Any = None,
        batch_size: int = 32,
        point_tile: int = 512,
        cloud_workers: int | None = None,
        weights_sha256: str | None = None,
    ) -> None:
        import torch

        if dtype not in ("float32", "bfloat16", "auto"):
            raise InputError(f"dtype must be float32, bfloat16 or auto, got {dtype!r}", "dtype")
        if batch_size < 1:
            raise InputError(f"batch_size must be >= 1, got {batch_size}", "batch_size")
        if cloud_workers is not None and cloud_workers < 1:
            raise InputError(f"cloud_workers must be >= 1, got {cloud_workers}", "cloud_workers")
        self.cloud_workers = cloud_workers
        #: Whether other work holds the cores right now (a server sets it to "a verification
        #: is in flight"): while it says so, a lone batch's clouds, its head and bev-netvlad's
        #: module go to the cloud workers, one thread each, as when other batches are in
        #: flight, rather than to all of torch's threads opposite a busy core (``_forward``).
        self.crowded_by: Callable[[], bool] | None = None
        self._pool: ThreadPoolExecutor | None = None
        self._workers = 1
        self._embedding = 0  # forward passes in progress, over all calling threads
        self._pool_lock = threading.Lock()
        self.cfg = cfg
        self.device = torch.device(device or "cpu")
        self.batch_size = batch_size
        self.point_tile = point_tile
        self._sha = weights_sha256 or _state_sha256(model)
        self.agreement: float | None = None
        #: bev-netvlad runs as its module (a copy in eval mode: convolutions are already one
        #: product each, and there is no batch norm left to fold that would save a pass).
        self._module: torch.nn.Module | None = None
        self._p: dict[str, Any] = {}
        if cfg.arch == "bev-netvlad":
            self._module = copy.deepcopy(model).eval().to(self.device, torch.float32)
        else:
            was_training = model.training
            model.eval()
            self._p = fold_model(model)
            model.train(was_training)
        self._params: dict[str, dict[str, Any]] = {}
        if dtype == "auto":
            dtype = self._choose_dtype(check_points)
        elif dtype == "bfloat16" and not bf16_supported():
            raise InputError("this CPU has no native bfloat16 support; use float32", "dtype")
        self.dtype = dtype

    # -- construction -------------------------------------------------------------------------

    @classmethod
    def from_checkpoint(
        cls,
        directory: str | Path,
        device: str | None = None,
        *,
        weights_sha256: str | None = None,
        **kwargs: Any,
    ) -> Encoder:
        """Load a model directory (``model.json`` + ``model.safetensors``) into an Encoder.
        ``weights_sha256``: the weights' hash when the caller has just taken it (a
        ``ModelIdentity``), so that the 64 MB file of the paper model is not hashed twice."""
        from pnvlad_service.models import store

        def load() -> Encoder:
            model, cfg = store.load_model(directory)
            sha = weights_sha256 or store.weights_sha256(directory)
            return cls(model, cfg, device=device, weights_sha256=sha, **kwargs)

        return on_torch_thread(load)  # the weights' copies and folding are multi-threaded

    def _cast(self, dtype: str) -> dict[str, Any]:
        """The folded parameters on the device for ``dtype`` (made once, then reused); for
        bev-netvlad, its module (bfloat16 runs it under autocast)."""
        if self._module is not None:
            return {"module": self._module, "dtype": dtype}
        if dtype not in self._params:
            self._params[dtype] = cast_folded(self._p, dtype, self.device)
        return self._params[dtype]

    # -- properties ---------------------------------------------------------------------------

    @property
    def dim(self) -> int:
        """Descriptor size (``cfg.output_dim``)."""
        return self.cfg.output_dim

    @property
    def weights_sha256(self) -> str:
        """SHA-256 of the weights (equal to ``store.weights_sha256`` of the checkpoint)."""
        return self._sha

    # -- inference ----------------------------------------------------------------------------

    def embed(self, points: Any) -> np.ndarray:
        """Descriptors float32 [B, dim] (unit rows) of points float [B, N, 3] or [N, 3].

        On CPU every step that runs on all of torch's threads (a single cloud, the head; on a
        cloud worker instead while crowded, see ``_forward``) runs on the process's torch
        thread (:func:`on_torch_thread`), and the calling thread opens
        no OpenMP team of its own."""
        import torch

        x = self._as_tensor(points)
        out = torch.empty((x.shape[0], self.dim), dtype=torch.float32)
        with torch.inference_mode():
            q = self._all_threads(self._cast, self.dtype)  # the first cast copies every weight

            def forward(c: torch.Tensor) -> torch.Tensor:
                return self._forward(c, q)

            def unit(t: torch.Tensor) -> torch.Tensor:
                return torch.nn.functional.normalize(t, dim=1)

            for s in range(0, x.shape[0], self.batch_size):
                chunk = x[s : s + self.batch_size].to(self.device, torch.float32)
                out[s : s + chunk.shape[0]] = over_scales(
                    forward, chunk, self.cfg.embed_scales, unit
                ).cpu()
        return out.numpy()

    def _as_tensor(self, points: Any) -> torch.Tensor:
        import torch

        if isinstance(points, torch.Tensor):
            x: Any = points.detach()
            numeric = x.is_floating_point() or x.dtype in (torch.int32, torch.int64)
        else:
            # Arrays are checked and converted in numpy: torch would run these passes over a
            # batch on all of its threads in the calling thread (see on_torch_thread).
            x = np.asarray(points)
            numeric = np.issubdtype(x.dtype, np.floating) or x.dtype in (np.int32, np.int64)
        if x.ndim == 2:
            x = x[None]
        channels = (3, self.cfg.input_dim)
        if x.ndim != 3 or x.shape[-1] not in channels or x.shape[1] < 1:
            want = "[B, N, 3] or [N, 3]"
            if self.cfg.local_k:
                want += f" (or with their {self.cfg.input_dim - 3} shape features appended)"
            raise InputError(f"expected points of shape {want}, got {list(x.shape)}", "points")
        if not numeric:
            raise InputError(f"expected float coordinates, got {x.dtype}", "points")
        if isinstance(x, np.ndarray):
            x = np.ascontiguousarray(x, dtype=np.float32)
            finite = bool(np.isfinite(x).all())
            x = torch.from_numpy(x)
        else:
            x = x.to(torch.float32).contiguous()
            finite = bool(torch.isfinite(x).all())
        if not finite:
            raise InputError("points contain NaN or infinite coordinates", "points")
        return x

    def _tiles(self, n: int) -> range:
        return range(0, n, self.point_tile)

    def _max_layer(self, h: torch.Tensor, layer: Dense) -> torch.Tensor:
        """``relu(max over points of h @ w + b)`` float32 [C_out] for one cloud's h [n, C_in].

        The product is taken a tile of points at a time so its output stays in cache; bias and
        ReLU come after the max (they commute with a per-channel max).
        """
        import torch

        m: torch.Tensor | None = None
        for s in self._tiles(h.shape[0]):
            t = (h[s : s + self.point_tile] @ layer.w).amax(dim=0)
            m = t if m is None else torch.maximum(m, t)
        assert m is not None
        return m.float().add_(layer.b)

    def _tnet(self, h: torch.Tensor, t: dict[str, Any], mm: torch.dtype) -> torch.Tensor:
        """Transform matrix float32 [k, k] of one cloud's per-point features h [n, c]."""
        import torch

        layers = t["points"]
        g = h.to(mm)
        for layer in layers[:-1]:
            g = torch.addmm(layer.b.to(mm), g, layer.w).relu_()
        g = self._max_layer(g, layers[-1]).relu_().unsqueeze(0)
        for layer in t["fcs"]:
            g = torch.addmm(layer.b, g, layer.w).relu_()
        g = torch.addmm(t["out"].b, g, t["out"].w)
        return g.reshape(t["k"], t["k"])

    def _forward(self, x: torch.Tensor, q: dict[str, Any]) -> torch.Tensor:
        """Descriptors float32 [b, out] of points float32 [b, n, 3] (folded network).

        The per-point network runs cloud by cloud (its activations stay in cache), several
        clouds side by side on the worker threads (``_clouds``); the fully connected head runs
        on the whole batch as one product. bev-netvlad: its module on the whole batch.
        """
        with self._pool_lock:
            self._embedding += 1
            alone = self._embedding == 1
        try:
            if alone and self.crowded_by is not None and self.crowded_by():
                alone = False
            # Crowded, the head (and bev-netvlad's whole module) goes to a cloud worker too: on
            # all threads, its parallel regions each wait at a barrier for the thread that has
            # no core (docs/SERVICE.md, "How a request runs").
            if self._module is not None:  # bev-netvlad turns its clouds itself
                fn, args = self._module_forward, (x, q)
            else:
                if self.cfg.canonical_heading:
                    from pnvlad_service.models.heading import canonical_heading

                    x = self._all_threads(canonical_heading, x)
                fn, args = self._head, (self._clouds(x, q, alone), q)
            pool = None if alone or self.device.type != "cpu" else self._worker_pool()
            if pool is None:
                return self._all_threads(fn, *args)
            return pool.submit(fn, *args).result()
        finally:
            with self._pool_lock:
                self._embedding -= 1

    def _module_forward(self, x: torch.Tensor, q: dict[str, Any]) -> torch.Tensor:
        import torch

        # bfloat16: the convolutions only. The NetVLAD head in bfloat16 moved trained descriptors
        # 3x as far (median 0.027 against 0.009 with it in float32) and kept 98.0 % of 1,000
        # benchmark submaps' top-1 against 99.4 % (docs/MODEL.md); it is a small part of the work.
        m, low = q["module"], q["dtype"] == "bfloat16"
        with torch.inference_mode():  # thread-local: entered again on the thread it runs on
            with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=low):
                cells = m.cell_features(x)
            return m.head(cells.float()).float()

    def _all_threads(self, fn: Any, *args: Any) -> Any:
        """``fn(*args)``, work on all of torch's threads: on the process's torch thread on CPU
        (:func:`on_torch_thread`), in the calling thread on a GPU."""
        return on_torch_thread(fn, *args) if self.device.type == "cpu" else fn(*args)

    def _head(self, parts: list[torch.Tensor], q: dict[str, Any]) -> torch.Tensor:
        """Descriptors float32 [b, out] of the clouds' pooled features: NetVLAD's
        normalisations (PN_VLAD), the fully connected layer and the gating."""
        import torch

        with torch.inference_mode():  # thread-local: entered again on the thread it runs on
            return self._head_products(torch.stack(parts), q)

    def _head_products(self, pooled: torch.Tensor, q: dict[str, Any]) -> torch.Tensor:
        import torch
        import torch.nn.functional as F

        if self.cfg.arch == "pointnetvlad":
            k, d = self.cfg.cluster_size, self.cfg.feature_dim
            v = pooled[:, : k * d].reshape(-1, k, d)
            a_sum = pooled[:, k * d :]
            v = v.sub_(a_sum.unsqueeze(-1) * q["centers"])
            v = F.normalize(v, dim=2)  # intra-normalisation over D for every cluster
            pooled = F.normalize(v.reshape(v.shape[0], -1), dim=1)
        fc = q["fc"]
        # float32 fc.w is [out, in], bfloat16 fc.w [in, out] (see _cast)
        f32 = fc.w.dtype == torch.float32
        y = F.linear(pooled, fc.w) if f32 else pooled.to(fc.w.dtype) @ fc.w
        y = y.float().add_(fc.b)
        if q["gate"] is not None:
            g = q["gate"]
            y = y * torch.sigmoid(torch.addmm(g.b, y, g.w))
        return F.normalize(y, dim=1)

    def _clouds(self, x: torch.Tensor, q: dict[str, Any], alone: bool) -> list[torch.Tensor]:
        """``_cloud`` of every cloud of x [b, n, 3], in order.

        On CPU with W > 1 workers, clouds go W at a time to the worker threads (one intra-op
        thread each). A last group of at most W/2 clouds, which would leave most workers idle,
        runs here one cloud at a time on all of torch's threads instead (on 2 cores: a batch of
        3 takes two single-threaded cloud times plus one two-threaded one, not three) - unless
        the batch is not ``alone`` (other threads are embedding at the same time, or
        ``crowded_by`` says other work holds the cores), when every cloud goes to the workers:
        a team of threads of which one waits for a busy core spends its time at the barriers
        of the forward pass's ~100 parallel regions (one paper cloud beside a busy core: 93 ms
        on all threads, 52 ms on a worker; docs/results/service.md, "a crowded encoder").
        """
        b = x.shape[0]
        pool = self._worker_pool() if self.device.type == "cpu" and (b > 1 or not alone) else None
        if pool is None:
            return self._here(x, q, range(b))
        workers = self._workers
        rest = b % workers
        side_by_side = b if (rest > workers / 2 or not alone) else b - rest

        def one(i: int) -> torch.Tensor:
            import torch

            with torch.inference_mode():  # thread-local: enter it in the worker too
                return self._cloud(x[i], q)

        out = list(pool.map(one, range(side_by_side)))
        return out + self._here(x, q, range(side_by_side, b))

    def _here(self, x: torch.Tensor, q: dict[str, Any], rows: range) -> list[torch.Tensor]:
        """``_cloud`` of ``x[rows]`` one after the other on all of torch's threads: on the
        torch thread on CPU."""
        import torch

        def run() -> list[torch.Tensor]:
            with torch.inference_mode():
                return [self._cloud(x[i], q) for i in rows]

        return self._all_threads(run) if rows else []

    def _worker_pool(self) -> ThreadPoolExecutor | None:
        """The cloud worker threads (made on first use), or None for a single worker."""
        import torch

        with self._pool_lock:
            if self._pool is None:
                workers = self.cloud_workers or torch.get_num_threads()
                if workers < 2:
                    return None

                def single_threaded() -> None:
                    # OpenMP's thread count is per calling thread: this leaves the rest of the
                    # process (and a lone batch of one cloud) on all of torch's threads.
                    torch.set_num_threads(1)

                self._workers = workers
                self._pool = ThreadPoolExecutor(
                    workers, thread_name_prefix="pnvlad-encoder", initializer=single_threaded
                )
            return self._pool

    def close(self) -> None:
        """Stop the cloud worker threads (a later batch starts them again)."""
        with self._pool_lock:
            if self._pool is not None:
                self._pool.shutdown(wait=True)
                self._pool = None

    def _cloud(self, x: torch.Tensor, q: dict[str, Any]) -> torch.Tensor:
        """One cloud x float32 [n, 3] (or [n, 10] with its shape features) -> pooled float32:
        PN_VLAD the un-normalised residual sums [K*D] (cluster-major) followed by the
        soft-assignment totals [K]; PN_MAX the max [D]."""
        import torch

        cfg = self.cfg
        mm = q["mm"]
        xyz, shape = split_inputs(x.unsqueeze(0), cfg.local_k)  # features computed here
        x = xyz[0]
        if q["input_tnet"] is not None:
            x = x @ self._tnet(x, q["input_tnet"], mm)
        if shape is not None:
            x = torch.cat([x, shape[0]], dim=1)
        h = x.to(mm)
        for layer in q["stem"]:
            h = torch.addmm(layer.b.to(mm), h, layer.w).relu_()
        trunk: list[Dense] = q["trunk"]
        last = len(trunk) - 1
        start = 0
        if q["feature_tnet"] is not None:
            t = self._tnet(h, q["feature_tnet"], mm)  # [c, c]
            first = trunk[0]
            w = (t @ first.w.float()).to(mm)  # (h T) W = h (T W)
            if last == 0:
                trunk = [Dense(w, first.b)]
            else:
                h = torch.addmm(first.b.to(mm), h, w).relu_()
                start = 1
        for layer in trunk[start:last]:
            h = torch.addmm(layer.b.to(mm), h, layer.w).relu_()
        if cfg.arch != "pointnetvlad":
            m = self._max_layer(h, trunk[last])
            return m.relu_() if cfg.last_relu else m
        return self._vlad_sums(h, trunk[last], q)

    def _vlad_sums(self, h: torch.Tensor, layer: Dense, q: dict[str, Any]) -> torch.Tensor:
        """The last trunk layer and NetVLAD's sums for one cloud, a tile of points at a time.

        Returns float32 [K*D + K]: ``sum_n a[n, k] x[n, d]`` ([K, D] flattened) and
        ``sum_n a[n, k]`` where x are the (per-point normalised) features and a the soft
        assignment.
        """
        import torch

        cl = q["cluster"]
        mm = q["mm"]
        k, d = self.cfg.cluster_size, self.cfg.feature_dim
        l2 = self.cfg.point_l2_norm
        relu = self.cfg.last_relu
        if not relu and not l2:
            # The port's configuration: x = h W + b is affine in h, so the [n, D] features are
            # never formed: logits h (W Wc) + (b Wc + c), sums (a^T h) W + (sum_n a) b.
            w, wc = layer.w.float(), cl.w.float()
            hf = h.float()
            a = torch.softmax(torch.addmm(layer.b @ wc + cl.b, hf, w @ wc), dim=-1)
            a_sum = a.sum(dim=0)
            vlad = torch.addmm(a_sum.unsqueeze(1) * layer.b, a.t() @ hf, w)
            return torch.cat([vlad.reshape(-1), a_sum])
        vlad = torch.zeros((k, d), dtype=torch.float32, device=h.device)
        a_sum = torch.zeros(k, dtype=torch.float32, device=h.device)
        bias = layer.b.to(mm)
        for s in self._tiles(h.shape[0]):
            xt = torch.addmm(bias, h[s : s + self.point_tile], layer.w)
            if relu:
                xt = xt.relu_()
            logits = (xt @ cl.w).float()  # [T, K]
            if l2:
                # softmax(BN((x / |x|) W)) == softmax(BN'(x W) / |x| + c): never build x / |x|.
                inv = torch.linalg.vector_norm(xt, dim=1, dtype=torch.float32).clamp_min_(1e-12)
                inv = inv.reciprocal_().unsqueeze(-1)
                logits = logits.mul_(inv)
            a = torch.softmax(logits.add_(cl.b), dim=-1)
            a_sum += a.sum(dim=0)
            if l2:
                a = a.mul_(inv)
            if mm == torch.float32:
                vlad.addmm_(a.t(), xt)
            else:
                vlad += (a.t().to(mm) @ xt).float()
        return torch.cat([vlad.reshape(-1), a_sum])

    # -- bfloat16 self-check ------------------------------------------------------------------

    def _choose_dtype(self, check_points: Any) -> str:
        if not bf16_supported():
            log.info("dtype auto: float32 (no native bfloat16 on this CPU)")
            return "float32"
        if check_points is None:
            log.info("dtype auto: float32 (no clouds given for the bfloat16 self-check)")
            return "float32"
        x = self._as_tensor(check_points)
        if x.shape[0] < 3:
            raise InputError("the bfloat16 self-check needs at least 3 clouds", "check_points")
        self.dtype = "float32"
        ref = self.embed(x)
        self.dtype = "bfloat16"
        low = self.embed(x)
        self.agreement = top1_agreement(ref, low)
        chosen = "bfloat16" if self.agreement >= BF16_MIN_AGREEMENT else "float32"
        log.info(
            "dtype auto: %s (bfloat16 top-1 agreement %.1f %% on %d clouds)",
            chosen,
            100 * self.agreement,
            x.shape[0],
        )
        return chosen


def other_distances(desc: np.ndarray) -> np.ndarray:
    """float64 [M, M]: the Euclidean distance of each row of ``desc`` [M, D] to every other
    row, inf on the diagonal (a row is not its own neighbour)."""
    d = desc.astype(np.float64)
    sq = (d * d).sum(1)
    dist = np.sqrt(np.maximum(sq[:, None] + sq[None, :] - 2 * d @ d.T, 0.0))
    np.fill_diagonal(dist, np.inf)
    return dist


def top1_agreement(ref: np.ndarray, other: np.ndarray) -> float:
    """Share of rows whose nearest other row (leave-one-out, Euclidean) is the same under
    descriptors ``ref`` and ``other`` (both float [M, D], M >= 2)."""
    return float((other_distances(ref).argmin(1) == other_distances(other).argmin(1)).mean())
