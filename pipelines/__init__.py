"""Pipelines: the stages joined into the jobs users run (design.md, Layers).

Between the stages and the app: a pipeline may import the core and the stages, never the app; the app's verbs are
argument parsers over it. `tracker` (the truth-free Tracker), `acquisition` (its cold start), `closed_loop`
(`envisat run`: simulate, render, the space camera, the Tracker), `track` (`envisat track`: a user's frames),
`scoring` (a run against a truth), `trials` (the benchmarks' random lit suns, attitudes, axes and trial truths),
`simulate` (`envisat simulate`: a scenario's MuJoCo truth as run.npz), `estimate` (`envisat estimate`: the
batched UKF over R runs of one truth), `campaign` (`envisat montecarlo`: Monte Carlo campaigns in resumable
blocks, rate sweeps), `train` (`envisat train`: the corner detector trained into a run directory, DDP under
torchrun), `evaluate` (`envisat evaluate`: the detector scored against labels, next to Harris and Shi-Tomasi).
"""
