"""Training batches from worker processes: torch.utils.data over the factory's shards, each worker its own shards.

One epoch: the shards in an order drawn from (seed, epoch); shard at position i of that order goes to reader slot
i mod slots, where slots = world x workers (slot = rank + world x worker: with one rank, shard i -> worker
i mod N), so every shard is read by exactly one worker of one rank per epoch. Each sample is built (crop,
augmentation, segments) from its own generator seeded by (seed, epoch, shard index, index in the shard): a
sample does not depend on the worker count. Each worker shuffles its samples in a buffer drawn from
(seed, epoch, slot) and batches them (its ragged end dropped); the DataLoader merges the workers' batches round
robin, in order (torch's in-order delivery), so the batches of an epoch are a function of (seed, epoch, workers,
rank, world) alone. Zero workers (in-process) and one worker give the same batches.

A batch (CPU tensors): the keys of perception/data.py's make_sample stacked, plus sample_id (B, 2) int64: the
shard's index in `paths` and the sample's index in the shard, and reader_slot (B,) int64: the slot that read it.
"""

from __future__ import annotations

import os
import signal

import numpy as np
import torch
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from envisat_pose.config import InputError
from envisat_pose.perception.data import DataConfig, make_sample, read_samples
from envisat_pose.pools import torchrun_int, without_main_script

# The batches the workers hand over live in shared memory (/dev/shm) until trained on: PREFETCH ready per worker
# and loader, two loaders at an epoch's end (train_run.shard_batches starts the next early). A container's default
# /dev/shm is 64 MB, which 2 workers' batches of 16 at 320 px (~9.4 MB each) overran ("unable to allocate shared
# memory ... No space left on device" after 3 steps): the prefetch is sized to what is free (prefetch_factor).
SHM_DIR = "/dev/shm"
PREFETCH = 4
LIVE_LOADERS = 2
SHM_SHARE = 0.8  # of the free shared memory the batches in flight may take
ORDER_KEY = 0x5EED  # the epoch's shard order: (seed, epoch, ORDER_KEY)
BUFFER_KEY = 0xB0F  # a slot's shuffle buffer: (seed, epoch, BUFFER_KEY, slot)


def shard_order(n_shards: int, seed: int, epoch: int) -> np.ndarray:
    """The epoch's order of the shards (indices into the dataset's shard list)."""
    return np.random.default_rng([seed, epoch, ORDER_KEY]).permutation(n_shards)


def slot_shards(n_shards: int, seed: int, epoch: int, slot: int, slots: int) -> list[int]:
    """Indices of the shards that reader slot `slot` of `slots` reads in this epoch (every slots-th of the order)."""
    return [int(i) for i in shard_order(n_shards, seed, epoch)[slot::slots]]


def shard_samples(path: str, shard_index: int, cfg: DataConfig, seed: int, epoch: int):
    """Training samples of one shard, each from its generator (seed, epoch, shard_index, index in the shard)."""
    for j, (_, image, label) in enumerate(read_samples([path])):
        rng = np.random.default_rng([seed, epoch, shard_index, j])
        sample = make_sample(image, label, cfg, rng)
        sample["sample_id"] = np.array([shard_index, j], dtype=np.int64)
        yield sample


