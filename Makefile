# Two entry points: `make serve` (main job) and `make test` (what CI runs).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin

# torch is installed first, so the package install keeps it: the CPU build from the PyTorch CPU index by
# default (PyPI's torch is the CUDA build on Linux, with some 20 NVIDIA packages); where that index cannot
# serve it, the default index's build, after a one-line message (one retry: an index that is not reachable
# costs seconds, not minutes of pip's default retries for every dependency). TORCH=cuda (`make serve
# TORCH=cuda`): the default index's build, for an NVIDIA GPU. The container takes the same switch.
TORCH ?= cpu
TORCH_PIN := torch==2.13.0
TORCH_CPU_INDEX ?= https://download.pytorch.org/whl/cpu
ifeq ($(TORCH),cpu)
TORCH_INSTALL = $(BIN)/pip install -q --retries 1 --index-url $(TORCH_CPU_INDEX) $(TORCH_PIN) \
	|| { echo "make: the CPU index $(TORCH_CPU_INDEX) could not serve $(TORCH_PIN): installing the default index's torch (CUDA on Linux)" >&2; \
	     $(BIN)/pip install -q $(TORCH_PIN); }
else ifeq ($(TORCH),cuda)
TORCH_INSTALL = $(BIN)/pip install -q $(TORCH_PIN)
else
$(error TORCH=$(TORCH): expected cpu (the default) or cuda)
endif

$(BIN)/nemsim: pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(TORCH_INSTALL)
	$(BIN)/pip install -q -e '.[service,test]'
	touch $(BIN)/nemsim

venv: $(BIN)/nemsim

serve: venv
	$(BIN)/nemsim serve

test: venv
	$(BIN)/python -m pytest -x -q

.PHONY: venv serve test benchmarks

# The service image (Dockerfile); without a container registry, first `sudo docker/build-base.sh` and a CPU torch
# wheel in docker/wheels/ (the Dockerfile's header), then: make container BASE_IMAGE=nemsim-base:bookworm
IMAGE ?= nemsim
BASE_IMAGE ?= python:3.11-slim
container:
	docker build --build-arg BASE_IMAGE=$(BASE_IMAGE) --build-arg TORCH=$(TORCH) \
	    --build-arg TORCH_INDEX_URL=$(TORCH_CPU_INDEX) -t $(IMAGE) .

.PHONY: container

# Benchmarks of the served model (benchmarks/README.md lists every result and its command): the data of the
# model card's recipe first (resumable; about 20 core-minutes per 500 `small` cases), then each benchmark, then
# every result stamped with the checkpoint's id. Long: hours of CPU; run it in the background.
CKPT ?= checkpoints/nemsim-small.pt
DATA ?= data
CACHE ?= runs/truth-cache
SMALL := benchmarks/small

$(DATA)/small.h5: | venv
	$(BIN)/nemsim design --n 500 --seed 42 --out $(DATA)/design.csv
	$(BIN)/nemsim generate --scene small --n 500 --seed 0 --out $@ --workers 2 --state-dtype float16
	$(BIN)/nemsim splits --design $(DATA)/design.csv --out $(DATA)/splits

benchmarks: venv $(DATA)/small.h5
	$(BIN)/nemsim bench speed-error --data $(DATA)/small.h5 --splits $(DATA)/splits --setting control-id \
	    --checkpoints $(CKPT) --runtimes torch-f32,openvino-bf16 --sim-domains full,quarter --cases 5 --out $(SMALL)
	$(BIN)/nemsim bench physics --checkpoint $(CKPT) --cache-dir $(CACHE) --out $(SMALL)/physics
	$(BIN)/nemsim bench extrapolation --checkpoint $(CKPT) --cache-dir $(CACHE) --out $(SMALL)/extrapolation
	$(BIN)/nemsim stress --checkpoint $(CKPT) --max-corners 32 --cache-dir $(CACHE) --json $(SMALL)/stress.json
	NEMSIM_ALLOCATOR=default $(BIN)/nemsim bench service --checkpoint $(CKPT) -n 30 \
	    --json $(SMALL)/service_latency.json
	OMP_NUM_THREADS=1 $(BIN)/nemsim bench service --probes --checkpoint $(CKPT) --json $(SMALL)/service_probes.json \
	    --md $(SMALL)/service_probes.md
	$(BIN)/nemsim counterfactual --checkpoint $(CKPT) --data $(DATA)/small.h5 --setting control-id \
	    --splits $(DATA)/splits --out $(SMALL)/counterfactual
	$(BIN)/nemsim bench inverse --checkpoint $(CKPT) --refine both --out $(SMALL)/inverse
	$(BIN)/python -m bench.stamp $(CKPT) $(SMALL)/speed_error.json $(SMALL)/speed_error.md \
	    $(SMALL)/physics/physics.json $(SMALL)/physics/physics.md $(SMALL)/extrapolation/extrapolation.json \
	    $(SMALL)/extrapolation/extrapolation.md $(SMALL)/stress.json $(SMALL)/service_latency.json \
	    $(SMALL)/counterfactual/counterfactual.json $(SMALL)/inverse/inverse.json $(SMALL)/inverse/inverse.md
