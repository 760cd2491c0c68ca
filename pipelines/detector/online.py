"""Training on frames as they are rendered: renderer processes (pipelines/detector/render_pool.py) hand raw frames and
labels to the trainer, which keeps the window on its device (pipelines/detector/device_pool.py) and crops and augments them
there (perception/batch_augment.py). No PNG, no tar. The frames are those of one GenerateConfig or of a mix of
looks (pipelines/detector/look_mix.py: which look and sample each frame is).

Schedule (K uses per frame, N samples per batch). Step s trains on the window of N consecutive frames
[floor(s N / K), floor(s N / K) + N), one crop of each: the window moves by N / K frames a step, so every frame is
cropped in at most K steps (exactly K once the run is past its first window), each time with its own placement,
scale and augmentation. Step s's crops, augmentation and line segments come from a generator seeded by
(seed, step): a batch is a function of (gen_cfg, data_cfg, seed, N, K, step) alone, whatever the worker count.

State (yielded after each step, JSON-able): the step to run next, the window's first frame (the first frame a
resumed run renders), the frames taken so far, the most uses any frame has had, and the run's identity (seed,
batch size, K, the sha256 of the configs and the looks' shares); `online_batches(..., start_state=state)`
continues with the next step, and frames that left the window are never rendered again.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace

import numpy as np

from envisat_pose.config import InputError, check, to_dict
from envisat_pose.pipelines.detector.device_pool import DevicePool
from envisat_pose.pipelines.detector.look_mix import as_looks, look_shares, max_side
from envisat_pose.pipelines.detector.render_pool import RenderPool

ONLINE_FORMAT = "envisat-pose online v1"
DEFAULT_USES_PER_FRAME = 8
MAX_USES_PER_FRAME = 8  # the cap: no frame cropped more than 8 times
STEP_KEY = 0x0A1E  # a step's generator: SeedSequence([seed, STEP_KEY, step]) (DDP rank r > 0: [..., step, r])
STREAM_KEY = 0x5A2B  # DDP rank r > 0's look seeds: SeedSequence([look seed, STREAM_KEY, r])


# ---------------------------------------------------------------------------------------------------------
# The schedule


def window_start(step: int, batch_size: int, uses_per_frame: int) -> int:
    """The first frame of step `step`'s window: floor(step N / K)."""
    return (step * batch_size) // uses_per_frame


def uses_before(frame: int, step: int, batch_size: int, uses_per_frame: int) -> int:
    """How many steps before `step` had `frame` in their window (its crops so far)."""
    n, s = 0, step - 1
    while s >= 0 and window_start(s, batch_size, uses_per_frame) + batch_size > frame:
        n += window_start(s, batch_size, uses_per_frame) <= frame
        s -= 1
    return n


def step_seed(seed: int, step: int, stream: int = 0) -> int:
    """The seed of step `step`'s torch.Generator (crops, augmentation, segments); stream: the DDP rank."""
    key = [seed, STEP_KEY, step] + ([stream] if stream else [])
    return int(np.random.SeedSequence(key).generate_state(1, dtype=np.uint64)[0] >> 1)


def stream_looks(looks: tuple, stream: int) -> tuple:
    """The looks DDP rank `stream` renders: rank 0's (a single process's) as given, another rank's with each look's
    seed drawn from (its seed, stream), so the ranks train on different frames (the same frames on every rank
    added nothing but the count)."""
    def seed(look) -> int:
        key = [look.generate.seed, STREAM_KEY, stream]
        return int(np.random.SeedSequence(key).generate_state(1, dtype=np.uint64)[0] >> 1)

    return looks if stream == 0 else tuple(replace(look, generate=replace(look.generate, seed=seed(look)))
                                           for look in looks)


def run_configs(looks, data_cfg) -> dict:
    """The configs an online run renders and crops by: its GenerateConfig (or the looks with their shares of the
    period) and the data config, as plain data (what run_identity hashes; a resume's refusal names their
    differences)."""
    looks = as_looks(looks)
    if len(looks) == 1:  # one look: its config alone (the record of runs made before mixes)
        source = {"generate": to_dict(looks[0].generate)}
    else:
        source = {"looks": [dict(look.record(), share=int(n)) for look, n in zip(looks, look_shares(looks))]}
    return dict(source, data=data_cfg.to_dict())


def run_identity(looks, data_cfg, seed: int, batch_size: int, uses_per_frame: int) -> dict:
    """What a state must match to resume a run: seed, N, K and the sha256 of the configs (run_configs)."""
    text = json.dumps(run_configs(looks, data_cfg), sort_keys=True)
    return {"format": ONLINE_FORMAT, "seed": int(seed), "batch_size": int(batch_size),
            "uses_per_frame": int(uses_per_frame), "config_sha256": hashlib.sha256(text.encode()).hexdigest()}


