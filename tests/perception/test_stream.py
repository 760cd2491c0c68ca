"""The trainer's loader (perception/stream.py) and loop (perception/train.py) with worker processes: the same seed
and worker count give bitwise the same batches, every shard is read by exactly one worker per epoch, a resumed
run trains on exactly the batches it had not trained on, a time budget stops the run inside it with a checkpoint
and a decayed rate, bf16 autocast trains on the CPU."""

import io
import json
import os
import tarfile
from collections import defaultdict

import numpy as np
import pytest
import torch

from envisat_pose.config import InputError
from envisat_pose.perception.data import DataConfig, shard_paths
from envisat_pose.perception.model import ModelConfig
from envisat_pose.perception.stream import epoch_loader, shard_order, slot_shards
from envisat_pose.perception.train import TrainConfig, train

SHARD_SIZES = (1, 2, 1, 3, 1)  # ragged on purpose: workers end their epochs at different batches


@pytest.fixture(scope="module")
def many_shards(tiny_dataset, tmp_path_factory):
    """The tiny dataset's 8 samples re-cut into 5 shards of 1, 2, 1, 3 and 1 samples (no manifest: *.tar)."""
    members = []
    for path in shard_paths(tiny_dataset):
        with tarfile.open(path) as tar:
            members += [(m, tar.extractfile(m).read()) for m in tar.getmembers()]
    keys = sorted({m.name.split(".", 1)[0] for m, _ in members})
    assert len(keys) == sum(SHARD_SIZES)
    out = tmp_path_factory.mktemp("many")
    start = 0
    for s, size in enumerate(SHARD_SIZES):
        mine = set(keys[start:start + size])
        start += size
        with tarfile.open(out / f"shard-{s:06d}.tar", "w") as tar:
            for m, data in members:
                if m.name.split(".", 1)[0] in mine:
                    tar.addfile(m, io.BytesIO(data))
    return str(out)


CFG = DataConfig(input_px=64, shuffle_buffer=3)


def batches(paths, seed, workers, epoch=0, n=None, batch_size=2):
    out = []
    for i, b in enumerate(epoch_loader(paths, CFG, seed, epoch, batch_size, workers)):
        if n is not None and i == n:
            break
        out.append(b)
    return out


def same(a, b):
    return len(a) == len(b) and all(x.keys() == y.keys() and all(torch.equal(x[k], y[k]) for k in x)
                                    for x, y in zip(a, b))


def test_same_seed_and_workers_give_bitwise_the_same_batches(many_shards):
    paths = shard_paths(many_shards)
    a, b = batches(paths, 3, workers=2, n=3), batches(paths, 3, workers=2, n=3)
    assert len(a) == 3 and same(a, b)
    assert not same(a, batches(paths, 4, workers=2, n=3))  # another seed: other crops and order
    # one worker process builds what the training process builds itself
    assert same(batches(paths, 3, workers=0), batches(paths, 3, workers=1))


def test_every_shard_is_read_by_exactly_one_worker_per_epoch(many_shards):
    paths = shard_paths(many_shards)
    for slots in (1, 2, 3, 7):  # 7: more readers than shards
        for epoch in (0, 1):
            parts = [slot_shards(len(paths), 9, epoch, s, slots) for s in range(slots)]
            assert sorted(i for p in parts for i in p) == list(range(len(paths)))
    for workers in (2, 3):
        for epoch in (0, 1):
            order = shard_order(len(paths), 9, epoch)
            readers, seen = defaultdict(set), []
            for b in batches(paths, 9, workers, epoch=epoch, batch_size=1):
                for (shard, j), slot in zip(b["sample_id"].tolist(), b["reader_slot"].tolist()):
                    readers[shard].add(slot)
                    seen.append((shard, j))
            # every sample once (batches of 1: nothing dropped), each shard by one worker: i -> i mod N
            assert sorted(seen) == [(s, j) for s, n in enumerate(SHARD_SIZES) for j in range(n)]
            assert dict(readers) == {int(s): {pos % workers} for pos, s in enumerate(order)}


def small_config(steps, **kw):
    return TrainConfig(**{**dict(steps=steps, batch_size=2, lr=3e-3, warmup_steps=2, checkpoint_every=10**6,
                                 model=ModelConfig(input_px=64, width=16, depth=2, stem_width=8),
                                 data=DataConfig(input_px=64, shuffle_buffer=3)), **kw})


