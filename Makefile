# The two commands a new machine needs: `make demo` and `make test`. Both install what is missing.
SHELL := /bin/bash
export ARUCOTAG_BUILD ?= $(CURDIR)/build

.PHONY: deps build test sanitize fuzz demo bench soak workspace-test clean

deps:
	bash scripts/install_deps.sh

build: deps
	bash scripts/build.sh

test: build
	bash scripts/run_tests.sh

# The whole suite again, built with ASan and UBSan into $(ARUCOTAG_BUILD)-sanitize; any sanitizer
# report is a failed test (scripts/sanitize.sh).
sanitize: deps
	bash scripts/sanitize.sh

# libFuzzer harnesses (test/fuzz), built with clang, ASan and UBSan into $(ARUCOTAG_BUILD)-fuzz,
# FUZZ_SECONDS (600) each; fails on any crash, sanitizer report, input over 1 s or 512 MB.
fuzz: deps
	bash scripts/fuzz.sh

demo: build
	bash scripts/demo.sh

# Detection benchmark: prints the table and writes $(ARUCOTAG_BUILD)/bench/results.{json,md}.
bench: build
	bash bench/run.sh

# Soak: SOAK_SECONDS (600) at 30 Hz into the nodelet in a manager, then SOAK_CYCLES (100) load/unload
# cycles; prints RSS growth, frames answered, latency, CPU per frame; fails past the budgets.
soak: build
	bash scripts/soak.sh

# The README's catkin workspace commands in a fresh workspace under $TMPDIR (devel and install space,
# run_tests); JUnit XML into $(ARUCOTAG_BUILD)/test_results/workspace. Needs no build here.
workspace-test: deps
	bash scripts/workspace_test.sh

clean:
	rm -rf $(ARUCOTAG_BUILD)
