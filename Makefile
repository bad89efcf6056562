# BreastBiomech: the two set-up commands and the benchmarks.
#   make demo   create .venv, install, run the main job on the built-in phantom (out/demo)
#   make test   create .venv if missing, install, run the whole test suite
#   make bench  print benchmark figures (see docs/benchmarks.md)

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/breastbiomech demo --out out/demo

test: $(STAMP)
	QT_QPA_PLATFORM=offscreen $(BIN)/python -m pytest

bench: $(STAMP)
	$(BIN)/breastbiomech bench phantom --json
	$(BIN)/breastbiomech bench segment --grid 256 256 80 --json
	$(BIN)/breastbiomech bench mesh --volume-cm3 1000 --edge-mm 3.0 --json
	$(BIN)/breastbiomech bench warp --json
	$(BIN)/breastbiomech bench solver --tets 20000 --relaxation --json

clean:
	rm -rf out .pytest_cache