def test_resumed_run_trains_on_what_it_had_not(many_shards, tmp_path, monkeypatch):
    """With 2 workers: a run stopped at step 2 and resumed to 6 sees exactly the batches 3-6 of an uninterrupted
    run (by sample id) and ends with its weights; another worker count is refused."""
    import envisat_pose.perception.train as train_module
    from envisat_pose.perception.weights import load_model

    torch.set_num_threads(1)
    real, seen = train_module.to_device, []

    def record(batch, device):
        seen.append(batch["sample_id"].clone())
        return real(batch, device)

    monkeypatch.setattr(train_module, "to_device", record)
    whole, part = str(tmp_path / "whole"), str(tmp_path / "part")
    train(small_config(6), many_shards, whole, progress=False, workers=2)
    whole_ids, seen[:] = list(seen), []
    train(small_config(2), many_shards, part, progress=False, workers=2)
    assert json.load(open(os.path.join(part, "state.json")))["workers"] == 2
    with pytest.raises(InputError, match="resume it with `workers` 2"):
        train(small_config(6), many_shards, part, resume=True, progress=False, workers=3)
    seen[:] = []
    train(small_config(6), many_shards, part, resume=True, progress=False)  # None: the run's own count
    assert len(whole_ids) == 6 and len(seen) == 4
    assert all(torch.equal(a, b) for a, b in zip(seen, whole_ids[2:]))
    a = load_model(os.path.join(whole, "checkpoint.safetensors")).state_dict()
    b = load_model(os.path.join(part, "checkpoint.safetensors")).state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)


class StepClock:
    """A clock that moves `tick` seconds each time it is read: the budget's logic tested on its own time, not on
    the machine's speed (the trainer reads its clock a fixed number of times per step)."""

    def __init__(self, tick: float):
        self.t, self.tick = 0.0, tick

    def __call__(self) -> float:
        self.t += self.tick
        return self.t


def test_time_budget_stops_inside_it_with_a_checkpoint_and_a_decayed_rate(many_shards, tmp_path):
    from envisat_pose.perception.weights import read_weights

    torch.set_num_threads(1)
    budget_s = 15.0
    cfg = small_config(10**6, time_budget_s=budget_s, checkpoint_every=5)
    run = str(tmp_path / "run")
    clock = StepClock(0.1)
    end = train(cfg, many_shards, run, progress=False, workers=1, clock=clock)
    state = json.load(open(os.path.join(run, "state.json")))
    assert end["stopped_by"] == "time_budget" and end["step"] > 3
    assert clock.t < budget_s and state["time_s"] < budget_s  # stopped inside the budget, checkpoint included
    assert state["step"] == end["step"]  # the final checkpoint holds the last step
    _, meta = read_weights(os.path.join(run, "checkpoint.safetensors"))
    assert int(meta["step"]) == end["step"]
    # the rate fell from its peak towards the bottom of the cosine (5 % of it at the budget's end; the run stops
    # a step and a checkpoint early)
    assert end["lr"] < 0.3 * cfg.lr
    assert clock.t > 0.7 * budget_s  # it used the budget, not a fraction of it
    # a slower machine (each step reads as longer) stops sooner, inside the same budget
    slow = StepClock(0.3)
    end_slow = train(cfg, many_shards, str(tmp_path / "slow"), progress=False, workers=1, clock=slow)
    assert end_slow["stopped_by"] == "time_budget" and 1 <= end_slow["step"] < end["step"]
    assert slow.t < budget_s


def test_bf16_autocast_trains_on_the_cpu(many_shards, tmp_path):
    """--bf16: the training steps' convolutions run under CPU autocast, their outputs bfloat16 (a global forward
    hook sees every module's output), and the loss stays finite; without it they run in float32 (the control,
    one step)."""
    torch.set_num_threads(1)
    dtypes = {True: set(), False: set()}
    flag = None

    def conv_output(module, args, output):
        if isinstance(module, torch.nn.Conv2d) and module.training:
            dtypes[flag].add(output.dtype)

    handle = torch.nn.modules.module.register_module_forward_hook(conv_output)
    try:
        flag = True
        end = train(small_config(3), many_shards, str(tmp_path / "bf16"), progress=False, workers=0, bf16=True)
        flag = False
        plain = train(small_config(1), many_shards, str(tmp_path / "fp32"), progress=False, workers=0)
    finally:
        handle.remove()
    assert end["bf16"] is True and end["step"] == 3 and plain["bf16"] is False
    assert dtypes == {True: {torch.bfloat16}, False: {torch.float32}}, dtypes
    assert np.isfinite(end["loss"]) and end["loss"] > 0


