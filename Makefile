# cystomap: the two set-up commands are `make run` and `make test` (see README.md).
SHELL := /bin/bash
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
CORES ?= 2
RECORDING_ARGS ?=
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
APT_PKGS :=

.PHONY: setup run test test-fast lint browser bench clean config-docs

$(STAMP): pyproject.toml constraints.txt
	@# open3d needs libusb-1.0-0; Debian's python3 needs python3-venv for `-m venv`.
	@ldconfig -p | grep -q 'libusb-1.0.so.0' || APT_NEED="libusb-1.0-0"; \
	 $(PYTHON) -c 'import ensurepip' 2>/dev/null || APT_NEED="$$APT_NEED python3-venv"; \
	 if [ -n "$$APT_NEED" ]; then \
	   echo "installing system packages:$$APT_NEED"; \
	   $(SUDO) apt-get update -qq && $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$APT_NEED; \
	 fi
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[dev]' -c constraints.txt
	@touch $@

setup: $(STAMP)

## run the whole workflow on the default study (the built-in phantom)
run: setup
	$(BIN)/snakemake --cores $(CORES)

## lint + the test suite (what CI runs)
test: setup lint browser
	$(BIN)/pytest -q

## the unit tier: no phantom render, no SfM, no Snakemake (tests marked slow are left out)
test-fast: setup
	$(BIN)/ruff check cystomap scripts tests
	$(BIN)/pytest -q -m "not slow"

lint: setup
	$(BIN)/ruff check cystomap scripts tests
	$(BIN)/snakemake --lint --cores 1

## Debian's chromium, for the study report's browser test (`make test` only, not `make run`)
browser:
	@command -v chromium >/dev/null 2>&1 || { \
	   echo "installing system packages: chromium"; \
	   $(SUDO) apt-get update -qq && $(SUDO) env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium; }

## full-size benchmarks; writes tables under results/bench/
## (RECORDING_ARGS, e.g. "--lengths 60,120 --scale 0.3333": the recording suite's options)
bench: setup
	$(BIN)/python -m cystomap.bench --out results/bench
	$(BIN)/python -m cystomap.bench.sfm --out results/bench
	$(BIN)/python -m cystomap.bench.recording --out results/bench $(RECORDING_ARGS)

clean:
	rm -rf results logs benchmarks .snakemake

## regenerate the schema's stage sections and the README's config table from the dataclasses
config-docs: setup
	$(BIN)/python -m cystomap.configschema --write
	$(BIN)/python -m cystomap.configdoc --write README.md
