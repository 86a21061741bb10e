# The two README commands: `make demo` (the main job) and `make test`; both set up first.
.PHONY: setup demo test
SHELL := /bin/bash

setup:
	@bash scripts/setup.sh

demo: setup
	@bash scripts/demo.sh

test: setup
	@source env.sh && python -m pytest -q test
