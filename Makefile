# mbfg — the two commands a fresh machine needs: `make report` and `make test`.
SHELL := /bin/bash
CARGO ?= cargo
MBFG := target/release/mbfg
SCENES := $(sort $(wildcard scenes/*.yaml))

.PHONY: all build report reference test bench fmt lint clean venv python

all: build

build:
	$(CARGO) build --release

# The validation pages (reports/index.md): scene summaries, RMSE over window sizes
# against the committed references, accuracy against time, hard cases, inverse dynamics.
report: build python
	@mkdir -p reports
	@set -e; for s in $(SCENES); do $(MBFG) check $$s; echo; done > reports/check.txt
	@echo "wrote reports/check.txt"
	$(CARGO) run --release --example inverse_report
	.venv/bin/python -m harness.report

# The committed ground truth (references/), regenerated from the scenes.
reference: python
	.venv/bin/python -m harness.reference

test: python
	$(CARGO) test --release
	$(CARGO) build --release
	@set -e; for s in $(SCENES); do $(MBFG) check $$s > /dev/null; done; echo "mbfg check: $(words $(SCENES)) scenes passed, 0 failed"
	.venv/bin/python -m pytest harness/tests -q

bench:
	$(CARGO) bench

fmt:
	$(CARGO) fmt --all

lint:
	$(CARGO) clippy --all-targets -- -D warnings

clean:
	$(CARGO) clean

# The Python harness (reference generators, reports) lives in .venv with pinned
# requirements; targets that need it depend on this one.
.venv/.installed: harness/requirements.txt
	python3 -m venv .venv
	.venv/bin/pip install --quiet --upgrade pip
	.venv/bin/pip install --quiet -r harness/requirements.txt
	touch $@

venv: .venv/.installed

# The mbfg Python module (PyO3), built in release mode into .venv.
python: .venv/.installed
	VIRTUAL_ENV=$(CURDIR)/.venv .venv/bin/maturin develop --release --quiet
