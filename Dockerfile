# NEMSim inference service, CPU-only image.
#   docker build -t nemsim .
#   docker run -p 8000:8000 -e NEMSIM_API_KEYS=<a key of >= 16 characters> nemsim
#       serves checkpoints/nemsim-small.pt; docs at http://localhost:8000/docs; clients send the header X-API-Key.
#       Without keys the server answers only clients inside the container (it warns at start-up).
#   docker run -p 8000:8000 -e NEMSIM_API_KEYS=... -v $PWD/ckpt:/ckpt -e NEMSIM_CHECKPOINT=/ckpt/model.pt nemsim
# A checkpoint that cannot load stops the container (exit 3); the HEALTHCHECK polls /ready. The image holds the
# library and the service (not the benchmark harness: `nemsim bench` is absent there).
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1 \
    OMP_NUM_THREADS=2 \
    NUMBA_CACHE_DIR=/tmp/numba-cache

WORKDIR /app

# torch first, from the CPU wheel index, so the package install below does not pull CUDA wheels
RUN pip install --index-url https://download.pytorch.org/whl/cpu torch==2.13.0

COPY pyproject.toml README.md ./
COPY nemsim ./nemsim
COPY service ./service
COPY rules ./rules
RUN pip install ".[service]"

# the shipped checkpoint: the service serves ./checkpoints/nemsim-small.pt (cwd = /app); resume state excluded
COPY checkpoints ./checkpoints

RUN useradd --create-home --uid 10001 nemsim && chown -R nemsim /app
USER nemsim

EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s --retries=3 \
    CMD python -c "import urllib.request, sys; sys.exit(0 if urllib.request.urlopen('http://127.0.0.1:8000/ready', timeout=4).status == 200 else 1)"

CMD ["nemsim", "serve", "--host", "0.0.0.0", "--port", "8000"]