def check_state(state: dict, identity: dict) -> int:
    """The step a saved state resumes at; InputError naming the field where it belongs to another run (format,
    seed, batch size, uses per frame or configs differ)."""
    check(isinstance(state, dict) and "step" in state, "start_state", state, "a state yielded by online_batches")
    for key, value in identity.items():
        if state.get(key) != value:  # a ValueError: the verb prints it as one line
            raise InputError(f"resume: the run was trained with {key} = {state.get(key)!r}, this call gives "
                             f"{value!r}: a run resumes only with its own (start a new run with its checkpoint as "
                             "`init` for another)")
    step = state["step"]
    check(isinstance(step, int) and step >= 0, "start_state.step", step, "a non-negative step")
    return step


def online_batches(looks, data_cfg, seed: int, batch_size: int, workers: int, device,
                   uses_per_frame: int = DEFAULT_USES_PER_FRAME, start_state: dict | None = None, make_batch=None,
                   stream: int = 0):
    """Training batches from frames rendered as training goes (the module doc): yields (batch, state) forever.

    looks: a random-mode GenerateConfig (frame f is its dataset's sample f), or a sequence of Looks (a mix of
    configs, random or sequence mode, by weight). data_cfg: the perception DataConfig (input size, crop rule,
    augmentation). seed: the crops' and augmentation's root seed.
    batch_size N, uses_per_frame K in [1, 8], workers renderer processes, device a torch device (name).
    batch: perception/batch_augment.training_batch's dict on the device (the keys of make_sample stacked) plus
    sample_id (N, 2) int64: (frame index, how many crops of that frame came before this one). state: a JSON-able
    dict, {format, seed, batch_size, uses_per_frame, config_sha256, step (the next), next_frame (the first frame
    a resumed run renders), frames_taken (frames handed to the trainer, all sessions), max_uses (the most crops
    of any frame so far), frame_ms (this session's mean cost of a frame in its worker: RenderPool.stage_ms)};
    start_state: such a state, to continue after it. make_batch: the batch of a window
    (batch_augment.training_batch's arguments; None: that one, ENVISAT's corner network's; another target's
    keypoint network: perception/keypoint_batch.keypoint_batch, over the looks' K keypoints). stream: the DDP
    rank (stream_looks, step_seed: each rank its own frames and crops; the state, rank 0's, holds for every rank).
    """
    import torch

    from envisat_pose.perception import batch_augment

    looks = as_looks(looks)
    check(isinstance(batch_size, int) and batch_size >= 1, "batch_size", batch_size, "at least 1")
    check(isinstance(workers, int) and workers >= 1, "workers", workers, "at least 1 renderer process")
    check(isinstance(uses_per_frame, int) and 1 <= uses_per_frame <= MAX_USES_PER_FRAME, "uses_per_frame",
          uses_per_frame, f"an integer in [1, {MAX_USES_PER_FRAME}]")
    n, k = batch_size, uses_per_frame
    identity = run_identity(looks, data_cfg, seed, n, k)
    step = 0 if start_state is None else check_state(start_state, identity)
    max_uses = 0 if start_state is None else int(start_state.get("max_uses", 0))
    device = torch.device(device)
    first = window_start(step, n, k)
    uses = {f: uses_before(f, step, n, k) for f in range(first, first + n)}
    make_batch = batch_augment.training_batch if make_batch is None else make_batch
    with RenderPool(stream_looks(looks, stream), workers, first, device.type) as source:
        pool = DevicePool(n, max_side(looks), device, source.keypoints)
        loaded = first
        while True:
            f0 = window_start(step, n, k)
            pool.load(source, f0 + n - loaded)
            loaded = f0 + n
            frames = torch.arange(f0, f0 + n, dtype=torch.int64)
            gen = torch.Generator().manual_seed(step_seed(seed, step, stream))
            batch = make_batch(pool.frames, pool.corners_px, pool.visible, pool.in_frame, data_cfg, gen,
                               (frames % n).to(device), pool.hw if len(looks) > 1 else None)
            prior = torch.tensor([uses.get(int(f), 0) for f in frames], dtype=torch.int64)
            batch["sample_id"] = torch.stack([frames, prior], dim=1).to(device)
            uses = {int(f): int(u) + 1 for f, u in zip(frames, prior)}  # the frames before f0 left for good
            max_uses = max(max_uses, max(uses.values()))
            if max_uses > k:
                raise RuntimeError(f"a frame was cropped {max_uses} times, more than uses_per_frame = {k}")
            step += 1
            state = dict(identity, step=step, next_frame=window_start(step, n, k), frames_taken=loaded,
                         max_uses=max_uses, frame_ms=source.stage_ms())
            yield batch, state

