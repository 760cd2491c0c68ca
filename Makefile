# The two commands of the README. Each one installs what it needs first (scripts/setup.sh).
.PHONY: demo test setup

demo: setup
	.venv/bin/envisat simulate --out out/run.npz --plot

test: setup
	.venv/bin/python -m pytest -q

setup:
	@bash scripts/setup.sh
