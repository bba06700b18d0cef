# The two commands: `make demo` and `make test`. Each creates .venv if it is missing.
PY      ?= python3
VENV    := .venv
BIN     := $(VENV)/bin
STAMP   := $(VENV)/.installed
# torch==2.13.0 is the CPU wheel on this machine's disk; a bare `torch` would pull a CUDA build.
TORCH   ?= torch==2.13.0

.PHONY: venv demo test test-all format bench schemas clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q "$(TORCH)"
	$(BIN)/python -m pip install -q -e ".[dev]"
	touch $(STAMP)

demo: $(STAMP)
	OMP_NUM_THREADS=1 $(BIN)/lasagna demo -o out/demo

# Lint and format checks first (ruff, configured in pyproject.toml), then the suite on two workers (pytest-xdist:
# each worker builds its own tiny catalogue and Chromium; one torch thread each, so the two cores are used once).
# pytest's exit code 5 ("no tests collected") is a failure, not a pass.
test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	OMP_NUM_THREADS=1 $(BIN)/python -m pytest -n 2; rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "make test: pytest collected no tests"; exit 1; fi; exit $$rc

# Fix what ruff can fix by itself (imports, formatting); `make test` then checks the rest.
format: $(STAMP)
	$(BIN)/ruff check --fix .
	$(BIN)/ruff format .

# Everything, including slow runs and the real-application checks (Krita, GIMP) where installed.
test-all: $(STAMP)
	OMP_NUM_THREADS=1 $(BIN)/python -m pytest -m ""

bench: $(STAMP)
	$(BIN)/python benchmarks/compositing.py

schemas: $(STAMP)
	$(BIN)/lasagna schema --out schemas

clean:
	rm -rf $(VENV) out build dist *.egg-info .pytest_cache .hypothesis
