"""A worker count given above what the machine holds (tests/conftest.py `machine`: 2 usable cores of 64, and where
a process's memory is measured, too little memory) is warned of once, in one line naming the field, the value and
the cores or memory, by every job that takes one: generate's shards, dataset export's, a campaign's blocks, a run's
closed loops, a training run's loader workers and renderers. Only the defaults were capped: a count given ran
without a word. Each job is stopped right after its checks (what follows is the job's own work)."""

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import warnings

import pytest

from envisat_pose.app.cli import main

CORES = r"^workers = 8: more processes than the 2 usable cores \(they share them\); the job runs as asked$"


class Stopped(Exception):
    """Raised where a test stops a job, its checks passed."""


def stop(*args, **kwargs):
    raise Stopped


def said(record) -> list[str]:
    return [str(w.message) for w in record if "usable cores" in str(w.message) or "of memory" in str(w.message)]


def test_generate_warns_of_more_workers_than_cores_and_the_verb_names_the_flag(machine, monkeypatch, tmp_path,
                                                                               capsys):
    from envisat_pose import GenerateConfig, run_generate
    from envisat_pose.datagen import factory

    machine(64, affinity=2)
    monkeypatch.setattr(factory, "spare_core", stop)  # the pool's start, the folder's shards scanned
    with pytest.warns(UserWarning) as record, pytest.raises(Stopped):
        run_generate(GenerateConfig(num_images=8, shard_size=1, resolution_px=64), str(tmp_path / "a"), workers=8)
    assert len(said(record)) == 1 and said(record)[0].startswith("workers = 8: more processes than the 2 usable")
    with warnings.catch_warnings(), pytest.raises(Stopped):
        warnings.simplefilter("error")  # 8 workers for 2 shards start 2 processes
        run_generate(GenerateConfig(num_images=2, shard_size=1, resolution_px=64), str(tmp_path / "b"), workers=8)
    monkeypatch.setattr(factory, "spare_core", lambda *a: (_ for _ in ()).throw(KeyboardInterrupt))
    assert main(["generate", "--num-images", "8", "--shard-size", "1", "--workers", "8", "--quiet", "--out",
                 str(tmp_path / "c")]) == 130
    lines = capsys.readouterr().err.splitlines()
    assert lines[0] == ("envisat generate: warning: --workers 8: more processes than the 2 usable cores (they share "
                        "them); the job runs as asked") and len(lines) == 2  # the warning, the interrupt


