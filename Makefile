# Two entry points on a fresh machine: `make demo` and `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench fuzz venv clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

venv: $(STAMP)

demo: $(STAMP)
	$(BIN)/python examples/intel_lab.py --out demo

lint: $(STAMP)
	$(BIN)/ruff check octolgp tests tools examples
	$(BIN)/ruff format --check octolgp tests tools examples
	$(BIN)/mypy

test: lint
	$(BIN)/python -m pytest -q

# Long fuzzing of insert_scan, every loader and OnlineMap.open (2000 examples per test).
fuzz: $(STAMP)
	HYPOTHESIS_PROFILE=fuzz $(BIN)/python -m pytest -q tests/test_fuzz.py

bench: $(STAMP)
	$(BIN)/octolgp bench paper2d --out bench_out

clean:
	rm -rf $(VENV) demo bench_out .pytest_cache .mypy_cache .ruff_cache
