"""The container image's recipe, without a container engine: what the Dockerfile promises a plain
`docker build .` (the official Python base, no torch in the served image and PyTorch's CPU
wheels in the tools one, OCI labels, a non-root user, a curl-free HEALTHCHECK, `pnvlad serve`),
and scripts/image_check.py, the HTTP judge of
scripts/image_test.sh, against a stub server: it passes a right answer and fails a wrong place,
a server that answers without the token, and one that is down.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest

from pnvlad_service import __version__

REPO = Path(__file__).resolve().parents[1]
DOCKERFILE = (REPO / "Dockerfile").read_text()
PYPROJECT = (REPO / "pyproject.toml").read_text()


def _instructions() -> list[tuple[str, str]]:
    """(KEYWORD, arguments) of every instruction, continuation lines joined, comments dropped."""
    text = re.sub(r"\\\n", " ", DOCKERFILE)
    out = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            keyword, _, rest = line.partition(" ")
            out.append((keyword.upper(), rest.strip()))
    return out


def _final_stage() -> list[tuple[str, str]]:
    ins = _instructions()
    last_from = max(i for i, (k, _) in enumerate(ins) if k == "FROM")
    return ins[last_from:]


def test_defaults_build_from_the_official_image_and_pytorch_cpu_wheels() -> None:
    args = dict(a.split("=", 1) for k, a in _instructions() if k == "ARG" and "=" in a)
    assert args["BASE_IMAGE"] == "python:3.11-slim"
    assert args["TORCH_INDEX_URL"] == "https://download.pytorch.org/whl/cpu"
    assert f"{args['TORCH_REQUIREMENT']}," in PYPROJECT  # the project's own torch range
    # Every stage starts from the base or from an earlier stage.
    stages: list[str] = []
    for k, a in _instructions():
        if k == "FROM":
            base, *alias = a.split(" AS ")
            assert base == "${BASE_IMAGE}" or base in stages, a
            stages += alias


def test_oci_labels() -> None:
    labels = " ".join(a for k, a in _final_stage() if k == "LABEL")
    found = dict(re.findall(r"org\.opencontainers\.image\.([a-z]+)=\"([^\"]*)\"", labels))
    assert {"title", "description", "version", "revision", "source", "licenses"} <= set(found)
    assert f'license = "{found["licenses"]}"' in PYPROJECT
    assert found["version"] == "${VERSION}"
    # A plain build is labelled with the package's version: the default must follow it.
    assert f"VERSION={__version__}" in [a for k, a in _final_stage() if k == "ARG"]


def test_runtime_stage_is_non_root_curl_free_and_serves() -> None:
    final = _final_stage()
    keys = [k for k, _ in final]
    user = [a for k, a in final if k == "USER"]
    assert user == ["10001:10001"]  # numeric: Kubernetes' runAsNonRoot can check it
    assert keys.index("USER") < keys.index("ENTRYPOINT")
    health = next(a for k, a in final if k == "HEALTHCHECK")
    assert "urllib.request" in health and "/readyz" in health
    assert not re.search(r"\b(curl|wget)\b", health)
    assert json.loads(next(a for k, a in final if k == "ENTRYPOINT")) == ["pnvlad", "serve"]
    volumes = json.loads(next(a for k, a in final if k == "VOLUME"))
    env = " ".join(a for k, a in final if k == "ENV")
    assert "PNVLAD_INDEX=/data/index" in env and "PNVLAD_CHECKPOINT=/data/model" in env
    assert {"/data/index", "/data/model"} <= set(volumes)
    # Nothing is built or installed in the final stage: it copies the venv and the package.
    runs = [a for k, a in final if k == "RUN"]
    assert not any(re.search(r"\b(pip|apt-get|gcc|cc|make)\b", r) for r in runs)
    copies = [a for k, a in final if k == "COPY"]
    assert copies and all(c.startswith("--from=") for c in copies)


def _stages() -> dict[str, list[tuple[str, str]]]:
    """Each stage's instructions by its name (the unnamed last one: "final")."""
    out: dict[str, list[tuple[str, str]]] = {}
    name = None
    for k, a in _instructions():
        if k == "FROM":
            name = a.split(" AS ")[1] if " AS " in a else "final"
            out[name] = [(k, a)]
        elif name is not None:
            out[name].append((k, a))
    return out


def test_the_served_image_holds_no_torch_and_the_tools_image_does() -> None:
    stages = _stages()

    def lineage(name: str) -> set[str]:
        """The stage and every stage it starts from or copies from."""
        seen, todo = set(), [name]
        while todo:
            s = todo.pop()
            if s in seen or s not in stages:
                continue
            seen.add(s)
            base = stages[s][0][1].split(" AS ")[0]
            todo += [base] + [a.split()[0].removeprefix("--from=") for k, a in stages[s]
                              if k == "COPY" and a.startswith("--from=")]  # fmt: skip
        return seen

    torch_stages = {n for n, ins in stages.items() if any("TORCH_REQUIREMENT" in a for k, a in ins
                                                          if k == "RUN")}  # fmt: skip
    assert torch_stages == {"tools"}
    assert "tools" not in lineage("final")
    final_runs = " ".join(a for k, a in stages["final"] if k == "RUN")
    assert "find_spec('torch')" in final_runs  # the build fails if torch ever gets in
    # The tools image installs torch before it copies pnvlad (its slow layer stays cached).
    tools = [(k, a) for k, a in stages["tools"]]
    torch_at = next(i for i, (k, a) in enumerate(tools) if "TORCH_REQUIREMENT" in a and k == "RUN")
    pnvlad_at = next(i for i, (k, a) in enumerate(tools) if a.startswith("--from=build"))
    assert torch_at < pnvlad_at