def test_the_prefetch_fits_the_shared_memory():
    """Batches in flight: 2 loaders x workers x prefetch, and the one in training, within 0.8 of the free shared
    memory. 10 MB batches, 2 workers: 100 MB free holds (80 / 10 - 1) // 4 = 1 each; 1 GB 4 (the most); 40 MB not
    one: refused in one line naming `workers` and what to do."""
    from envisat_pose.perception.stream import PREFETCH, prefetch_factor

    mb = 1_000_000
    assert prefetch_factor(2, 10 * mb, 100 * mb) == 1
    assert prefetch_factor(2, 10 * mb, 130 * mb) == 2  # (104 / 10 - 1) // 4 = 2
    assert prefetch_factor(2, 10 * mb, 1000 * mb) == PREFETCH == 4
    assert prefetch_factor(2, 10 * mb, None) == PREFETCH  # no /dev/shm to read: torch's way
    with pytest.raises(InputError, match=r"^workers = 2: .* ~50 MB of shared memory .* 40 MB free") as err:
        prefetch_factor(2, 10 * mb, 40 * mb)
    assert "\n" not in str(err.value) and "--shm-size" in str(err.value)


def test_the_ranks_on_a_node_share_its_shared_memory(monkeypatch):
    """Under torchrun each of the node's LOCAL_WORLD_SIZE ranks sizes its loaders' prefetch to its share of the
    free shared memory: 10 MB batches, 2 workers, 520 MB free: one rank prefetches 4 (the most), each of 4 ranks
    (130 MB: (104 / 10 - 1) // 4 = 2) 2; a LOCAL_WORLD_SIZE of 0 counts as one."""
    from envisat_pose.perception import stream

    mb = 1_000_000
    monkeypatch.setattr(stream, "shm_free_bytes", lambda: 520 * mb)
    monkeypatch.setattr(stream, "sample_bytes", lambda paths, cfg, seed: 10 * mb)
    for ranks, prefetch in (("", 4), ("4", 2), ("0", 4)):
        monkeypatch.setenv("LOCAL_WORLD_SIZE", ranks)
        assert stream.run_prefetch(["shard"], None, 0, 1, 2) == prefetch, ranks


def test_a_run_sizes_its_prefetch_to_the_free_shared_memory(many_shards, tmp_path, monkeypatch):
    """Measured once before the first epoch from a sample made in-process: with little shared memory free the
    workers prefetch less and train the same batches; with none to spare the run is refused before any step."""
    from envisat_pose.perception import stream

    seen = []
    real = stream.epoch_loader
    monkeypatch.setattr(stream, "epoch_loader", lambda *a, **k: seen.append(a[-1]) or real(*a, **k))
    one = sum(np.asarray(v).nbytes for v in next(stream.shard_samples(
        shard_paths(many_shards)[0], 0, small_config(1).data, 0, 0)).values()) + 8
    assert stream.sample_bytes(shard_paths(many_shards), small_config(1).data, 0) == one
    batch = 2 * one  # batch_size 2
    monkeypatch.setattr(stream, "shm_free_bytes", lambda: int((2 * 1 * 2 + 1) * batch / 0.8) + 1)  # 2 each for 1 worker
    train(small_config(2), many_shards, str(tmp_path / "a"), progress=False, workers=1)
    assert seen and set(seen) == {2}
    monkeypatch.setattr(stream, "shm_free_bytes", lambda: batch)
    with pytest.raises(InputError, match="shared memory"):
        train(small_config(2), many_shards, str(tmp_path / "b"), progress=False, workers=1)
    assert not (tmp_path / "b").exists()


def test_workers_ignore_ctrl_c_from_their_first_instruction():
    """A worker forked while Ctrl-C reaches the process group must not print a traceback from its bootstrap
    (seen in CI: KeyboardInterrupt in multiprocessing's _after_fork, before _worker_init ran): the fork server
    hands SIGINT and SIGTERM ignored to every process it forks; the caller's own handlers are kept."""
    import signal

    from envisat_pose.perception.stream import _worker_context

    before = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    ctx = _worker_context()
    assert {sig: signal.getsignal(sig) for sig in before} == before
    for sig in (signal.SIGINT, signal.SIGTERM):
        child = ctx.Process(target=signal.raise_signal, args=(sig,))  # at once: no worker_init, no handler set
        child.start()
        child.join(60)
        assert child.exitcode == 0, (sig, child.exitcode)  # 1: KeyboardInterrupt; -15: killed by SIGTERM


def test_a_buffer_beyond_the_samples_gives_the_order_a_buffer_of_them_all_gives(many_shards):
    """What the warning of a shuffle_buffer over the data's samples says (perception.data.warn_shuffle_buffer): a
    reader shuffles all of its samples, in the order a buffer of exactly the data's size gives."""
    from envisat_pose.perception.stream import ShardStream

    paths = shard_paths(many_shards)
    n = sum(SHARD_SIZES)

    def order(buffer):
        cfg = DataConfig(input_px=64, shuffle_buffer=buffer)
        return [tuple(s["sample_id"]) for s in ShardStream(paths, cfg, seed=3, epoch=1)]

    assert order(10 * n) == order(n) and len(order(n)) == n
    assert order(10 * n) != order(1)  # the order is shuffled at all: a buffer of one is the shards' order
