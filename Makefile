# BreastBiomech: the two set-up commands and the benchmarks.
#   make demo   create .venv, install, run the whole pipeline on the built-in phantom: compressed
#               scan (plate friction hidden in its truth), segmentation, mesh, fit, the diagnosis
#               that names the missing friction, out/demo/report.md (about 8 min on 2 CPU cores)
#   make test   create .venv if missing, install, run the whole test suite
#   make bench  print benchmark figures (see docs/benchmarks.md)
#   make table1-cases  the five compressed phantom cases of the seed's Table 1 (out/table1/case<N>;
#               2 mm truth meshes; DEVICE=cuda on a GPU: under a minute per case
#               on an H100; far slower on a CPU)

PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test bench table1-cases clean

DEVICE ?=

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/breastbiomech demo --out out/demo

test: $(STAMP)
	QT_QPA_PLATFORM=offscreen $(BIN)/python -m pytest -n 2 --dist loadfile

bench: $(STAMP)
	$(BIN)/breastbiomech bench phantom --json
	$(BIN)/breastbiomech bench segment --grid 256 256 80 --json
	$(BIN)/breastbiomech bench mesh --volume-cm3 1000 --edge-mm 3.0 --json
	$(BIN)/breastbiomech bench warp --json
	$(BIN)/breastbiomech bench solver --tets 20000 --relaxation --json

table1-cases: $(STAMP)
	for n in 1 2 3 4 5; do \
	  $(BIN)/breastbiomech phantom --case $$n --compressed $(if $(DEVICE),--device $(DEVICE)) --out out/table1/case$$n || exit 1; \
	done

clean:
	rm -rf out .pytest_cache
