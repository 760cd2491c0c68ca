# The two commands of the README. Each one installs what it needs first (scripts/setup.sh).
.PHONY: demo test setup

demo: setup
	mkdir -p out
	.venv/bin/envisat demo --out out/demo
	.venv/bin/envisat simulate --out out/run.npz --plot
	.venv/bin/envisat estimate --truth out/run.npz --runs 30 --out out/est.npz --plot

test:
	@WITH_VIEWER_CHECK=1 bash scripts/setup.sh
	.venv/bin/python -m pytest -q

setup:
	@bash scripts/setup.sh
