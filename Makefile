# The two commands of the README. Each one installs what it needs first (scripts/setup.sh).
.PHONY: demo test setup

demo: setup
	mkdir -p out
	.venv/bin/envisat demo --out out/demo
	.venv/bin/envisat simulate --out out/run.npz --plot
	.venv/bin/envisat estimate --truth out/run.npz --runs 30 --out out/est.npz --plot

test: setup
	.venv/bin/python -m pytest -q

setup:
	@bash scripts/setup.sh
