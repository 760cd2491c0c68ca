"""The trainer's defaults that scale with the machine (tests/conftest.py `machine` pretends its size): DataLoader
workers no more than the shards and their batches keep busy, torch threads no more than the usable cores."""

import torch

from envisat_pose.perception import train as perception_train
from envisat_pose.perception.train import TrainConfig
from envisat_pose.pipelines.detector.train import default_workers, train_detector


def test_default_workers_follow_the_cores_the_shards_and_the_batches(machine):
    machine(1)
    assert default_workers() == 0 and default_workers(10, 1000, 16) == 0  # in-process on one core
    machine(64, affinity=2)
    assert default_workers() == 1
    machine(64, quota=4)
    assert default_workers() == 3
    machine(64)
    assert default_workers() == 63
    assert default_workers(6) == 6  # a worker per shard at most
    assert default_workers(6, 60, 16) == 3  # 60 images make 3 batches of 16: 3 workers fill one each


def test_the_ranks_on_a_node_share_its_cores_and_memory(machine, monkeypatch):
    """torchrun's LOCAL_WORLD_SIZE ranks share the node's cores (each rank's workers, less one for itself) and its
    memory (each rank's renderers); WORLD_SIZE ranks share the shards; a LOCAL_WORLD_SIZE of 0 (no launcher sets
    it) counts as one process, never a division by zero."""
    from envisat_pose.pipelines.detector.train import RENDERER_BYTES, default_render_workers

    machine(64, memory_gb=1000.0)
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "4")
    assert default_workers() == 64 // 4 - 1
    monkeypatch.setenv("WORLD_SIZE", "8")
    assert default_workers(16) == 2  # 16 shards over 8 ranks
    monkeypatch.delenv("WORLD_SIZE")
    machine(64, memory_gb=20 * RENDERER_BYTES / 1e9)  # room for 20 renderers on the node, 5 a rank
    assert default_render_workers() == 5
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "0")
    machine(64)
    assert default_workers() == 63 and default_render_workers() == 63


def test_a_small_dataset_trains_on_a_big_machine_as_on_a_small_one(machine, monkeypatch, tiny_dataset, tmp_path):
    """8 images in 2 shards of 4, batches of 8: one worker makes a batch an epoch; the 7 workers an 8-core
    machine's cores gave each made none, and the run stopped ("fewer samples than one batch ... per worker")
    where a 2-core machine trained. The torch threads recorded are no more than the usable cores."""
    seen = {}

    def capture(cfg, data_dirs, run_dir, **kwargs):
        seen.update(workers=kwargs["workers"], threads=kwargs["provenance"]["threads"])
        return {"step": 0}

    monkeypatch.setattr(perception_train, "train", capture)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        machine(8)
        train_detector(TrainConfig(steps=1, batch_size=8), tiny_dataset, str(tmp_path / "a"))
        assert seen == {"workers": 1, "threads": 2}
        machine(64, quota=1)
        train_detector(TrainConfig(steps=1, batch_size=8), tiny_dataset, str(tmp_path / "b"))
        assert seen == {"workers": 0, "threads": 1}
        train_detector(TrainConfig(steps=1, batch_size=8), tiny_dataset, str(tmp_path / "c"), workers=2, threads=2)
        assert seen == {"workers": 2, "threads": 2}  # asked for: as asked
        assert torch.get_num_threads() == 2  # the caller's, given back
    finally:
        torch.set_num_threads(before)



def test_a_rank_outside_torchrun_is_rank_0(monkeypatch):
    """RANK set alone (a scheduler's or another tool's variable, WORLD_SIZE unset or 1) is not a DDP rank: the run
    is rank 0 (it writes its checkpoints and record); under torchrun (WORLD_SIZE 2) RANK is the rank."""
    from envisat_pose.pipelines.detector.train import ddp_rank

    monkeypatch.setenv("RANK", "3")
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    assert ddp_rank() == 0
    monkeypatch.setenv("WORLD_SIZE", "1")
    assert ddp_rank() == 0
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "1")
    assert ddp_rank() == 1
