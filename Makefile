# The README's entry points. Everything installs into .venv from nothing.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup demo test lint bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[dev]"
	$(BIN)/python -m costseg.compile_kernels
	touch $(STAMP)

demo: setup
	$(BIN)/python scripts/demo.py

lint: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

# pytest-xdist: one test process per core (most tests run on one thread); an idle process takes
# tests queued for the other (worksteal), so a few long tests near the end do not leave a core idle
test: lint
	$(BIN)/python -m pytest -q -n auto --dist worksteal

bench: setup
	$(BIN)/python scripts/bench_decision.py
	$(BIN)/python scripts/bench_pipeline.py
	$(BIN)/python scripts/bench.py
	$(BIN)/python scripts/bench_data.py
	$(BIN)/python scripts/bench_predict.py
	$(BIN)/python scripts/bench_protocols.py

clean:
	rm -rf $(VENV) runs eval .pytest_cache .ruff_cache .hypothesis