def test_a_generate_rerun_warns_only_of_the_processes_its_shards_left_start(machine, tmp_path, capsys):
    """A finished dataset rerun starts no process, one shard left starts one: neither says a word (the warning
    counted every shard of the dataset, and came on a rerun that had nothing to do)."""
    from envisat_pose import GenerateConfig, run_generate

    cfg, out = GenerateConfig(num_images=3, shard_size=1, resolution_px=64), str(tmp_path / "a")
    manifest = run_generate(cfg, out)
    machine(64, affinity=2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert run_generate(cfg, out, workers=8)["shards"] == manifest["shards"]  # nothing to do
        os.remove(os.path.join(out, manifest["shards"][0]["name"]))
        assert len(run_generate(cfg, out, workers=8)["shards"]) == 3  # one shard redone, in one process
    capsys.readouterr()
    assert main(["generate", "--num-images", "3", "--shard-size", "1", "--resolution", "64", "--workers", "8",
                 "--out", out]) == 0
    assert "warning" not in capsys.readouterr().err


def test_a_campaign_and_a_rate_sweep_warn_once(machine, monkeypatch, tmp_path):
    from envisat_pose import MonteCarloConfig, RunnerConfig, run_campaign
    from envisat_pose.pipelines.campaigns import campaign, sweep

    machine(64, affinity=2)
    monkeypatch.setattr(campaign, "campaign_at_one_rate", stop)
    monkeypatch.setattr(sweep, "campaign_at_one_rate", stop)
    cfg = MonteCarloConfig(runs=8, block_runs=1, duration_s=20.0)
    for job in (lambda: run_campaign(cfg, tmp_path / "one", RunnerConfig("local", 8)),
                lambda: sweep.run_sweep(cfg, sweep.sweep_for(cfg, [1.0, 2.0]), str(tmp_path / "sweep"),
                                        RunnerConfig("local", 8))):
        with pytest.warns(UserWarning) as record, pytest.raises(Stopped):
            job()
        assert len(said(record)) == 1 and said(record)[0].startswith("workers = 8: more processes than the 2")
    with warnings.catch_warnings(), pytest.raises(Stopped):
        warnings.simplefilter("error")
        run_campaign(cfg, tmp_path / "inline", RunnerConfig("inline", 8))  # one process: this one


def test_a_run_warns_of_its_closed_loops_beyond_the_cores_and_the_memory(machine, monkeypatch, tmp_path):
    """8 closed loops at RUN_PROCESS_BYTES (1.4 GB) on 2 cores and 5 GB: both in one line; the default count, sized
    to the machine, says nothing."""
    from envisat_pose.pipelines.runs import closed_loop
    from envisat_pose.pipelines.runs.run_config import RunConfig

    machine(64, affinity=2, memory_gb=5.0)
    monkeypatch.setattr(closed_loop, "made_out_dir", stop)
    with pytest.warns(UserWarning) as record, pytest.raises(Stopped):
        closed_loop.run_closed_loop(RunConfig(runs=8, workers=8, duration_s=5.0), str(tmp_path / "r"))
    assert said(record) == ["workers = 8: more processes than the 2 usable cores (they share them); 8 processes at "
                            "~1.4 GB each need ~11.2 GB, more than the 5.0 GB of memory available; the job runs as "
                            "asked"]
    with warnings.catch_warnings(), pytest.raises(Stopped):
        warnings.simplefilter("error")
        closed_loop.run_closed_loop(RunConfig(runs=8, duration_s=5.0), str(tmp_path / "r"))


def test_training_warns_of_its_loader_workers_and_of_its_renderers_memory(machine, monkeypatch, tmp_path):
    from envisat_pose import GenerateConfig, TrainConfig, run_generate, train_detector
    from envisat_pose.pipelines.detector import train
    from envisat_pose.pipelines.detector.train import OnlineConfig

    data = str(tmp_path / "data")
    run_generate(GenerateConfig(num_images=1, shard_size=1, resolution_px=64), data)
    monkeypatch.setattr(train, "output_lock", stop)
    machine(64, affinity=2, memory_gb=2.0)
    with pytest.warns(UserWarning) as record, pytest.raises(Stopped):
        train_detector(TrainConfig(steps=1), [data], str(tmp_path / "run"), workers=8)
    assert len(said(record)) == 1 and said(record)[0].startswith("workers = 8: more processes than the 2 usable")
    online = OnlineConfig(GenerateConfig(resolution_px=64), workers=2)  # within the cores, not 2 GB at 1.2 GB each
    with pytest.warns(UserWarning) as record, pytest.raises(Stopped):
        train_detector(TrainConfig(steps=1), [], str(tmp_path / "run"), online=online)
    assert said(record) == ["online.workers = 2: 2 processes at ~1.2 GB each need ~2.4 GB, more than the 2.0 GB of "
                            "memory available; the job runs as asked"]


def test_training_under_torchrun_counts_every_local_ranks_loader_workers(machine, monkeypatch, tmp_path):
    """Each of a node's torchrun ranks starts its own DataLoader workers: 2 workers on each of 2 local ranks are 4
    processes on 2 usable cores (the warning counted one rank's 2 and said nothing)."""
    from envisat_pose import GenerateConfig, TrainConfig, run_generate, train_detector
    from envisat_pose.pipelines.detector import train

    data = str(tmp_path / "data")
    run_generate(GenerateConfig(num_images=1, shard_size=1, resolution_px=64), data)
    monkeypatch.setattr(train, "output_lock", stop)
    machine(64, affinity=2)
    for name, value in (("WORLD_SIZE", "2"), ("LOCAL_WORLD_SIZE", "2"), ("RANK", "0"), ("LOCAL_RANK", "0")):
        monkeypatch.setenv(name, value)
    with pytest.warns(UserWarning) as record, pytest.raises(Stopped):
        train_detector(TrainConfig(steps=1), [data], str(tmp_path / "run"), workers=2)
    assert said(record) == ["workers = 2 for each of the machine's 2 ranks (4 processes): more processes than the 2 "
                            "usable cores (they share them); the job runs as asked"]
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "1")  # two machines of one rank each: 2 workers on each machine's 2 cores
    with warnings.catch_warnings(), pytest.raises(Stopped):
        warnings.simplefilter("error")
        train_detector(TrainConfig(steps=1), [data], str(tmp_path / "run"), workers=2)
