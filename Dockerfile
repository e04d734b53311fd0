# pnvlad localisation service: CPU-only, non-root, `pnvlad serve` as the entry point.
#
#   docker build -t pnvlad .
#   docker run --rm -p 127.0.0.1:8000:8000 --read-only \
#     -v "$PWD/map.index:/data/index:ro" -v "$PWD/runs/model:/data/model:ro" pnvlad
#
# The index bundle and the model checkpoint are mounted, not baked in (docs/SERVICE.md).
#
# Build arguments; the defaults are the official Python image and PyTorch's CPU wheel index,
# and a plain `docker build .` needs nothing else. scripts/image_test.sh overrides the first
# three to build with no container registry (a local Debian base, torch from a wheel folder).
#   BASE_IMAGE         base of every stage: a python3 (3.11 or newer) with venv
#   TORCH_INDEX_URL    index that torch comes from; empty: pip's configured index
#   TORCH_REQUIREMENT  torch requirement, or the path of a torch wheel file
#   VERSION, REVISION, SOURCE  OCI labels: the version (keep it = pnvlad_service.__version__),
#                      the commit and the repository URL

ARG BASE_IMAGE=python:3.11-slim

# The venv with torch and every dependency of pnvlad, but not pnvlad itself: the slow layers,
# rebuilt only when the base, torch or pyproject.toml's dependencies change.
FROM ${BASE_IMAGE} AS deps
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
ARG TORCH_REQUIREMENT="torch>=2.4,<2.14"
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_ROOT_USER_ACTION=ignore
RUN python3 -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH
# CPU wheels of torch (no CUDA libraries: about 200 MB to download instead of several GB).
# Dropped from it: the C++ test binaries and test data, the C++ headers (only for compiling
# extensions) and protoc - none is used at run time. torch_shm_manager stays.
# (DL3013: the requirement, with its version range or wheel file, is the build argument.)
# hadolint ignore=DL3013
RUN pip install ${TORCH_INDEX_URL:+--index-url "$TORCH_INDEX_URL"} "$TORCH_REQUIREMENT" \
    && torch="$(python -c 'import sysconfig; print(sysconfig.get_path("purelib"))')/torch" \
    && rm -rf "$torch/test" "$torch/include" "$torch/bin/upgrader_models" \
    && find "$torch/bin" -type f ! -name torch_shm_manager -delete
COPY pyproject.toml /tmp/pyproject.toml
RUN python -c "import tomllib; print('\n'.join(tomllib.load(open('/tmp/pyproject.toml', 'rb'))['project']['dependencies']))" > /tmp/requirements.txt \
    && pip install -r /tmp/requirements.txt \
    && rm /tmp/pyproject.toml /tmp/requirements.txt

# The venv as it ships, made smaller without changing what runs: torch's own libraries without
# their symbol tables (strip --strip-unneeded keeps what linking needs; only torch's: the
# auditwheel-patched libraries of numpy, scipy and faiss are left alone), no test suites of
# numpy, scipy, sympy and networkx, no pip. binutils stays in this stage.
FROM deps AS venv
# hadolint ignore=DL3008
RUN apt-get update && apt-get install -y --no-install-recommends binutils \
    && site="$(python -c 'import sysconfig; print(sysconfig.get_path("purelib"))')" \
    && strip --strip-unneeded "$site"/torch/lib/libtorch*.so "$site"/torch/lib/libc10.so \
        "$site"/torch/lib/libshm.so \
    && for pkg in numpy scipy sympy networkx; do \
        find "$site/$pkg" -type d -name tests -prune -exec rm -rf {} +; done \
    && pip uninstall -y -q pip

# pnvlad itself, into a prefix of its own so that the final stage adds it as a small layer.
FROM deps AS build
WORKDIR /src
COPY pyproject.toml README.md ./
COPY pnvlad_service ./pnvlad_service
COPY cli ./cli
RUN pip install --no-deps --no-compile --prefix /opt/pnvlad . \
    && PYTHONPATH="$(python -c 'import sysconfig; print(sysconfig.get_path("purelib", vars={"base": "/opt/pnvlad"}))')" pip check \
    && python -m compileall -q -s /opt/pnvlad -p /opt/venv /opt/pnvlad

FROM ${BASE_IMAGE}
RUN useradd --system --uid 10001 --user-group --no-create-home --home-dir /nonexistent pnvlad
COPY --from=venv /opt/venv /opt/venv
COPY --from=build /opt/pnvlad /opt/venv
ENV PATH=/opt/venv/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PNVLAD_HOST=0.0.0.0 \
    PNVLAD_PORT=8000 \
    PNVLAD_INDEX=/data/index \
    PNVLAD_CHECKPOINT=/data/model
# The final image must import what the server imports (the torch files dropped above included).
RUN pnvlad --version && python -c "import faiss, torch, pnvlad_service.server.app"
USER 10001:10001
WORKDIR /tmp
VOLUME ["/data/index", "/data/model"]
EXPOSE 8000
# Healthy = model and index loaded and answering (/readyz), with python's urllib: no curl.
HEALTHCHECK --interval=30s --timeout=5s --start-period=90s --retries=3 \
    CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:%s/readyz' % os.environ.get('PNVLAD_PORT', '8000'), timeout=4)"]
ENTRYPOINT ["pnvlad", "serve"]
CMD []
# Last, so that a new revision relabels the image without redoing any layer above.
ARG VERSION=0.1.0
ARG REVISION=""
ARG SOURCE=""
LABEL org.opencontainers.image.title="pnvlad" \
      org.opencontainers.image.description="LiDAR place recognition service: PointNetVLAD descriptors searched in a FAISS index over HTTP (CPU)" \
      org.opencontainers.image.version="${VERSION}" \
      org.opencontainers.image.revision="${REVISION}" \
      org.opencontainers.image.source="${SOURCE}" \
      org.opencontainers.image.licenses="MIT" \
      org.opencontainers.image.vendor="pnvlad team"
