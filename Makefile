# Two entry points: `make serve` (main job) and `make test` (what CI runs).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin

$(BIN)/nemsim: pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e '.[service,test]'
	touch $(BIN)/nemsim

venv: $(BIN)/nemsim

serve: venv
	$(BIN)/nemsim serve

test: venv
	$(BIN)/python -m pytest -x -q

.PHONY: venv serve test
