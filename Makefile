# Everything a fresh machine needs, from python3 alone. Each target creates .venv if missing.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# Every extra: the daemon's core plus the twin, the view, the emulator and the test tools
# (pyproject.toml). `make test CONSTRAINTS=constraints.txt`: the versions pinned there.
EXTRAS := twin,view,emulator,test
CONSTRAINTS ?=

.PHONY: demo test browser lint types format bench soak clean

$(STAMP): pyproject.toml $(CONSTRAINTS)
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet $(if $(CONSTRAINTS),-c $(CONSTRAINTS)) -e '.[$(EXTRAS)]'
	touch $(STAMP)

## The view's browser test needs Debian's chromium: installed when missing and we may
## (root, or sudo without a password); otherwise one line saying how, and make stops.
browser:
	@sh scripts/need-chromium

## The main job on the embedded default: emulated cell, zenoh peer on loopback, local MCAP.
demo: $(STAMP)
	$(BIN)/python -m daq.demo

## The test suite (what CI runs): lint, types, then pytest without the slow soak/accuracy sweeps:
## the tests that measure real time alone, the others on two workers (tests/conftest.py).
test: $(STAMP) browser
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy
	$(BIN)/python -m pytest -q -m "not slow and not realtime" -n 2 --dist loadfile
	$(BIN)/python -m pytest -q -m "not slow and realtime"

lint: $(STAMP)
	$(BIN)/ruff check .

## The type checker: strict on every package (pyproject.toml [tool.mypy]).
types: $(STAMP)
	$(BIN)/mypy

format: $(STAMP)
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

## Speed benchmarks (ratios against reference implementations measured in the same run).
bench: $(STAMP)
	$(BIN)/python -m benchmarks

## Slow soak and accuracy sweeps over many seeds.
soak: $(STAMP)
	$(BIN)/python -m pytest -q -m slow

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