class ShardStream(IterableDataset):
    """The samples of one epoch for one rank: in a DataLoader worker w of N, those of slot rank + world * w (see
    the module doc); in-process, slot rank of world."""

    def __init__(self, paths: list[str], cfg: DataConfig, seed: int, epoch: int, rank: int = 0, world: int = 1):
        super().__init__()
        self.paths, self.cfg, self.seed, self.epoch, self.rank, self.world = list(paths), cfg, seed, epoch, rank, world

    def slot(self) -> tuple[int, int]:
        info = get_worker_info()
        worker, workers = (info.id, info.num_workers) if info is not None else (0, 1)
        return self.rank + self.world * worker, self.world * workers

    def __iter__(self):
        slot, slots = self.slot()
        buffer_rng = np.random.default_rng([self.seed, self.epoch, BUFFER_KEY, slot])
        buffer: list[dict] = []
        for i in slot_shards(len(self.paths), self.seed, self.epoch, slot, slots):
            for sample in shard_samples(self.paths[i], i, self.cfg, self.seed, self.epoch):
                sample["reader_slot"] = np.int64(slot)
                buffer.append(sample)
                if len(buffer) >= self.cfg.shuffle_buffer:
                    yield buffer.pop(int(buffer_rng.integers(len(buffer))))
        while buffer:
            yield buffer.pop(int(buffer_rng.integers(len(buffer))))


def collate_batch(samples: list[dict]) -> dict[str, torch.Tensor]:
    """Stack a list of samples into CPU tensors (in the worker, so only the batch crosses processes)."""
    return {k: torch.from_numpy(np.stack([s[k] for s in samples])) for k in samples[0]}


def _worker_init(_: int) -> None:
    """One OpenCV thread per worker: the workers are the parallelism (N workers on N cores, not N x cores).
    SIGINT and SIGTERM are the training process's to handle (it stops after its step with a checkpoint, then
    shuts the workers down): a Ctrl-C that reaches the whole process group must not kill them first."""
    import cv2

    cv2.setNumThreads(1)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)


def _worker_context():
    """Workers start from a fork server (a clean process that imported this module), not by forking the training
    process: a forked child inherits OpenCV's thread pool half-alive (seen here: a worker forked after cv2 had run
    in the parent hung for good in cv2.setNumThreads, on a condition variable of the parent's pool)."""
    import multiprocessing

    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(["envisat_pose.perception.stream"])  # once the server runs, later calls are moot
    _start_forkserver_deaf()
    return ctx


def _start_forkserver_deaf() -> None:
    """Start the fork server (if not running) with SIGINT and SIGTERM ignored, a disposition it and every worker
    it forks inherit from birth: a Ctrl-C to the process group while a worker bootstraps (between the fork and
    _worker_init) otherwise printed a KeyboardInterrupt traceback from the worker. The caller's handlers are
    ignored only for the server's fork and exec (milliseconds); from another thread the server starts as is."""
    import threading
    from multiprocessing import forkserver

    if threading.current_thread() is not threading.main_thread():
        forkserver.ensure_running()
        return
    old = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    old = {sig: h for sig, h in old.items() if h is not None}  # None: a handler not set from Python, left alone
    try:
        for sig in old:
            signal.signal(sig, signal.SIG_IGN)
        forkserver.ensure_running()
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def epoch_batches(paths: list[str], cfg: DataConfig, seed: int, epoch: int, batch_size: int, workers: int,
                  rank: int = 0, world: int = 1, pin_memory: bool = False, prefetch: int = PREFETCH):
    """The iterator of one epoch's batches (epoch_loader's), its workers started without the calling script."""
    with without_main_script():
        return iter(epoch_loader(paths, cfg, seed, epoch, batch_size, workers, rank, world, pin_memory, prefetch))


def worker_error_line(err: Exception) -> str:
    """The one line a worker's exception said: torch re-raises it in the trainer with a 'Caught ... in DataLoader
    worker' header and the worker's whole traceback; a user error keeps only its own message."""
    lines = [ln for ln in str(err).strip().splitlines() if ln.strip()]
    if len(lines) > 1 and lines[0].startswith("Caught "):
        last = lines[-1]
        name = type(err).__name__
        return last.split(f"{name}: ", 1)[1] if f"{name}: " in last else last
    return str(err)


def close_batches(batches) -> None:
    """Stop an epoch iterator's worker processes now. Left to the garbage collector, an iterator caught in a
    reference cycle (a generator's frame held by an exception's traceback) is finalized late, or at the
    interpreter's exit, where joining its workers was seen to hang. torch's DataLoader iterator has no public
    close: `_shutdown_workers` is what its own __del__ calls."""
    shutdown = getattr(batches, "_shutdown_workers", None)
    if shutdown is not None:
        shutdown()


