# Two commands do all set-up on a fresh machine: `make evaluate` and `make test`.
PYTHON ?= python3.11
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# The exact versions `make` installs, CI tests and the GPU bundle downloads (`make lock` writes it).
LOCK := constraints.txt
# `make test-newest`: its own environment, and the packages it holds at the lock's versions
# (torch's newest builds on PyPI are CUDA builds of about 4 GB with their nvidia-* packages).
NEWEST ?= .venv-newest
NEWEST_HELD ?= torch torchvision
GPU_BUNDLE ?= ../shared/tools/gpu/bundle.sh
empty :=
space := $(empty) $(empty)

.PHONY: evaluate train test test-newest lint lock benchmark gpu-bundle venv clean

# The lock installed exactly (pip-sync removes what it does not list), then the project itself.
# pip-sync shows each package as it installs (about 2-3 minutes the first time).
$(STAMP): pyproject.toml setup.py $(LOCK)
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet -c $(LOCK) pip pip-tools
	@echo "Installing the packages of $(LOCK) into $(VENV) (about 2-3 minutes the first time):"
	$(BIN)/pip-sync $(LOCK)
	$(BIN)/python -m pip install --quiet --no-deps -e .
	touch $(STAMP)

venv: $(STAMP)

## Benchmark the default descriptor and the ground-truth rankings on the built-in synthetic scene.
evaluate: $(STAMP)
	$(BIN)/python evaluate.py $(ARGS)

## Train a descriptor for localization on the built-in synthetic scene (configs/train.yaml).
train: $(STAMP)
	$(BIN)/python train.py $(ARGS)

## Run the test suite: its files shared by two processes (pytest-xdist; a file's tests stay in one,
## with its module fixtures; the files with slow tests first, tests/conftest.py), 15 minutes on 2 cores.
test: $(STAMP)
	$(BIN)/python -m pytest -n 2 --dist loadfile --no-loadscope-reorder $(ARGS)

## The smoke subset (tests marked `smoke`) on the newest releases pyproject.toml's ranges allow, in
## $(NEWEST) (resolved again on every run), NEWEST_HELD at the lock's versions; CI runs it after `make test`.
test-newest:
	test -x $(NEWEST)/bin/python || $(PYTHON) -m venv $(NEWEST)
	grep -iE '^($(subst $(space),|,$(strip $(NEWEST_HELD))))==' $(LOCK) > $(NEWEST)/held.txt || true
	$(NEWEST)/bin/python -m pip install --quiet --upgrade pip
	$(NEWEST)/bin/python -m pip install --quiet --upgrade --upgrade-strategy eager -c $(NEWEST)/held.txt -e '.[dev]'
	$(NEWEST)/bin/python -m pip list --format=freeze --exclude-editable > $(NEWEST)/tested.txt
	$(NEWEST)/bin/python -m pip check
	$(NEWEST)/bin/python -m pytest -m smoke -n 2 --dist loadfile --no-loadscope-reorder -p no:cacheprovider $(ARGS)

## Check the code's format and lint (ruff, with pyproject.toml's settings) and that every
## third-party import is a declared dependency (deptry); CI runs it before the tests.
lint: $(STAMP)
	$(BIN)/ruff format --check .
	$(BIN)/ruff check .
	$(BIN)/deptry .

## Write the lock (constraints.txt) from pyproject.toml's ranges, keeping the versions it has where
## they still fit; `make lock ARGS=--upgrade` moves every package to its newest allowed release.
lock: $(STAMP)
	$(BIN)/pip-compile --quiet --extra dev --strip-extras --allow-unsafe --no-emit-index-url \
		--no-emit-find-links --output-file $(LOCK) $(ARGS) pyproject.toml

## The packages a GPU machine without a package index lacks (.gpu/, the shared bundle script),
## at the lock's versions.
gpu-bundle:
	PIP_CONSTRAINT=$(CURDIR)/$(LOCK) bash $(GPU_BUNDLE)

## Print speed figures (benchmarks/, listed in the README).
benchmark: $(STAMP)
	for script in benchmarks/bench_*.py; do $(BIN)/python $$script || exit 1; done

clean:
	rm -rf $(VENV) $(NEWEST) outputs multirun .cache
