"""Load test of `pnvlad serve` on loopback: N concurrent clients for T seconds.

Starts the server itself (so it can read the server's peak RSS, VmHWM in /proc/<pid>/status)
unless --url is given, then for each --clients value runs that many client threads, each
sending preprocessed 4096-point queries (submaps of the bundle's own map, as float32 binary or
JSON) back to back for --seconds or until --max-requests in all. Prints throughput, latency
p50/p95/p99, errors, the server's batch sizes and peak RSS, and compares with the encoder's
own batch-1 time and batch-32 throughput measured in this process (--baseline) before the
phases and again after them: the targets use the mean of the two, so a machine that slows down
or speeds up during the run (a shared VM does) weighs on both sides alike.

With a bundle that carries geometry, each client count runs twice, re-ranking off
(``verify=false``) and on (the top ``--rerank`` candidates registered to the query), the two
alternating in ``--rounds`` slices (off, on, off, on, ...) that are pooled per mode, so that
a machine whose speed drifts during the run weighs on both alike; the script prints what
re-ranking adds to the 1-client p50 and takes from the 8-client throughput (the #10
targets: +25 ms at most, -30 % at most), with the candidates registered a query (the cascade
stops at a sure one) and the share verified. The queries are then the map's
submaps turned by a random yaw and jittered (``--perturb``), so that verification does its
whole work (a yaw search and the registration) rather than match a cloud against itself; or,
with ``--query-run``, the submaps of a run the bundle left out, as a vehicle would send them.
``--server-env PNVLAD_VERIFY_CACHE=0`` starts the server without its cache of prepared
candidates (every candidate prepared afresh: the cold cost).

``--runtime torch onnx`` starts one server per runtime (``PNVLAD_RUNTIME``; the model needs
its ``model.onnx``, ``pnvlad model export``) and alternates the phases' slices between them as
it alternates re-ranking off and on, then prints each runtime's 1-client p50 and 8-client
throughput against torch's (the #38 target: ONNX Runtime no more than 5 % slower anywhere).

``--swap OTHER`` is another test: the clients (the largest ``--clients``) query for
``--seconds`` while the server's map is swapped between ``--index`` and ``OTHER`` every
``--swap-every`` seconds (``POST /admin/reload``), and once to a broken copy of ``OTHER`` (its
geometry truncated, or its index file cut), which must be refused (422) with the old map still
answering. Every answer must name one of the two bundles, and its matches must be submaps of
the bundle it names; it prints the errors, the answers per bundle, the p50/p99 outside and
during the swaps.

Loopback only; bounded in time and count.

    python benchmarks/load_test.py --index demo/map.index --clients 1 8 --seconds 20
    python benchmarks/load_test.py --index runs/demo/map.index \
        --query-run runs/demo/city/business/HELD_OUT_RUN --server-env PNVLAD_VERIFY_CACHE=0
    python benchmarks/load_test.py --index map.index --runtime torch onnx --clients 1 8
    python benchmarks/load_test.py --index map.index --swap map-plus-run.index --clients 8
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import shutil
import subprocess
import threading
import time
from pathlib import Path
from urllib.parse import urlparse

import numpy as np
from entry import run
from local_server import start_server

from pnvlad_service.client import LocalizeClient, ServerError
from pnvlad_service.server.metrics import STAGES


def vmhwm_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as fh:
        m = re.search(r"VmHWM:\s+(\d+) kB", fh.read())
    return int(m.group(1)) / 1024 if m else float("nan")


def children(pid: int) -> list[int]:
    """The pids of ``pid``'s child processes (verification, multiprocessing's resource tracker)."""
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):  # a thread that ended meanwhile
            out += [int(k) for k in (task / "children").read_text().split()]
    return out


def cpu_seconds(pid: int) -> float:
    """User + system CPU seconds of process ``pid`` so far (all its threads; /proc/<pid>/stat)."""
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def process_cpu(pid: int | None) -> dict[str, float]:
    """CPU seconds so far of the server (``pid``) and of its children together (the
    verification process), {} without a pid."""
    if not pid:
        return {}
    out = {"server": cpu_seconds(pid), "child": 0.0}
    for k in children(pid):
        with contextlib.suppress(OSError):  # a child that ended meanwhile
            out["child"] += cpu_seconds(k)
    return out


def load_queries(index: Path | None, count: int, seed: int = 0) -> list[np.ndarray]:
    """Submaps of the bundle's map (read from the indexed tree), else random clouds."""
    rng = np.random.default_rng(seed)
    if index is not None:
        from pnvlad_service.index.bundle import Metadata
        from pnvlad_service.index.manifest import Manifest

        manifest = Manifest.read(index)
        meta = Metadata.load(index / "metadata.npz")
        root = Path(manifest.indexed[0]["root"])
        picks = rng.choice(len(meta), min(count, len(meta)), replace=False)
        out = []
        for i in picks:
            p = root / str(meta.path[i])
            if p.is_file():
                out.append(np.fromfile(p, "<f8").reshape(-1, 3).astype(np.float32))
        if out:
            return out
    return [rng.uniform(-0.9, 0.9, (4096, 3)).astype(np.float32) for _ in range(count)]


