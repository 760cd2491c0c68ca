"""The verbs' defaults that scale with the machine, on machines these tests pretend (tests/conftest.py `machine`):
one core, 64 cores, 64 by os.cpu_count but 2 by affinity or by a cgroup quota, 64 cores with 24 GB."""

import argparse

import pytest
import torch

from envisat_pose.app.cli import build_parser


def parsed(argv: list[str]) -> argparse.Namespace:
    return build_parser().parse_args(argv)


@pytest.mark.parametrize("affinity, quota, workers", [(None, None, 64), (2, None, 2), (None, 2, 2)])
def test_dataset_export_starts_one_worker_per_usable_core(machine, affinity, quota, workers):
    machine(64, affinity, quota)
    assert parsed(["dataset", "export", "src", "--format", "coco", "--out", "new"]).workers == workers


@pytest.mark.parametrize("cores, affinity, memory_gb, workers", [
    (1, None, 1000, 1),
    (64, 2, 1000, 2),     # taskset -c 0,1 on a 64-core host: 8 processes (9.1 GB RSS) ran slower than 2 (2.9 GB)
    (64, None, 5.0, 3),   # 1.4 GB a closed loop: 64 cores, 5 GB free
    (64, None, 1000, 8),  # one per run
    (512, None, 1000, 8),
])
def test_run_starts_no_more_closed_loops_than_the_cores_and_memory_hold(machine, cores, affinity, memory_gb,
                                                                        workers):
    from envisat_pose.pipelines.runs.run_config import RunConfig

    machine(cores, affinity, memory_gb=memory_gb)
    assert RunConfig(scenario="default", runs=8, duration_s=5.0).workers == workers


def test_a_run_of_many_loops_on_a_huge_machine_starts_the_most_processes_a_run_may(machine):
    """300 runs on 512 cores with 1 TB: 256 processes (RunConfig's limit), not a refused default of 300."""
    from envisat_pose.pipelines.runs.run_config import RunConfig

    machine(512, memory_gb=1000)
    assert RunConfig(scenario="default", runs=300, duration_s=5.0).workers == 256


def test_online_training_starts_no_more_renderers_than_the_memory_holds(machine, tmp_path):
    """63 renderers (a 64-core machine's cores less one) at ~1.1 GB each would need ~67 GB of a 24 GB machine."""
    from envisat_pose.app.train import online_config, resolve_config

    machine(64, memory_gb=24)
    args = parsed(["train", "--online", "--out", str(tmp_path / "run")])
    assert online_config(args, resolve_config(args)).workers == 20
    machine(64, affinity=2)
    args = parsed(["train", "--online", "--out", str(tmp_path / "run")])
    assert online_config(args, resolve_config(args)).workers == 1


def test_the_detector_verbs_run_torch_on_no_more_threads_than_the_quota_allows(machine):
    """A container's --cpus=2 on a 64-core host: torch would run its default (the affinity's cores) under a quota
    of 2; --threads still sets any count."""
    from envisat_pose.app.detect import detector_inputs

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        machine(64, quota=1)
        detector_inputs(argparse.Namespace(limit=None, weights=None, threads=None, target=None))
        assert torch.get_num_threads() == 1
        detector_inputs(argparse.Namespace(limit=None, weights=None, threads=3, target=None))
        assert torch.get_num_threads() == 3
    finally:
        torch.set_num_threads(before)
