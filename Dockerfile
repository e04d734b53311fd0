# pnvlad localisation service: CPU-only, non-root, `pnvlad serve` as the entry point.
#
#   docker build -t pnvlad .
#   docker run --rm -p 127.0.0.1:8000:8000 \
#     -v "$PWD/map.index:/data/index:ro" -v "$PWD/runs/model:/data/model:ro" pnvlad
#
# The index bundle and the model checkpoint are mounted, not baked in (docs/SERVICE.md).

ARG PYTHON=3.11

FROM python:${PYTHON}-slim AS build
ENV PIP_NO_CACHE_DIR=1 PIP_DISABLE_PIP_VERSION_CHECK=1
RUN python -m venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH
# CPU wheels of torch (no CUDA libraries: about 200 MB instead of several GB), installed first
# so that installing pnvlad finds its torch requirement already met.
RUN pip install --index-url https://download.pytorch.org/whl/cpu "torch>=2.4,<2.14"
WORKDIR /src
COPY pyproject.toml README.md ./
COPY pnvlad_service ./pnvlad_service
COPY cli ./cli
RUN pip install . && pnvlad --version

FROM python:${PYTHON}-slim
RUN useradd --system --uid 10001 --user-group --no-create-home --home-dir /nonexistent pnvlad
COPY --from=build /opt/venv /opt/venv
ENV PATH=/opt/venv/bin:$PATH \
    PYTHONUNBUFFERED=1 \
    PNVLAD_HOST=0.0.0.0 \
    PNVLAD_PORT=8000 \
    PNVLAD_INDEX=/data/index \
    PNVLAD_CHECKPOINT=/data/model
USER 10001:10001
WORKDIR /tmp
VOLUME ["/data"]
EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=90s --retries=3 \
    CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:%s/healthz' % os.environ.get('PNVLAD_PORT', '8000'), timeout=4)"]
ENTRYPOINT ["pnvlad", "serve"]
CMD []