def loader_batches(batches, flag: dict | None = None):
    """The batches of an epoch iterator, with a worker's user error (InputError: a damaged shard, a bad label) as
    its own one line, and the loader's end after a stop signal (its workers gone) as a plain end."""
    try:
        yield from batches
    except InputError as err:
        raise type(err)(worker_error_line(err)) from None
    except RuntimeError:
        if flag and flag.get("signal"):
            return
        raise


def shm_free_bytes() -> int | None:
    """The shared memory free for the workers' batches (SHM_DIR's file system), None where it cannot be read."""
    try:
        st = os.statvfs(SHM_DIR)
    except OSError:
        return None
    return st.f_bavail * st.f_frsize


def sample_bytes(paths: list[str], cfg: DataConfig, seed: int) -> int:
    """The bytes of one training sample as a worker sends it (the first of the first shard, made here)."""
    sample = next(shard_samples(paths[0], 0, cfg, seed, 0), None)
    return 0 if sample is None else sum(np.asarray(v).nbytes for v in sample.values()) + 8  # and its reader_slot


def prefetch_factor(workers: int, batch_bytes: int, free_bytes: int | None) -> int:
    """Batches each worker keeps ready: PREFETCH, fewer where the batches in flight (LIVE_LOADERS x workers x
    prefetch, and the one in training) would take more than SHM_SHARE of the free shared memory; InputError (one
    line, before any step) where one each does not fit."""
    if free_bytes is None or batch_bytes <= 0:
        return PREFETCH
    fit = int((SHM_SHARE * free_bytes / batch_bytes - 1) // (LIVE_LOADERS * workers))
    if fit < 1:
        need_mb = (LIVE_LOADERS * workers + 1) * batch_bytes / 1e6
        raise InputError(f"workers = {workers}: their batches in flight need ~{need_mb:.0f} MB of shared memory and "
                         f"{SHM_DIR} has {free_bytes / 1e6:.0f} MB free: give `workers` 0 (in-process) or fewer, or "
                         "the machine more (a container: docker run --shm-size=1g)")
    return min(PREFETCH, fit)


def run_prefetch(paths: list[str], cfg: DataConfig, seed: int, batch_size: int, workers: int) -> int:
    """The prefetch of a run's loaders, sized once before its first epoch to the shared memory then free (its
    share of it under torchrun; prefetch_factor): while a run trains, its own batches take some of it."""
    free = shm_free_bytes()
    if workers <= 0 or not paths or free is None:
        return PREFETCH
    ranks = max(1, torchrun_int("LOCAL_WORLD_SIZE", 1))  # torchrun's ranks on this node share it
    return prefetch_factor(workers, batch_size * sample_bytes(paths, cfg, seed), free // ranks)


def epoch_loader(paths: list[str], cfg: DataConfig, seed: int, epoch: int, batch_size: int, workers: int,
                 rank: int = 0, world: int = 1, pin_memory: bool = False, prefetch: int = PREFETCH) -> DataLoader:
    """The DataLoader of one epoch: `workers` processes (0: in-process), full batches only, pinned when asked
    (CUDA), each worker `prefetch` batches ahead (run_prefetch; the batches are the same whatever it is). Its own
    torch.Generator (from seed): the global one is neither read nor moved."""
    extra = {"prefetch_factor": prefetch, "worker_init_fn": _worker_init,
             "multiprocessing_context": _worker_context()} if workers > 0 else {}
    return DataLoader(ShardStream(paths, cfg, seed, epoch, rank, world), batch_size=batch_size, drop_last=True,
                      num_workers=workers, collate_fn=collate_batch, pin_memory=pin_memory,
                      generator=torch.Generator().manual_seed(seed), **extra)
