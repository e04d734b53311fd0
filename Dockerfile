# pnvlad localisation service: CPU-only, non-root, no torch, `pnvlad serve` as the entry point.
#
#   docker build -t pnvlad .
#   docker run --rm -p 127.0.0.1:8000:8000 --read-only \
#     -v "$PWD/map.index:/data/index:ro" -v "$PWD/runs/model:/data/model:ro" pnvlad
#
# The index bundle and the model are mounted, not baked in (docs/SERVICE.md). The server embeds
# with ONNX Runtime on the model's model.onnx (`pnvlad model export`, where torch is): the image
# holds no torch. `docker build --target tools -t pnvlad-tools .` builds the image with torch and
# onnx instead (training, evaluation, the export; scripts/image_test.sh makes its demo data so).
#
# Build arguments; the defaults are the official Python image and PyTorch's CPU wheel index,
# and a plain `docker build .` needs nothing else. scripts/image_test.sh overrides the first
# three to build with no container registry (a local Debian base, torch from a wheel folder).
#   BASE_IMAGE         base of every stage: a python3 (3.11 or newer) with venv
#   TORCH_INDEX_URL    index that torch comes from (the tools image); empty: pip's configured one
#   TORCH_REQUIREMENT  torch requirement, or the path of a torch wheel file (the tools image)
#   VERSION, REVISION, SOURCE  OCI labels: the version (keep it = pnvlad_service.__version__),
#                      the commit and the repository URL

ARG BASE_IMAGE=python:3.11-slim

# The venv with every dependency of pnvlad (ONNX Runtime, FAISS, FastAPI, ...; torch is an
# extra), not pnvlad itself: rebuilt only when the base or pyproject.toml's dependencies change.
# No bytecode here: the final stage compiles what the server imports, and only that.
FROM ${BASE_IMAGE} AS deps
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1 PIP_ROOT_USER_ACTION=ignore \
    PYTHONDONTWRITEBYTECODE=1
RUN python3 -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH
COPY pyproject.toml /tmp/pyproject.toml
RUN python -c "import tomllib; print('\n'.join(tomllib.load(open('/tmp/pyproject.toml', 'rb'))['project']['dependencies']))" > /tmp/requirements.txt \
    && pip install --no-compile -r /tmp/requirements.txt \
    && rm /tmp/pyproject.toml /tmp/requirements.txt

# The venv as it ships, smaller without changing what the server runs (docs/SERVICE.md, "The
# image"; the image test checks it serves, verifies and runs the filter G):
# - ONNX Runtime's libonnxruntime.so (its C API for other programs: the Python module carries
#   its own copy and never loads it) and its tools for exporters and quantisation;
# - SciPy's subpackages the server does not import (it uses ndimage, which takes special and
#   _lib); the test suites of NumPy and SciPy; pip and setuptools;
# - symbol tables of the extension modules without an RPATH (uvloop's 13 MB one is 2 MB
#   without): those with one were patched by auditwheel, and stripping them breaks them.
# binutils stays in this stage.
FROM deps AS venv
# (SC2016: the single-quoted script is sh -c's, which expands it.)
# hadolint ignore=DL3008,SC2016
RUN apt-get update && apt-get install -y --no-install-recommends binutils \
    && site="$(python -c 'import sysconfig; print(sysconfig.get_path("purelib"))')" \
    && rm -rf "$site"/onnxruntime/capi/libonnxruntime.so.* "$site"/onnxruntime/transformers \
        "$site"/onnxruntime/tools "$site"/onnxruntime/quantization "$site"/onnxruntime/datasets \
        "$site"/onnxruntime/backend \
    && for sub in cluster datasets differentiate fft fftpack integrate interpolate io linalg \
        misc odr optimize signal sparse spatial stats; do rm -rf "$site/scipy/$sub"; done \
    && for pkg in numpy scipy; do \
        find "$site/$pkg" -type d -name tests -prune -exec rm -rf {} +; done \
    && find "$site" -name '*.so*' -type f -exec sh -c 'for so; do \
        readelf -d "$so" | grep -q -E "RPATH|RUNPATH" || strip --strip-unneeded "$so"; done' sh {} + \
    && pip uninstall -y -q setuptools pip \
    && rm -f "$site/distutils-precedence.pth"

# pnvlad itself, into a prefix of its own so that the final stage adds it as a small layer.
FROM deps AS build
WORKDIR /src
COPY pyproject.toml README.md ./
COPY pnvlad_service ./pnvlad_service
COPY cli ./cli
RUN pip install --no-deps --no-compile --prefix /opt/pnvlad . \
    && PYTHONPATH="$(python -c 'import sysconfig; print(sysconfig.get_path("purelib", vars={"base": "/opt/pnvlad"}))')" pip check \
    && python -m compileall -q -s /opt/pnvlad -p /opt/venv /opt/pnvlad

