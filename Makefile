# The commands of the README. Each one installs what it needs first (scripts/setup.sh).
# Tests in two lanes: `make test` the fast one (minutes), `make test-slow` the slow end-to-end tests (marked
# `slow`: tests/conftest.py), `make test-all` both (what CI runs: .ci/run). The fast lane runs in TEST_WORKERS
# processes (pytest-xdist; a test file's tests in one process, so module fixtures are built once); the slow lane
# runs in one, since several of its tests start worker processes of their own.
TEST_WORKERS ?= 2
FAST = .venv/bin/python -m pytest -q -m "not slow" -n $(TEST_WORKERS) --dist loadfile
.PHONY: demo test test-slow test-all setup

demo: setup
	mkdir -p out
	.venv/bin/envisat demo --out out/demo
	.venv/bin/envisat simulate --out out/run.npz --plot
	.venv/bin/envisat estimate --truth out/run.npz --runs 30 --out out/est.npz --plot

test:
	@bash scripts/setup.sh
	$(FAST)

test-slow:
	@WITH_VIEWER_CHECK=1 bash scripts/setup.sh
	.venv/bin/python -m pytest -q -m slow

# both lanes, the fast one first; the slow lane runs even when the fast one failed, and the exit status is a failure
# if either failed
test-all:
	@WITH_VIEWER_CHECK=1 bash scripts/setup.sh
	@rc=0; $(FAST) || rc=1; .venv/bin/python -m pytest -q -m slow || rc=1; exit $$rc

setup:
	@bash scripts/setup.sh
