# The commands of the README. Each one installs what it needs first (scripts/setup.sh).
# Tests in two lanes: `make test` the fast one (minutes), `make test-slow` the slow end-to-end tests (marked
# `slow`: tests/conftest.py), `make test-all` both (what CI runs: .ci/run). The fast lane runs in TEST_WORKERS
# processes (pytest-xdist; a test file's tests in one process, so module fixtures are built once); the slow lane
# runs in one, since several of its tests start worker processes of their own.
TEST_WORKERS ?= 2
FAST = .venv/bin/python -m pytest -q -m "not slow" -n $(TEST_WORKERS) --dist loadfile
# ruff (pyproject.toml [tool.ruff]): unused imports and variables, undefined names, import order
LINT = .venv/bin/ruff check .
.PHONY: demo test test-slow test-all setup

demo: setup
	mkdir -p out
	.venv/bin/envisat demo --out out/demo
	.venv/bin/envisat simulate --out out/run.npz --plot
	.venv/bin/envisat estimate --truth out/run.npz --runs 30 --out out/est.npz --plot

test:
	@bash scripts/setup.sh
	$(LINT)
	$(FAST)

test-slow:
	@WITH_VIEWER_CHECK=1 bash scripts/setup.sh
	.venv/bin/python -m pytest -q -m slow

# the linter, then both lanes, the fast one first; every part runs even when one before it failed, and the exit
# status is a failure if any failed
test-all:
	@WITH_VIEWER_CHECK=1 bash scripts/setup.sh
	@rc=0; $(LINT) || rc=1; $(FAST) || rc=1; .venv/bin/python -m pytest -q -m slow || rc=1; exit $$rc

setup:
	@bash scripts/setup.sh