# pnvlad as the served image holds it: the pretrained models serving-only (model.json and
# model.onnx, checked against their catalogue, which is rewritten without the weights). The
# server embeds with ONNX Runtime and has no torch to read model.safetensors; the tools image
# takes the build stage's full models. (-P: not the sources in the working directory, /src.)
FROM build AS served
RUN PYTHONPATH="$(python -c 'import sysconfig; print(sysconfig.get_path("purelib", vars={"base": "/opt/pnvlad"}))')" \
    python -P -c "from pnvlad_service.models import pretrained; print(len(pretrained.make_serving_only()), 'weights files left out of', pretrained.PACKAGE_CATALOGUE.parent)"

# The tools image (`--target tools`): pnvlad with torch and onnx (the `torch` extra), for
# training, evaluation and `pnvlad model export` in a container. Not slimmed; `pnvlad` is its
# entry point. Bytecode for the whole venv but torch's internal test helpers, some of which are
# Python 3.12 syntax that compileall fails on under 3.11.
FROM deps AS tools
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
ARG TORCH_REQUIREMENT="torch>=2.4,<2.14"
# CPU wheels of torch (no CUDA libraries: about 200 MB to download instead of several GB).
# (DL3013: the requirement, with its version range or wheel file, is the build argument.)
# hadolint ignore=DL3013
RUN pip install ${TORCH_INDEX_URL:+--index-url "$TORCH_INDEX_URL"} "$TORCH_REQUIREMENT"
COPY pyproject.toml /tmp/pyproject.toml
RUN python -c "import tomllib; print('\n'.join(r for r in tomllib.load(open('/tmp/pyproject.toml', 'rb'))['project']['optional-dependencies']['torch'] if not r.startswith('torch')))" > /tmp/requirements.txt \
    && pip install -r /tmp/requirements.txt \
    && rm /tmp/pyproject.toml /tmp/requirements.txt
COPY --from=build /opt/pnvlad /opt/venv
RUN useradd --system --uid 10001 --user-group --no-create-home --home-dir /nonexistent pnvlad \
    && python -m compileall -q -x '/torch/testing/_internal/' /opt/venv/lib \
    && python -c "import torch, onnx, pnvlad_service.models.onnx_export"
ENV PYTHONUNBUFFERED=1
USER 10001:10001
ENTRYPOINT ["pnvlad"]

FROM ${BASE_IMAGE}
RUN useradd --system --uid 10001 --user-group --no-create-home --home-dir /nonexistent pnvlad
COPY --from=venv /opt/venv /opt/venv
COPY --from=served /opt/pnvlad /opt/venv
ENV PATH=/opt/venv/bin:$PATH
# Bytecode for what the server imports (compiling the whole venv would add 30 MB), and the check
# that the final image imports what the server imports, without torch.
RUN python -c "import faiss, onnxruntime, scipy.ndimage, small_gicp, uvicorn.loops.uvloop, uvicorn.protocols.http.httptools_impl, uvicorn.lifespan.on, pnvlad_cli.main, pnvlad_cli.serve, pnvlad_service.server.app, pnvlad_service.localization.verify.registration, pnvlad_service.localization.verify.verify_process, pnvlad_service.localization.query.localizer, pnvlad_service.localization.verify.scale, pnvlad_service.preprocess.filter_g, pnvlad_service.models.onnx_encoder" \
    && pnvlad --version \
    && pnvlad model list > /dev/null \
    && python -c "import importlib.util, sys; sys.exit('torch in the image' if importlib.util.find_spec('torch') else 0)"
ENV PYTHONUNBUFFERED=1 \
    PYTHONDONTWRITEBYTECODE=1 \
    PNVLAD_HOST=0.0.0.0 \
    PNVLAD_PORT=8000 \
    PNVLAD_INDEX=/data/index \
    PNVLAD_CHECKPOINT=/data/model
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
      org.opencontainers.image.description="LiDAR place recognition service: PointNetVLAD descriptors searched in a FAISS index over HTTP (CPU, ONNX Runtime)" \
      org.opencontainers.image.version="${VERSION}" \
      org.opencontainers.image.revision="${REVISION}" \
      org.opencontainers.image.source="${SOURCE}" \
      org.opencontainers.image.licenses="MIT" \
      org.opencontainers.image.vendor="pnvlad team"
