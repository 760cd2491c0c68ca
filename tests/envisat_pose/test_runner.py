"""The core runner: the same results whatever the backend and worker count; errors reach the caller."""

import math

import pytest

from envisat_pose.config import ConfigError
from envisat_pose.runner import RunnerConfig, run_tasks

TASKS = [(n, k) for n in range(20, 26) for k in (3, 7)]
EXPECTED = {i: math.comb(*args) for i, args in enumerate(TASKS)}


@pytest.mark.parametrize("cfg", [RunnerConfig("inline"), RunnerConfig("local", 1), RunnerConfig("local", 2),
                                 RunnerConfig("dask", 2)], ids=["inline", "local-1", "local-2", "dask-2"])
def test_every_backend_returns_every_result_once(cfg):
    got = {}
    for i, result in run_tasks(math.comb, TASKS, cfg):
        assert i not in got
        got[i] = result
    assert got == EXPECTED


def test_inline_yields_in_order_and_sets_the_worker_environment(monkeypatch):
    monkeypatch.delenv("ENVISAT_RUNNER_PROBE", raising=False)
    cfg = RunnerConfig("inline", env={"ENVISAT_RUNNER_PROBE": "1"})
    assert [i for i, _ in run_tasks(math.comb, TASKS, cfg)] == list(range(len(TASKS)))
    import os

    assert os.environ["ENVISAT_RUNNER_PROBE"] == "1"


@pytest.mark.parametrize("cfg", [RunnerConfig("inline"), RunnerConfig("local", 2)], ids=["inline", "local-2"])
def test_a_failing_task_raises_in_the_caller(cfg):
    with pytest.raises(ValueError):
        list(run_tasks(math.comb, [(5, 2), (-1, 2), (6, 2)], cfg))


def test_bad_runner_config_names_the_field():
    with pytest.raises(ConfigError, match="workers"):
        list(run_tasks(math.comb, TASKS, RunnerConfig("local", 0)))
    with pytest.raises(ConfigError, match="scheduler"):
        list(run_tasks(math.comb, TASKS, RunnerConfig("local", 2, scheduler="tcp://127.0.0.1:1")))
