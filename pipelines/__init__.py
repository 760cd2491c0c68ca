"""Pipelines: the stages joined into the jobs users run (design.md, Layers), one sub-package per job.

Between the stages and the app: a pipeline may import the core and the stages, never the app; the app's verbs are
argument parsers over it. `tracking` (the truth-free Tracker, its cold start, bank, integrity checks and builders),
`runs` (`envisat run`'s closed loop and `envisat track` on a user's frames, their files, scoring against a truth,
the benchmarks' trials), `campaigns` (`envisat simulate`, `estimate`, `montecarlo` and `report`), `detector`
(`envisat train`, `detect`, `evaluate`, `calibrate`), `adaptation` (`envisat adapt`), `datasets` (`envisat dataset
export`), `common` (what the jobs share below them); `jobs.py` resolves a named scenario into any job's config.
The groups import one another without a loop (tests/test_architecture.py).
"""
