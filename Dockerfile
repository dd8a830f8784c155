# NEMSim inference service image, with torch's CPU build (the rule of `make serve`) unless TORCH=cuda.
#   docker build -t nemsim .                              # or: make container
#   docker build --build-arg TORCH=cuda -t nemsim-cuda .  # or: make container TORCH=cuda; PyPI's CUDA build,
#       for `docker run --gpus all ... nemsim-cuda nemsim serve --host 0.0.0.0 --device cuda`
#   docker run -p 8000:8000 -e NEMSIM_API_KEYS=<a key of >= 16 characters> nemsim
#       serves checkpoints/nemsim-small.pt; docs at http://localhost:8000/docs; clients send the header X-API-Key.
#       Without keys the server answers only clients inside the container (it warns at start-up).
#   docker run -p 8000:8000 -e NEMSIM_API_KEYS=... -v $PWD/ckpt:/ckpt -e NEMSIM_CHECKPOINT=/ckpt/model.pt nemsim
# A checkpoint that cannot load stops the container (exit 3); the HEALTHCHECK polls /ready. The image holds the
# library and the service (not the benchmark harness: `nemsim bench` is absent there).
#
# Without a container registry or the PyTorch wheel index (PyPI and a Debian mirror reachable):
#   sudo docker/build-base.sh                                   # Debian bookworm base from debootstrap
#   pip download --no-deps -d docker/wheels torch==2.13.0+cpu   # any index or wheel folder holding the CPU wheel
#   docker build --build-arg BASE_IMAGE=nemsim-base:bookworm -t nemsim .
# A torch wheel in docker/wheels/ is installed instead of the index's; both bases need only `python3 -m venv`.
# Two stages: the packages go into a virtual environment (/opt/nemsim) built in the first stage, and only that
# environment reaches the image (no build tools, wheels or pip caches in its layers).
ARG BASE_IMAGE=python:3.11-slim

FROM ${BASE_IMAGE} AS build
ARG TORCH=cpu
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
ENV PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    PATH=/opt/nemsim/bin:$PATH
RUN python3 -m venv /opt/nemsim

# torch first, as a CPU wheel (TORCH=cuda: PyPI's build), so the package install below keeps it
COPY docker/wheels/ /wheels/
RUN set -e; \
    wheel=$(ls /wheels/torch-2.13.0+cpu-*.whl 2>/dev/null | head -n 1); \
    case "$TORCH" in \
      cuda) pip install torch==2.13.0 ;; \
      cpu) if [ -n "$wheel" ]; then pip install "$wheel"; \
           elif ! pip install --index-url "$TORCH_INDEX_URL" torch==2.13.0; then \
             echo "no CPU torch: $TORCH_INDEX_URL unreachable and no wheel in docker/wheels/ (above)" >&2; exit 1; \
           fi ;; \
      *) echo "TORCH=$TORCH: expected cpu (the default) or cuda" >&2; exit 2 ;; \
    esac

WORKDIR /src
COPY pyproject.toml README.md ./
COPY nemsim ./nemsim
COPY service ./service
COPY rules ./rules
RUN pip install ".[service]" \
    && python -c "import torch, service.main; assert (torch.version.cuda is not None) == ('$TORCH' == 'cuda')"

FROM ${BASE_IMAGE}
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    OMP_NUM_THREADS=2 \
    NUMBA_CACHE_DIR=/tmp/numba-cache \
    PATH=/opt/nemsim/bin:$PATH
COPY --from=build /opt/nemsim /opt/nemsim

# the shipped checkpoint: the service serves ./checkpoints/nemsim-small.pt (cwd = /app); resume state excluded
WORKDIR /app
COPY checkpoints ./checkpoints

RUN useradd --create-home --uid 10001 nemsim && chown -R nemsim /app
USER nemsim

EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s --retries=3 \
    CMD python -c "import urllib.request, sys; sys.exit(0 if urllib.request.urlopen('http://127.0.0.1:8000/ready', timeout=4).status == 200 else 1)"

CMD ["nemsim", "serve", "--host", "0.0.0.0", "--port", "8000"]
