# The two commands a new machine needs: `make demo` and `make test`. Both install what is missing.
SHELL := /bin/bash
export ARUCOTAG_BUILD ?= $(CURDIR)/build

.PHONY: deps build test sanitize demo bench clean

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

demo: build
	bash scripts/demo.sh

# Detection benchmark: prints the table and writes $(ARUCOTAG_BUILD)/bench/results.{json,md}.
bench: build
	bash bench/run.sh

clean:
	rm -rf $(ARUCOTAG_BUILD)
