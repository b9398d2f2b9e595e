# mbfg — the two commands a fresh machine needs: `make report` and `make test`.
SHELL := /bin/bash
CARGO ?= cargo
MBFG := target/release/mbfg
SCENES := $(sort $(wildcard scenes/*.yaml))

.PHONY: all build install report reference test bench fmt lint clean venv python

all: build

build:
	$(CARGO) build --release

# The mbfg command on the PATH: copied to $(PREFIX)/bin (default ~/.local/bin).
PREFIX ?= $(HOME)/.local
install: build
	install -D -m 755 $(MBFG) $(PREFIX)/bin/mbfg
	@case ":$$PATH:" in *":$(PREFIX)/bin:"*) ;; *) echo "add $(PREFIX)/bin to PATH: export PATH=\"$(PREFIX)/bin:\$$PATH\"";; esac

# The validation pages (reports/index.md): scene summaries, RMSE over window sizes
# against the committed references, accuracy against time, hard cases, inverse dynamics.
# Their sweeps run on a local Dask cluster, or on the scheduler at SCHEDULER
# (e.g. `make report SCHEDULER=tcp://host:8786`; docs/sweeps.md).
report: build python
	@mkdir -p reports
	@set -e; for s in $(SCENES); do $(MBFG) check $$s; echo; done > reports/check.txt
	@echo "wrote reports/check.txt"
	$(CARGO) run --release --features testing --example inverse_report
	.venv/bin/python -m harness.report $(if $(SCHEDULER),--scheduler $(SCHEDULER))

# The committed ground truth (references/), regenerated from the scenes.
reference: python
	.venv/bin/python -m harness.reference $(if $(SCHEDULER),--scheduler $(SCHEDULER))

# The tests check the solvers against the oracles of the feature `testing`
# (mbfg::reference, mbfg::motions, mbfg::inverse::classical), which the library's
# own build leaves out. The command the harness tests run is the one `cargo test`
# built for the CLI's tests, target/release/mbfg (the feature adds only those
# oracles; building it again would compile mbfg a third time).
test: python
	$(CARGO) test --release --features testing
	@set -e; for s in $(SCENES); do $(MBFG) check $$s > /dev/null; done; echo "mbfg check: $(words $(SCENES)) scenes passed, 0 failed"
	.venv/bin/python -m pytest harness/tests -q

bench:
	$(CARGO) bench

fmt:
	$(CARGO) fmt --all

lint:
	$(CARGO) clippy --all-targets --features testing -- -D warnings

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

# The mbfg Python module (PyO3), built in release mode into .venv, and the same build
# as a wheel in target/wheels/ (from the same compilation: seconds), which the packaging
# test installs into a fresh venv.
python: .venv/.installed
	VIRTUAL_ENV=$(CURDIR)/.venv .venv/bin/maturin develop --release --quiet
	@rm -f target/wheels/mbfg-*.whl
	VIRTUAL_ENV=$(CURDIR)/.venv .venv/bin/maturin build --release --quiet --out target/wheels

# Fuzzing the parsers (docs/fuzzing.md) on the stable toolchain: libFuzzer comes with
# libfuzzer-sys, the coverage instrumentation from these flags. FUZZ_SECONDS is the
# budget per target; fuzz-ci is the short fixed run for CI, built with less
# optimization (profile fuzz-ci in fuzz/Cargo.toml) as its build dominates.
FUZZ_TARGETS := scene expr trajectory runs
FUZZ_SECONDS ?= 600
FUZZ_CI_SECONDS := 10
FUZZ_HOST = $(shell rustc -vV | sed -n 's/^host: //p')
FUZZ_FLAGS := --cfg fuzzing -Cpasses=sancov-module -Cllvm-args=-sanitizer-coverage-level=4 -Cllvm-args=-sanitizer-coverage-inline-8bit-counters -Cllvm-args=-sanitizer-coverage-pc-table -Cllvm-args=-sanitizer-coverage-trace-compares
FUZZ_MAX_LEN_scene := 16384
FUZZ_MAX_LEN_expr := 24576
FUZZ_MAX_LEN_trajectory := 65536
FUZZ_MAX_LEN_runs := 64
# An explicit --target keeps the flags off build scripts and proc macros.
FUZZ_BUILD = cd fuzz && RUSTFLAGS="$(FUZZ_FLAGS)" $(CARGO) build --profile $(1) --target $(FUZZ_HOST) --target-dir target
# One target for $(2) seconds, built with profile $(3): new inputs go to fuzz/target/work/$(1) (the committed
# seeds are only read), the log to fuzz/target/$(1).log, a crash to fuzz/target/artifacts/$(1)/.
FUZZ_ONE = mkdir -p fuzz/target/work/$(1) fuzz/target/artifacts/$(1); echo "fuzz $(1): $(2) s"; \
	if fuzz/target/$(FUZZ_HOST)/$(3)/$(1) fuzz/target/work/$(1) fuzz/corpus/$(1) -max_total_time=$(2) \
		-max_len=$(FUZZ_MAX_LEN_$(1)) -timeout=10 -rss_limit_mb=2048 -artifact_prefix=fuzz/target/artifacts/$(1)/ \
		-print_final_stats=1 > fuzz/target/$(1).log 2>&1; \
	then grep -E '^(Done|stat::number_of_executed_units)' fuzz/target/$(1).log; \
	else tail -n 40 fuzz/target/$(1).log; echo "fuzz $(1) failed: see docs/fuzzing.md"; exit 1; fi;
FUZZ_RUN = $(foreach t,$(FUZZ_TARGETS),$(call FUZZ_ONE,$(t),$(1),$(2)))

.PHONY: fuzz fuzz-ci
fuzz:
	$(call FUZZ_BUILD,release)
	@set -e; $(call FUZZ_RUN,$(FUZZ_SECONDS),release)

fuzz-ci:
	$(call FUZZ_BUILD,fuzz-ci)
	@set -e; $(call FUZZ_RUN,$(FUZZ_CI_SECONDS),fuzz-ci)