def test_every_package_is_installed() -> None:
    """The image (like any wheel) installs pnvlad with `pip install .`, not editable: a package
    missing from pyproject's explicit list is missing there, while the editable install of the
    test suite still finds it."""
    listed = set(re.findall(r'^\s*"(pnvlad_[a-z_.]+)",$', PYPROJECT, flags=re.MULTILINE))
    on_disk = {
        ".".join(p.parent.relative_to(REPO).parts).replace("cli", "pnvlad_cli", 1)
        for p in [*(REPO / "pnvlad_service").rglob("__init__.py"), REPO / "cli" / "__init__.py"]
    }
    assert on_disk - listed == set()


# --- scripts/image_check.py against a stub server ---------------------------------------------

DATASET, INDEXED, HELD = "area", "2026-01-01-00-00-00", "2026-02-01-00-00-00"
CENTRE = (5_734_700.0, 619_200.0)


def _tree(root: Path) -> Path:
    """Two runs along one street, a submap every 20 m (the held-out one 1 m further north)."""
    ds = root / DATASET
    ds.mkdir(parents=True)
    (ds / "test_regions.json").write_text(
        json.dumps({"centres": [list(CENTRE)], "half_size": 60.0, "all": False})
    )
    for r, run in enumerate((INDEXED, HELD)):
        (ds / run / "pointcloud_20m").mkdir(parents=True)
        rows = ["timestamp,northing,easting"]
        for k in range(7):
            ts = 1_700_000_000_000_000 * (r + 1) + k
            rows.append(f"{ts},{CENTRE[0] - 70 + 20 * k + r},{CENTRE[1] + 1.5 * r}")
            (ds / run / "pointcloud_20m" / f"{ts}.bin").write_bytes(b"\0" * 24 * 4096)
        (ds / run / "pointcloud_locations_20m.csv").write_text("\n".join(rows) + "\n")
    return root


class _Stub(BaseHTTPRequestHandler):
    token = "t0ken"
    needs_token = True
    offset_m = 0.0  # how far north of the truth the stub's top-1 lies

    def log_message(self, *args: object) -> None:
        pass

    def do_POST(self) -> None:
        self.rfile.read(int(self.headers["Content-Length"]))
        if self.needs_token and self.headers.get("Authorization") != f"Bearer {self.token}":
            return self._send(401, {"title": "Unauthorized"}, "application/problem+json")
        # The stub cannot embed: it answers the indexed submap nearest the checker's query
        # (the held-out one nearest the middle of the held-out queries: N - 9 m), moved by
        # offset_m.
        self._send(
            200,
            {
                "matches": [
                    {
                        "rank": 1,
                        "run": INDEXED,
                        "timestamp": 1_700_000_000_000_003,
                        "northing": CENTRE[0] - 10 + self.offset_m,
                        "easting": CENTRE[1],
                        "distance": 0.1,
                    }
                ],
                "timings_ms": {"embed": 1.0, "total": 2.0},
            },
            "application/json",
        )

    def _send(self, status: int, body: dict, ctype: str) -> None:
        raw = json.dumps(body).encode()
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(raw)))
        self.end_headers()
        self.wfile.write(raw)


@pytest.fixture()
def stub() -> Iterator[type[_Stub]]:
    handler = type("Stub", (_Stub,), {})
    server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    handler.url = f"http://127.0.0.1:{server.server_address[1]}"  # type: ignore[attr-defined]
    yield handler
    server.shutdown()
    server.server_close()


def _check(url: str, root: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [
            sys.executable,
            str(REPO / "scripts" / "image_check.py"),
            "--url",
            url,
            "--root",
            str(root),
            "--dataset",
            DATASET,
            "--held",
            HELD,
            "--token",
            _Stub.token,
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_image_check_passes_a_right_answer(stub: type[_Stub], tmp_path: Path) -> None:
    res = _check(stub.url, _tree(tmp_path))  # type: ignore[attr-defined]
    assert res.returncode == 0, res.stdout + res.stderr
    assert "401 application/problem+json  ok" in res.stdout
    assert "RIGHT (within 25 m, the nearest indexed submap)" in res.stdout
    assert "(held out of the index)" in res.stdout and f"/{HELD}/" in res.stdout


@pytest.mark.parametrize(
    ("change", "says"),
    [
        ({"offset_m": 40.0}, "WRONG (within 25 m"),
        ({"needs_token": False}, "without the token: 200"),
    ],
)
def test_image_check_fails(stub: type[_Stub], tmp_path: Path, change: dict, says: str) -> None:
    for name, value in change.items():
        setattr(stub, name, value)
    res = _check(stub.url, _tree(tmp_path))  # type: ignore[attr-defined]
    assert res.returncode == 1, res.stdout
    assert says in res.stdout


def test_image_check_fails_when_the_server_is_down(tmp_path: Path) -> None:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    res = _check(f"http://127.0.0.1:{port}", _tree(tmp_path))
    assert res.returncode != 0