def run_queries(run: Path, count: int) -> tuple[list[np.ndarray], list[float | None]]:
    """Up to ``count`` test-layout submaps of another run (``run``: a run folder of the tree
    that the bundle left out), evenly spaced along it, and each one's scale from the run's
    frame sidecar (None without one): queries as a vehicle that prepared its own submaps
    sends them, at the places of the map but not its own clouds."""
    from pnvlad_service.data.frames import frames_path, read_frames_csv
    from pnvlad_service.data.tree import LAYOUTS
    from pnvlad_service.io.submap import read_submap

    names = LAYOUTS["oxford"]
    folder = names.folder("test")
    files = sorted((Path(run) / folder).glob("*.bin"))
    if not files:
        raise SystemExit(f"{run}: no {folder}/*.bin submaps (give a run folder)")
    sidecar = frames_path(Path(run) / names.csv("test"))
    scales = {f.timestamp: f.scale for f in read_frames_csv(sidecar)} if sidecar.is_file() else {}
    picks = np.linspace(0, len(files) - 1, min(count, len(files))).round().astype(int)
    clouds = [read_submap(files[i]).astype(np.float32) for i in picks]
    return clouds, [scales.get(int(files[i].stem)) for i in picks]


def perturbed(clouds: list[np.ndarray], seed: int = 0) -> list[np.ndarray]:
    """Each cloud turned about z by a random yaw and jittered by 0.002 (about 2 cm), clipped
    to the submap bound."""
    rng = np.random.default_rng(seed)
    out = []
    for c in clouds:
        a = rng.uniform(0, 2 * np.pi)
        r = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        moved = c @ r.T.astype(np.float32) + rng.normal(0, 0.002, c.shape).astype(np.float32)
        out.append(np.clip(moved, -1.0, 1.0).astype(np.float32))
    return out


def has_geometry(index: Path | None) -> bool:
    if index is None:
        return False
    from pnvlad_service.index.manifest import Manifest

    return Manifest.read(index).geometry is not None


