# Two commands do all set-up on a fresh machine: `make evaluate` and `make test`.
PYTHON ?= python3.11
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: evaluate train test lint benchmark venv clean

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

venv: $(STAMP)

## Benchmark the default descriptor and the ground-truth rankings on the built-in synthetic scene.
evaluate: $(STAMP)
	$(BIN)/python evaluate.py $(ARGS)

## Train a descriptor for localization on the built-in synthetic scene (configs/train.yaml).
train: $(STAMP)
	$(BIN)/python train.py $(ARGS)

## Run the test suite: its files shared by two processes (pytest-xdist; a file's tests stay in one,
## with its module fixtures), 12 minutes on 2 cores where one process takes 17.5.
test: $(STAMP)
	$(BIN)/python -m pytest -n 2 --dist loadfile $(ARGS)

## Check the code's format and lint (ruff, with pyproject.toml's settings); CI runs it before the tests.
lint: $(STAMP)
	$(BIN)/ruff format --check .
	$(BIN)/ruff check .

## Print speed figures (benchmarks/, listed in the README).
benchmark: $(STAMP)
	for script in benchmarks/bench_*.py; do $(BIN)/python $$script || exit 1; done

clean:
	rm -rf $(VENV) outputs multirun .cache