def encoder_baseline(
    checkpoint: Path, clouds: list[np.ndarray], repeats: int, runtime: str = "auto"
) -> dict:
    """Batch-1 median latency (ms) and batch-32 throughput (clouds/s) of the encoder alone."""
    from pnvlad_service.models.runtimes import load_encoder

    enc = load_encoder(checkpoint, runtime=runtime)
    x1 = clouds[0][None]
    for _ in range(3):
        enc.embed(x1)
    t1 = []
    for _ in range(repeats):
        t = time.perf_counter()
        enc.embed(x1)
        t1.append(time.perf_counter() - t)
    x32 = np.stack([clouds[i % len(clouds)] for i in range(32)])
    enc.embed(x32)
    t32 = []
    for _ in range(max(2, repeats // 4)):
        t = time.perf_counter()
        enc.embed(x32)
        t32.append(time.perf_counter() - t)
    close = getattr(enc, "close", None)
    if close is not None:
        close()
    return {"batch1_ms": 1000 * float(np.median(t1)), "batch32_cps": 32 / float(np.median(t32))}


def run_phase(
    url: str,
    clients: int,
    seconds: float,
    max_requests: int,
    bodies: list[tuple[bytes, str]],
    ctype: str,
) -> dict:
    """``bodies``: (body, path) pairs sent round-robin. The raw samples of one slice of a
    phase (:func:`summarise` turns slices into figures)."""
    lat: list[float] = []
    registered: list[int] = []
    verified: list[bool] = []
    # The server's own stage times (ms), and the rest of each request's time (HTTP, the
    # client): where a request's time goes.
    stages: dict[str, list[float]] = {k: [] for k in (*STAGES, "outside")}
    errors: list[str] = []
    lock = threading.Lock()
    stop = time.monotonic() + seconds
    sent = [0]

    def client(k: int) -> None:
        with LocalizeClient(url, timeout=120) as conn:  # one keep-alive connection per thread
            i = k
            while time.monotonic() < stop:
                with lock:
                    if sent[0] >= max_requests:
                        break
                    sent[0] += 1
                body, path = bodies[i % len(bodies)]
                i += clients
                t = time.perf_counter()
                try:
                    status, data = conn.send("POST", path, body, ctype)
                    dt = time.perf_counter() - t
                    with lock:
                        if status == 200:
                            lat.append(dt)
                            doc = json.loads(data)
                            timings = doc.get("timings_ms", {})
                            for name in STAGES:
                                stages[name].append(float(timings.get(name, np.nan)))
                            stages["outside"].append(1000 * dt - timings.get("total", np.nan))
                            if doc.get("verification"):
                                registered.append(int(doc["verification"]["registered"]))
                                verified.append(bool(doc["verified"]))
                        else:
                            errors.append(f"{status}: {data[:200]!r}")
                except ServerError as exc:
                    with lock:
                        errors.append(repr(exc))

    threads = [threading.Thread(target=client, args=(k,)) for k in range(clients)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return {
        "clients": clients,
        "lat": lat,
        "registered": registered,
        "verified": verified,
        "stages": stages,
        "errors": errors,
        "wall": time.perf_counter() - t0,
    }


def summarise(slices: list[dict]) -> dict:
    """The figures of one or more slices of a phase (same client count and mode), pooled:
    throughput is all their requests over all their seconds, percentiles over all their
    requests, the mean batch all their clouds over all their encoder passes (the ``batches``
    and ``clouds`` the caller counted on the server for each slice)."""
    lat = [x for sl in slices for x in sl["lat"]]
    registered = [x for sl in slices for x in sl["registered"]]
    verified = [x for sl in slices for x in sl["verified"]]
    errors = [x for sl in slices for x in sl["errors"]]
    stages = {k: [x for sl in slices for x in sl["stages"][k]] for k in slices[0]["stages"]}
    wall = sum(sl["wall"] for sl in slices)
    batches = sum(sl.get("batches", 0) for sl in slices)
    clouds = sum(sl.get("clouds", 0) for sl in slices)
    cpu = {k: sum(sl.get("cpu", {}).get(k, 0.0) for sl in slices) for k in ("server", "child")}
    measured = any(sl.get("cpu") for sl in slices)  # with the server's pid
    ms = np.array(lat) * 1000 if lat else np.array([np.nan])
    p50, p95, p99 = np.percentile(ms, [50, 95, 99])
    return {
        "clients": slices[0]["clients"],
        "requests": len(lat),
        "errors": len(errors),
        "first_errors": errors[:3],
        "seconds": round(wall, 2),
        "throughput": len(lat) / wall,
        "p50_ms": float(p50),
        "p95_ms": float(p95),
        "p99_ms": float(p99),
        "registered_mean": float(np.mean(registered)) if registered else 0.0,
        "verified_share": float(np.mean(verified)) if verified else 0.0,
        "mean_batch": clouds / batches if batches else 0.0,  # clouds an encoder pass
        # CPU time a request: the server's process and its verification child
        **{
            f"cpu_{k}_ms": 1000 * v / len(lat) if lat and measured else float("nan")
            for k, v in cpu.items()
        },
        **{f"{k}_p50_ms": float(np.nanmedian(v)) if v else float("nan") for k, v in stages.items()},
    }


def batch_sizes(url: str) -> dict[str, float]:
    with LocalizeClient(url, timeout=30) as conn:
        _, data = conn.send("GET", "/metrics")
    out = {}
    for line in data.decode().splitlines():
        if line.startswith("pnvlad_batch_size_count"):
            out["batches"] = float(line.split()[-1])
        if line.startswith("pnvlad_batch_size_sum"):
            out["clouds"] = float(line.split()[-1])
    return out


def main() -> int | None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--index", type=Path, help="Bundle: start a server on it (and read its map).")
    ap.add_argument("--checkpoint", type=Path, help="Model (default: the bundle's).")
    ap.add_argument("--url", help="Use a running server instead (no RSS unless --pid).")
    ap.add_argument("--pid", type=int, help="The running server's pid, for its peak RSS.")
    ap.add_argument("--clients", type=int, nargs="+", default=[1, 8])
    ap.add_argument(
        "--seconds", type=float, default=20.0, help="Per client count and re-ranking mode."
    )
    ap.add_argument("--max-requests", type=int, default=5000, help="Per phase.")
    ap.add_argument(
        "--rounds",
        type=int,
        default=3,
        help="With re-ranking off and on (or several runtimes): each phase's seconds cut into "
        "this many slices, the modes alternating slice by slice and each pooled (one --seconds "
        "block each: 1).",
    )
    ap.add_argument("--body", choices=["binary", "json"], default="binary")
    ap.add_argument("--queries", type=int, default=64, help="Distinct query clouds.")
    ap.add_argument("--baseline", action=argparse.BooleanOptionalAction, default=True)
    ap.add_argument("--repeats", type=int, default=20, help="Encoder baseline repetitions.")
    ap.add_argument("--json", type=Path, help="Also write the results here.")
    ap.add_argument(
        "--rerank",
        choices=["auto", "both", "off"],
        default="auto",
        help="Phases with re-ranking off and on (both; auto: when the bundle has geometry).",
    )
    ap.add_argument(
        "--runtime",
        nargs="+",
        choices=["torch", "onnx", "auto"],
        help="One server per runtime (PNVLAD_RUNTIME), their phases alternated slice by slice "
        "(default: one server, its own choice).",
    )
    ap.add_argument(
        "--perturb",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="Turn and jitter the queries (default: when re-ranking the map's own submaps).",
    )
    ap.add_argument(
        "--query-run",
        type=Path,
        help="Queries from this run folder of the tree (one the bundle left out) instead of "
        "the map's own submaps; not perturbed unless --perturb.",
    )
    ap.add_argument(
        "--server-env",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="Environment of the started server, e.g. PNVLAD_VERIFY_CACHE=0 (repeatable).",
    )
    ap.add_argument(
        "--swap",
        type=Path,
        help="The swap test: another bundle (same model) the map is swapped with while the "
        "largest --clients query for --seconds.",
    )
    ap.add_argument("--swap-every", type=float, default=2.0, help="Seconds between swaps.")
    args = ap.parse_args()
    if not args.url and not args.index:
        ap.error("give --index (start a server) or --url")
    if args.swap is not None:
        if args.index is None or args.url is not None:
            ap.error("--swap starts its own server: give --index, not --url")
        return swap_test(args)
    both = args.rerank == "both" or (args.rerank == "auto" and has_geometry(args.index))
    reranks = ["off", "on"] if both else [None]
    runtimes = args.runtime or [None]
    if len(runtimes) > 1 and args.url:
        ap.error("several --runtime values start their own servers: give --index, not --url")
    modes = [(rt, rr) for rt in runtimes for rr in reranks]

    scales: list[float | None] = []
    if args.query_run is not None:
        clouds, scales = run_queries(args.query_run, args.queries)
    else:
        clouds = load_queries(args.index, args.queries)
    scales = scales or [None] * len(clouds)
    if args.perturb or (args.perturb is None and both and args.query_run is None):
        clouds = perturbed(clouds)
    checkpoint = args.checkpoint
    if checkpoint is None and args.index is not None:
        from pnvlad_service.localization.query.localizer import checked_model

        checkpoint = Path(checked_model(args.index).checkpoint)  # the bundle's model
    result: dict = {}

    def baseline(when: str) -> None:
        if not args.baseline or checkpoint is None:
            return
        for rt in runtimes:
            enc = encoder_baseline(checkpoint, clouds, args.repeats, rt or "auto")
            result.setdefault("encoder_runs", {}).setdefault(rt or "-", []).append(enc)
            print(
                f"encoder alone ({when}{', ' + rt if rt else ''}): batch-1 "
                f"{enc['batch1_ms']:.1f} ms, batch-32 {enc['batch32_cps']:.1f} clouds/s",
                flush=True,
            )

    baseline("before")

    servers: dict[str | None, tuple[subprocess.Popen | None, str, int | None]] = {}
    try:
        for rt in runtimes:
            if args.url is not None:
                servers[rt] = (None, args.url, args.pid)
                continue
            env = dict(kv.split("=", 1) for kv in args.server_env)
            if rt is not None:
                env["PNVLAD_RUNTIME"] = rt
            proc, url = start_server(args.index, checkpoint=args.checkpoint, env=env)
            servers[rt] = (proc, url, proc.pid)
        for _, url, _ in servers.values():
            if urlparse(url).hostname not in ("127.0.0.1", "localhost", "::1"):
                raise SystemExit("loopback only: the load test refuses other hosts")
        for rt, (_, url, _) in servers.items():
            with LocalizeClient(url) as c:
                _, ready = c.send("GET", "/readyz")
            result.setdefault("runtimes", {})[rt or "-"] = json.loads(ready).get("runtime")
            print(f"server {url}: {json.loads(ready).get('runtime')}", flush=True)

        def request(mode: str | None) -> tuple[list[tuple[bytes, str]], str]:
            """The bodies (and their paths) of a phase: re-ranking off, on, or the server's
            default; each query's scale sent when known (the cloud's own, as its frame
            sidecar has it)."""
            flag = {None: {}, "off": {"verify": False}, "on": {"verify": True}}[mode]
            if args.body == "binary":
                q = "&verify=" + str(flag["verify"]).lower() if flag else ""
                return [
                    (
                        c.astype("<f4").tobytes(),
                        f"/localize?top_n=5{q}" + (f"&scale={sc!r}" if sc is not None else ""),
                    )
                    for c, sc in zip(clouds, scales, strict=True)
                ], "application/octet-stream"
            return [
                (
                    json.dumps(
                        {"points": c.tolist(), "top_n": 5, **flag}
                        | ({"scale": sc} if sc is not None else {})
                    ).encode(),
                    "/localize",
                )
                for c, sc in zip(clouds, scales, strict=True)
            ], "application/json"

        for rt, rr in modes:
            run_phase(servers[rt][1], 1, 2.0, 10, *request(rr))  # warm-up
        result["phases"] = []
        rounds = args.rounds if len(modes) > 1 else 1
        print(
            f"{'clients':>7} {'runtime':>7} {'rerank':>6} {'round':>5} {'requests':>8} "
            f"{'errors':>6} {'req/s':>7} {'p50 ms':>8} {'p95 ms':>8} {'p99 ms':>8} "
            f"{'mean batch':>10} {'registered':>10} {'verified':>8} {'embed p50':>9} "
            f"{'verify p50':>10} {'CPU ms/req':>10} {'of which child':>14}"
        )

        def row(ph: dict, label: str) -> None:
            print(
                f"{ph['clients']:>7} {ph['runtime']:>7} {ph['rerank']:>6} {label:>5} "
                f"{ph['requests']:>8} {ph['errors']:>6} {ph['throughput']:>7.2f} "
                f"{ph['p50_ms']:>8.1f} {ph['p95_ms']:>8.1f} {ph['p99_ms']:>8.1f} "
                f"{ph['mean_batch']:>10.2f} {ph['registered_mean']:>10.2f} "
                f"{100 * ph['verified_share']:>7.0f}% {ph['embed_p50_ms']:>9.1f} "
                f"{ph['verify_p50_ms']:>10.1f} "
                f"{ph['cpu_server_ms'] + ph['cpu_child_ms']:>10.1f} {ph['cpu_child_ms']:>14.1f}",
                flush=True,
            )

        for n in args.clients:
            # The modes (runtimes x re-ranking off / on) alternate in `rounds` slices each,
            # pooled: a machine that drifts during the phase weighs on all alike.
            slices: dict = {mode: [] for mode in modes}
            for r in range(rounds):
                for rt, rr in modes:
                    _, url, pid = servers[rt]
                    b0, c0 = batch_sizes(url), process_cpu(pid)
                    sl = run_phase(
                        url, n, args.seconds / rounds, args.max_requests // rounds, *request(rr)
                    )
                    b1, c1 = batch_sizes(url), process_cpu(pid)
                    sl["cpu"] = {k: c1[k] - c0[k] for k in c1}
                    sl["batches"] = b1.get("batches", 0) - b0.get("batches", 0)
                    sl["clouds"] = b1.get("clouds", 0) - b0.get("clouds", 0)
                    slices[(rt, rr)].append(sl)
                    if rounds > 1:
                        label = {"runtime": rt or "-", "rerank": rr or "-"}
                        row(summarise([sl]) | label, str(r + 1))
            for rt, rr in modes:
                ph = summarise(slices[(rt, rr)]) | {
                    "runtime": rt or "-",
                    "rerank": rr or "-",
                    "rounds": rounds,
                }
                result["phases"].append(ph)
                row(ph, "all")
                for e in ph["first_errors"]:
                    print(f"  error: {e}")
        names = (*STAGES, "outside")
        print("where a request's time goes, p50 ms (the server's stages; outside: HTTP, client)")
        print(f"{'clients':>7} {'runtime':>7} {'rerank':>6} " + " ".join(f"{n:>10}" for n in names))
        for ph in result["phases"]:
            print(
                f"{ph['clients']:>7} {ph['runtime']:>7} {ph['rerank']:>6} "
                + " ".join(f"{ph[n + '_p50_ms']:>10.1f}" for n in names)
            )
        for rt, (_, _, pid) in servers.items():
            if not pid:
                continue
            peak = vmhwm_mb(pid)
            kids = {k: vmhwm_mb(k) for k in children(pid)}
            result.setdefault("server_peak_rss_mb", {})[rt or "-"] = peak
            result.setdefault("child_peak_rss_mb", {})[rt or "-"] = kids
            print(
                f"server peak RSS (VmHWM{', ' + rt if rt else ''}): {peak:.0f} MB"
                + "".join(f", child process {k} {mb:.0f} MB" for k, mb in kids.items())
            )
    finally:
        for proc, _, _ in servers.values():
            if proc is not None:
                proc.terminate()
                proc.wait(20)
    baseline("after")  # with the servers stopped, as before the phases
    for rt, runs in result.get("encoder_runs", {}).items():
        enc = {key: float(np.mean([r[key] for r in runs])) for key in ("batch1_ms", "batch32_cps")}
        result.setdefault("encoder", {})[rt] = enc
        print(
            f"encoder alone (mean{', ' + rt if rt != '-' else ''}): batch-1 "
            f"{enc['batch1_ms']:.1f} ms, batch-32 {enc['batch32_cps']:.1f} clouds/s"
        )
    for rt in runtimes:
        phases = [p for p in result.get("phases", []) if p["runtime"] == (rt or "-")]
        if both:
            rerank_targets(phases, rt)
        enc = result.get("encoder", {}).get(rt or "-")
        for ph in phases if enc else []:
            if ph.get("rerank") == "on":
                continue  # the encoder targets are about the path without re-ranking
            tag = f" ({rt})" if rt else ""
            if ph["clients"] == 1:
                print(
                    f"target 1{tag}: p50 {ph['p50_ms']:.1f} ms vs 1.25 x batch-1 "
                    f"{1.25 * enc['batch1_ms']:.1f} ms -> "
                    f"{'OK' if ph['p50_ms'] <= 1.25 * enc['batch1_ms'] else 'MISSED'}"
                )
            if ph["clients"] == 8:
                print(
                    f"target 2{tag}: {ph['throughput']:.2f} req/s vs 0.8 x batch-32 "
                    f"{0.8 * enc['batch32_cps']:.2f} clouds/s -> "
                    f"{'OK' if ph['throughput'] >= 0.8 * enc['batch32_cps'] else 'MISSED'}"
                )
    if "torch" in runtimes and "onnx" in runtimes:
        runtime_targets(result.get("phases", []))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))


def runtime_targets(phases: list[dict]) -> None:
    """ONNX Runtime's 1-client p50 and 8-client throughput against torch's, each client count
    and re-ranking mode (#38: no more than 5 % slower anywhere)."""
    by = {(p["runtime"], p["clients"], p["rerank"]): p for p in phases}
    for (rt, n, rr), onnx in sorted(by.items(), key=lambda kv: (kv[0][1], kv[0][2])):
        torch_ph = by.get(("torch", n, rr))
        if rt != "onnx" or torch_ph is None:
            continue
        slower_p50 = onnx["p50_ms"] / torch_ph["p50_ms"] - 1
        slower_tput = 1 - onnx["throughput"] / torch_ph["throughput"]
        for what, slower in (("p50", slower_p50), ("throughput", slower_tput)):
            verdict = "OK" if slower <= 0.05 else "MISSED"
            word = "slower" if slower > 0 else "faster"
            print(
                f"onnx vs torch, {n} client(s), re-ranking {rr}: {what} "
                f"{100 * abs(slower):.1f} % {word} (target: at most 5 % slower) -> {verdict}"
            )


# --------------------------------------------------------------------------------------------
# The swap test
# --------------------------------------------------------------------------------------------


def broken_copy(bundle: Path, work: Path) -> Path:
    """A copy of ``bundle`` that must be refused: its geometry truncated by a row and a half,
    or (without geometry) its index file cut short."""
    from pnvlad_service.index.geometry import POINTS_FILE, ROW_BYTES

    out = work / "broken.index"
    shutil.copytree(bundle, out)
    points = out / POINTS_FILE
    if points.is_file():
        os.truncate(points, max(0, points.stat().st_size - ROW_BYTES - ROW_BYTES // 2))
    else:
        data = (out / "index.faiss").read_bytes()
        (out / "index.faiss").write_bytes(data[: len(data) // 2])
    return out


def swap_test(args: argparse.Namespace) -> int:
    """8 clients (the largest --clients) across swaps of two bundles and one refused one."""
    import secrets
    import tempfile

    from pnvlad_service.index.bundle import Metadata
    from pnvlad_service.localization.query.localizer import checked_model

    bundles = {"a": args.index.resolve(), "b": args.swap.resolve()}
    ids: dict[str, str] = {}
    members: dict[str, set[str]] = {}
    for name, path in bundles.items():
        checked_model(path, args.checkpoint)  # same model for both, or say so now
        members[name] = set(Metadata.load(path / "metadata.npz").submap_id.tolist())
    clouds, scales = (
        run_queries(args.query_run, args.queries)
        if args.query_run is not None
        else (load_queries(args.index, args.queries), [])
    )
    scales = scales or [None] * len(clouds)
    bodies = [
        (c.astype("<f4").tobytes(), "/localize?top_n=5" + (f"&scale={s!r}" if s else ""))
        for c, s in zip(clouds, scales, strict=True)
    ]
    key = secrets.token_urlsafe(16)
    env = dict(kv.split("=", 1) for kv in args.server_env) | {"PNVLAD_ADMIN_KEY": key}
    if args.runtime:
        env["PNVLAD_RUNTIME"] = args.runtime[0]
    work = Path(tempfile.mkdtemp(prefix="pnvlad-swap-"))
    broken = broken_copy(bundles["b"], work)
    proc, url = start_server(bundles["a"], checkpoint=args.checkpoint, env=env)
    clients = max(args.clients)
    answers: list[tuple[float, float, int, str, list[str]]] = []  # start, end, status, id, ids
    swaps: list[tuple[float, float, str, int, str]] = []  # start, end, to, status, detail
    lock = threading.Lock()
    stop = time.monotonic() + args.seconds
    try:
        with LocalizeClient(url) as c:
            ids["a"] = json.loads(c.send("GET", "/readyz")[1])["index"]["id"]
            print(f"server {url}: {json.loads(c.send('GET', '/readyz')[1])['runtime']}")

        def client(k: int) -> None:
            with LocalizeClient(url, timeout=120) as conn:
                i = k
                while time.monotonic() < stop:
                    body, path = bodies[i % len(bodies)]
                    i += clients
                    t = time.perf_counter()
                    try:
                        status, data = conn.send("POST", path, body, "application/octet-stream")
                    except ServerError:
                        status, data = 0, b"{}"
                    t1 = time.perf_counter()
                    doc = json.loads(data) if status == 200 else {}
                    names = [m["submap_id"] for m in doc.get("matches", [])]
                    with lock:
                        answers.append((t, t1, status, doc.get("index", {}).get("id", ""), names))

        def swapper() -> None:
            # a -> b -> a, then the broken copy (refused: a serves on), then b, a, b, ...
            schedule = ["b", "a", "broken"] + ["b", "a"] * 10_000
            n = 0
            with LocalizeClient(url, api_key=key, timeout=300) as admin:
                while time.monotonic() < stop - args.swap_every:
                    time.sleep(args.swap_every)
                    to = schedule[n]
                    path = broken if to == "broken" else bundles[to]
                    body = json.dumps({"index": str(path)}).encode()
                    t = time.perf_counter()
                    status, data = admin.send("POST", "/admin/reload", body, "application/json")
                    t1 = time.perf_counter()
                    doc = json.loads(data)
                    if status == 200 and to != "broken":
                        ids[to] = doc["current"]["index"]["id"]
                    detail = (
                        doc.get("detail", "") if status != 200 else doc["current"]["index"]["id"]
                    )
                    with lock:
                        swaps.append((t, t1, to, status, detail))
                    print(f"swap to {to}: {status} in {t1 - t:.2f} s ({detail})", flush=True)
                    n += 1

        threads = [threading.Thread(target=client, args=(k,)) for k in range(clients)]
        threads.append(threading.Thread(target=swapper))
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        proc.terminate()
        proc.wait(20)
        shutil.rmtree(work, ignore_errors=True)
    by_id = {v: k for k, v in ids.items()}
    errors = [a for a in answers if a[2] != 200]
    wrong = [a for a in answers if a[2] == 200 and (a[3] not in by_id
             or any(n not in members[by_id[a[3]]] for n in a[4]))]  # fmt: skip
    good = [s for s in swaps if s[2] != "broken"]
    refused = [s for s in swaps if s[2] == "broken"]

    def during(a: tuple) -> bool:
        return any(a[0] < s[1] + 0.5 and a[1] > s[0] for s in good)

    lat = {
        "all": [1000 * (a[1] - a[0]) for a in answers if a[2] == 200],
        "during swaps": [1000 * (a[1] - a[0]) for a in answers if a[2] == 200 and during(a)],
        "outside swaps": [1000 * (a[1] - a[0]) for a in answers if a[2] == 200 and not during(a)],
    }
    counts = {name: sum(1 for a in answers if a[3] == i) for name, i in ids.items()}
    print(
        f"{len(answers)} answers from {clients} clients in {args.seconds:.0f} s: "
        f"{len(errors)} errors, {len(wrong)} not labelled with exactly one bundle of theirs; "
        + ", ".join(f"{n} from bundle {k} ({ids[k]})" for k, n in counts.items())
    )
    for name, values in lat.items():
        if values:
            p50, p99 = np.percentile(values, [50, 99])
            print(f"  {name:>14}: {len(values):5d} answers, p50 {p50:.1f} ms, p99 {p99:.1f} ms")
    print(
        f"{len(good)} swaps ({sum(s[3] == 200 for s in good)} answered 200), load + swap "
        f"{np.mean([s[1] - s[0] for s in good]) if good else float('nan'):.2f} s on average"
    )
    for s in refused:
        after = [a for a in answers if a[0] > s[1] and a[2] == 200][:20]
        kept = {a[3] for a in after}
        print(
            f"the broken bundle: {s[3]} ({s[4]}); the next {len(after)} answers from "
            f"{sorted(by_id.get(k, k) for k in kept)}"
        )
    ok = (
        not errors
        and not wrong
        and all(s[3] == 200 for s in good)
        and all(400 <= s[3] < 500 for s in refused)
    )
    print("swap test:", "OK" if ok else "FAILED")
    if args.json:
        args.json.write_text(
            json.dumps(
                {"answers": len(answers), "errors": len(errors), "mislabelled": len(wrong),
                 "per_bundle": counts, "ids": ids, "swaps": swaps,
                 "latency_ms": {k: (np.percentile(v, [50, 99]).tolist() if v else None)
                                for k, v in lat.items()}},
                indent=2,
            )
        )  # fmt: skip
    return 0 if ok else 1


def rerank_targets(phases: list[dict], runtime: str | None = None) -> None:
    """What re-ranking adds to the 1-client p50 and takes from the 8-client throughput."""
    by = {(p["clients"], p["rerank"]): p for p in phases}
    tag = f" ({runtime})" if runtime else ""
    if (1, "off") in by and (1, "on") in by:
        add = by[(1, "on")]["p50_ms"] - by[(1, "off")]["p50_ms"]
        print(
            f"re-ranking{tag} adds {add:.1f} ms to the 1-client p50 (target <= 25) -> "
            f"{'OK' if add <= 25 else 'MISSED'}"
        )
    if (8, "off") in by and (8, "on") in by:
        drop = 1 - by[(8, "on")]["throughput"] / by[(8, "off")]["throughput"]
        print(
            f"re-ranking{tag} takes {100 * drop:.1f} % of the 8-client throughput (target <= 30) "
            f"-> {'OK' if drop <= 0.30 else 'MISSED'}"
        )


if __name__ == "__main__":
    run(main)
