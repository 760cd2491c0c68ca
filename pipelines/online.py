"""Training on frames as they are rendered: renderer processes hand raw frames and labels to the trainer, which
crops and augments them on its device (perception/batch_augment.py). No PNG, no tar.

Frames. Frame f is sample f of the dataset `envisat generate` would make of the same GenerateConfig (random mode):
the factory's view, look and corruption of seed sample_seed(gen_cfg.seed, f // shard_size, f % shard_size)
(datagen/factory.py: sample_view, then the render, then sample_arrays: the space camera applied on the CPU in the
renderer process unless storage is 'clean', the label by labels.make_label). Its pixels and label depend only on
(gen_cfg, f): they equal that dataset's PNG and JSON where the GL rasterizer is the same (llvmpipe here; another
driver, an EGL GPU, may differ by a few pixel levels along edges, and then so do the batches).

Workers. `workers` spawned processes, each with its own SceneRenderer (MUJOCO_GL: osmesa on a CPU, egl where the
device is CUDA, unless set), worker w rendering frames f = w, w + W, w + 2W, ... into its ring of shared-memory
slots (multiprocessing.shared_memory: image (H, W) uint8, corners_px (8, 2) float64, visible, in_frame (8,) bool,
frame index). The trainer takes frames in order f = 0, 1, 2, ... (frame f from worker f mod W), copies each into
its device pool (through pinned host buffers on CUDA) and gives the slot back. A slow worker stalls the trainer
rather than reorder anything.

Schedule (K uses per frame, N samples per batch). Step s trains on the window of N consecutive frames
[floor(s N / K), floor(s N / K) + N), one crop of each: the window moves by N / K frames a step, so every frame is
cropped in at most K steps (exactly K once the run is past its first window), each time with its own placement,
scale and augmentation. Step s's crops, augmentation and line segments come from a generator seeded by
(seed, step): a batch is a function of (gen_cfg, data_cfg, seed, N, K, step) alone, whatever the worker count.

State (yielded after each step, JSON-able): the step to run next, the window's first frame (the first frame a
resumed run renders), the frames taken so far, the most uses any frame has had, and the run's identity (seed,
batch size, K, the configs' sha256); `online_batches(..., start_state=state)` continues with the next step, and
frames that left the window are never rendered again.
"""

from __future__ import annotations

import hashlib
import json
import os
import queue
import time
import traceback
from dataclasses import dataclass

import numpy as np

from envisat_pose.config import check, to_dict

ONLINE_FORMAT = "envisat-pose online v1"
DEFAULT_USES_PER_FRAME = 8
MAX_USES_PER_FRAME = 8  # the cap: no frame cropped more than 8 times
SLOTS_PER_WORKER = 4  # frames a worker may render ahead of the trainer
STEP_KEY = 0x0A1E  # a step's generator: SeedSequence([seed, STEP_KEY, step])
WAIT_POLL_S = 1.0


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


def step_seed(seed: int, step: int) -> int:
    """The seed of step `step`'s torch.Generator (crops, augmentation, segments)."""
    return int(np.random.SeedSequence([seed, STEP_KEY, step]).generate_state(1, dtype=np.uint64)[0] >> 1)


def run_identity(gen_cfg, data_cfg, seed: int, batch_size: int, uses_per_frame: int) -> dict:
    """What a state must match to resume a run: seed, N, K and the sha256 of both configs."""
    text = json.dumps({"generate": to_dict(gen_cfg), "data": data_cfg.to_dict()}, sort_keys=True)
    return {"format": ONLINE_FORMAT, "seed": int(seed), "batch_size": int(batch_size),
            "uses_per_frame": int(uses_per_frame), "config_sha256": hashlib.sha256(text.encode()).hexdigest()}


# ---------------------------------------------------------------------------------------------------------
# Rendering one frame (in a worker)


def frame_sample(gen_cfg, frame: int) -> tuple[int, int]:
    """(shard index, index in the shard) of frame `frame` in the dataset of gen_cfg (its seed's location)."""
    return frame // gen_cfg.shard_size, frame % gen_cfg.shard_size


def render_frame(renderer, gen_cfg, frame: int) -> tuple[np.ndarray, dict]:
    """Frame `frame`: the factory's sample of that index, (image (H, W) uint8, label dict), nothing encoded."""
    from envisat_pose.datagen.factory import sample_arrays, sample_view

    shard, i = frame_sample(gen_cfg, frame)
    _, seed, rng, view, x, scene = sample_view(gen_cfg, shard, i, renderer.fovy_deg, renderer.znear_m,
                                               renderer.target_boxes)
    out = renderer.render(view)
    return sample_arrays(renderer.K, renderer.target_boxes, gen_cfg, out, x, scene, rng, seed)


@dataclass
class FrameRing:
    """A worker's slots in one shared-memory block: images (n, H, W) uint8, corners_px (n, 8, 2) float64,
    flags (n, 2, 8) bool (visible, in_frame), frame (n,) int64."""

    shm: object
    images: np.ndarray
    corners_px: np.ndarray
    flags: np.ndarray
    frame: np.ndarray

    @staticmethod
    def nbytes(n: int, res: int) -> int:
        return n * res * res + n * 16 * 8 + n * 16 + n * 8

    @classmethod
    def view(cls, shm, n: int, res: int) -> "FrameRing":
        buf, a = shm.buf, 0
        images = np.ndarray((n, res, res), np.uint8, buf, a)
        a += n * res * res
        corners = np.ndarray((n, 8, 2), np.float64, buf, a)
        a += n * 16 * 8
        frame = np.ndarray((n,), np.int64, buf, a)
        a += n * 8
        flags = np.ndarray((n, 2, 8), np.bool_, buf, a)
        return cls(shm, images, corners, flags, frame)

    def write(self, slot: int, frame: int, image: np.ndarray, label: dict) -> None:
        self.images[slot] = image
        self.corners_px[slot] = np.asarray(label["corners_px"], dtype=np.float64)
        self.flags[slot, 0] = np.asarray(label["visible"], dtype=bool)
        self.flags[slot, 1] = np.asarray(label["in_frame"], dtype=bool)
        self.frame[slot] = frame


def gl_environment(device_type: str, workers: int) -> dict[str, str]:
    """The renderer processes' environment: MUJOCO_GL (the caller's, else egl for a CUDA device, osmesa
    otherwise), EGL_PLATFORM surfaceless with egl, LP_NUM_THREADS (llvmpipe's threads) the machine's cores shared
    among the workers unless set."""
    from envisat_pose.runner import cpu_share

    env = {"MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl" if device_type == "cuda" else "osmesa")}
    if env["MUJOCO_GL"].lower() == "egl":
        env["EGL_PLATFORM"] = os.environ.get("EGL_PLATFORM", "surfaceless")
    env["LP_NUM_THREADS"] = os.environ.get("LP_NUM_THREADS", str(cpu_share(workers)))
    return env


def render_worker(cfg_json: str, worker: int, workers: int, first_frame: int, shm_name: str, n_slots: int,
                  free_q, ready_q, env: dict[str, str]) -> None:
    """A renderer process: frames first_frame' = the first f >= first_frame with f mod workers == worker, then
    every workers-th, each into a slot the trainer gave back (free_q; None ends it), announced on ready_q as
    (slot, frame); an error as ('error', worker, traceback text)."""
    os.environ.update(env)
    from multiprocessing import shared_memory

    try:
        import cv2

        from envisat_pose.datagen.generate_config import config_from_json
        from envisat_pose.datagen.render import SceneRenderer

        cv2.setNumThreads(1)
        cfg = config_from_json(cfg_json)
        shm = shared_memory.SharedMemory(name=shm_name)
        ring = FrameRing.view(shm, n_slots, cfg.resolution_px)
        renderer = SceneRenderer(cfg.resolution_px, cfg.shadows,
                                 texture_set_size=cfg.appearance.texture_set_size if cfg.appearance_on else 0,
                                 texture_seed=cfg.appearance.texture_seed, earth_seed=cfg.earth_seed)
        f = first_frame + (worker - first_frame) % workers
        while True:
            slot = free_q.get()
            if slot is None:
                break
            image, label = render_frame(renderer, cfg, f)
            ring.write(slot, f, image, label)
            ready_q.put((slot, f))
            f += workers
        renderer.close()
        del ring
        shm.close()
    except BaseException:  # the trainer raises it
        ready_q.put(("error", worker, traceback.format_exc()))


# ---------------------------------------------------------------------------------------------------------
# The trainer's side


class FrameSource:
    """Renderer processes and their shared-memory rings; frames handed out in order from first_frame.
    Use as a context manager (close() ends the processes and frees the memory)."""

    def __init__(self, gen_cfg, workers: int, first_frame: int, device_type: str = "cpu",
                 slots_per_worker: int = SLOTS_PER_WORKER):
        import multiprocessing
        from multiprocessing import shared_memory

        from envisat_pose.datagen.generate_config import config_json

        ctx = multiprocessing.get_context("spawn")  # a clean process: no GL, torch or OpenCV state inherited
        self.workers, self.next_frame, self.res = workers, first_frame, gen_cfg.resolution_px
        self.rings, self.free_qs, self.ready_qs, self.procs = [], [], [], []
        env = gl_environment(device_type, workers)
        try:
            for w in range(workers):
                shm = shared_memory.SharedMemory(create=True, size=FrameRing.nbytes(slots_per_worker, self.res))
                self.rings.append(FrameRing.view(shm, slots_per_worker, self.res))
                free_q, ready_q = ctx.Queue(), ctx.Queue()
                for slot in range(slots_per_worker):
                    free_q.put(slot)
                p = ctx.Process(target=render_worker, name=f"envisat-render-{w}", daemon=True,
                                args=(config_json(gen_cfg), w, workers, first_frame, shm.name, slots_per_worker,
                                      free_q, ready_q, env))
                p.start()
                self.free_qs.append(free_q)
                self.ready_qs.append(ready_q)
                self.procs.append(p)
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> "FrameSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def take(self, out_image: np.ndarray) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
        """The next frame in order, its image copied into out_image (H, W) uint8 and its slot given back:
        (frame, corners_px (8, 2) float64, visible (8,) bool, in_frame (8,) bool)."""
        w = self.next_frame % self.workers
        while True:
            try:
                msg = self.ready_qs[w].get(timeout=WAIT_POLL_S)
                break
            except queue.Empty:
                if not self.procs[w].is_alive():
                    raise RuntimeError(f"renderer worker {w} ended (exit code {self.procs[w].exitcode}) before "
                                       f"frame {self.next_frame}") from None
        if msg[0] == "error":
            raise RuntimeError(f"renderer worker {msg[1]} failed:\n{msg[2]}")
        slot, frame = msg
        if frame != self.next_frame:
            raise RuntimeError(f"renderer worker {w} sent frame {frame}, expected {self.next_frame}")
        ring = self.rings[w]
        out_image[...] = ring.images[slot]
        label = ring.corners_px[slot].copy(), ring.flags[slot, 0].copy(), ring.flags[slot, 1].copy()
        self.free_qs[w].put(slot)
        self.next_frame += 1
        return (frame, *label)

    def close(self) -> None:
        """End the workers (they finish the frame at hand) and free the shared memory."""
        for q in self.free_qs:
            q.put(None)
        deadline = time.monotonic() + 10.0
        for p in self.procs:
            p.join(max(0.0, deadline - time.monotonic()))
            if p.is_alive():
                p.terminate()
                p.join(2.0)
        for q in self.free_qs + self.ready_qs:
            q.close()
            q.cancel_join_thread()
        for ring in self.rings:
            shm = ring.shm
            ring.images = ring.corners_px = ring.flags = ring.frame = None
            shm.close()
            shm.unlink()
        self.rings, self.procs, self.free_qs, self.ready_qs = [], [], [], []


class DevicePool:
    """The window's frames on the device, frame f in slot f mod N: frames (N, H, W) uint8, corners_px (N, 8, 2)
    float64, visible and in_frame (N, 8) bool, frame (N,) int64. New frames go through a pinned host buffer on
    CUDA (copied without waiting for the device; two buffers in turn, each reused after its copy is done)."""

    def __init__(self, n: int, res: int, device):
        import torch

        self.n, self.device = n, device
        self.frames = torch.zeros((n, res, res), dtype=torch.uint8, device=device)
        self.corners_px = torch.zeros((n, 8, 2), dtype=torch.float64, device=device)
        self.visible = torch.zeros((n, 8), dtype=torch.bool, device=device)
        self.in_frame = torch.zeros((n, 8), dtype=torch.bool, device=device)
        self.frame = torch.full((n,), -1, dtype=torch.int64, device=device)
        cuda = device.type == "cuda"
        self.staging = [self._host(n, res, cuda) for _ in range(2 if cuda else 1)]
        self.events = [None] * len(self.staging)
        self.turn = 0

    @staticmethod
    def _host(n: int, res: int, pinned: bool) -> dict:
        import torch

        def t(shape, dtype):
            return torch.zeros(shape, dtype=dtype, pin_memory=pinned)

        return {"frames": t((n, res, res), torch.uint8), "corners_px": t((n, 8, 2), torch.float64),
                "visible": t((n, 8), torch.bool), "in_frame": t((n, 8), torch.bool), "frame": t((n,), torch.int64)}

    def load(self, source: FrameSource, count: int) -> None:
        """Take the next `count` frames from source into their slots."""
        import torch

        if count <= 0:
            return
        k = self.turn
        self.turn = (self.turn + 1) % len(self.staging)
        if self.events[k] is not None:
            self.events[k].synchronize()  # the buffer's last copy is done
        host = self.staging[k]
        images = host["frames"].numpy()
        for i in range(count):
            frame, corners, visible, in_frame = source.take(images[i])
            host["corners_px"][i] = torch.from_numpy(corners)
            host["visible"][i] = torch.from_numpy(visible)
            host["in_frame"][i] = torch.from_numpy(in_frame)
            host["frame"][i] = frame
        slots = (host["frame"][:count] % self.n).to(self.device)
        blocking = self.device.type != "cuda"
        for name in ("frames", "corners_px", "visible", "in_frame", "frame"):
            getattr(self, name).index_copy_(0, slots, host[name][:count].to(self.device, non_blocking=not blocking))
        if not blocking:
            self.events[k] = torch.cuda.Event()
            self.events[k].record()


def check_state(state: dict, identity: dict) -> int:
    """The step a saved state resumes at; ConfigError where it belongs to another run (format, seed, batch size,
    uses per frame or configs differ)."""
    check(isinstance(state, dict) and "step" in state, "start_state", state, "a state yielded by online_batches")
    for key, value in identity.items():
        check(state.get(key) == value, f"start_state.{key}", state.get(key),
              f"{value!r}, this run's (a state resumes only the run that wrote it)")
    step = state["step"]
    check(isinstance(step, int) and step >= 0, "start_state.step", step, "a non-negative step")
    return step


def online_batches(gen_cfg, data_cfg, seed: int, batch_size: int, workers: int, device,
                   uses_per_frame: int = DEFAULT_USES_PER_FRAME, start_state: dict | None = None):
    """Training batches from frames rendered as training goes (the module doc): yields (batch, state) forever.

    gen_cfg: a random-mode GenerateConfig (the looks; frame f is its dataset's sample f). data_cfg: the
    perception DataConfig (input size, crop rule, augmentation). seed: the crops' and augmentation's root seed.
    batch_size N, uses_per_frame K in [1, 8], workers renderer processes, device a torch device (name).
    batch: perception/batch_augment.training_batch's dict on the device (the keys of make_sample stacked) plus
    sample_id (N, 2) int64: (frame index, how many crops of that frame came before this one). state: a JSON-able
    dict, {format, seed, batch_size, uses_per_frame, config_sha256, step (the next), next_frame (the first frame
    a resumed run renders), frames_taken (frames handed to the trainer, all sessions), max_uses (the most crops
    of any frame so far)}; start_state: such a state, to continue after it.
    """
    import torch

    from envisat_pose.perception import batch_augment

    check(gen_cfg.mode == "random", "mode", gen_cfg.mode, "'random' (online training renders random views)")
    check(isinstance(batch_size, int) and batch_size >= 1, "batch_size", batch_size, "at least 1")
    check(isinstance(workers, int) and workers >= 1, "workers", workers, "at least 1 renderer process")
    check(isinstance(uses_per_frame, int) and 1 <= uses_per_frame <= MAX_USES_PER_FRAME, "uses_per_frame",
          uses_per_frame, f"an integer in [1, {MAX_USES_PER_FRAME}]")
    n, k = batch_size, uses_per_frame
    identity = run_identity(gen_cfg, data_cfg, seed, n, k)
    step = 0 if start_state is None else check_state(start_state, identity)
    max_uses = 0 if start_state is None else int(start_state.get("max_uses", 0))
    device = torch.device(device)
    first = window_start(step, n, k)
    uses = {f: uses_before(f, step, n, k) for f in range(first, first + n)}
    pool = DevicePool(n, gen_cfg.resolution_px, device)
    with FrameSource(gen_cfg, workers, first, device.type) as source:
        loaded = first
        while True:
            f0 = window_start(step, n, k)
            pool.load(source, f0 + n - loaded)
            loaded = f0 + n
            frames = torch.arange(f0, f0 + n, dtype=torch.int64)
            gen = torch.Generator().manual_seed(step_seed(seed, step))
            batch = batch_augment.training_batch(pool.frames, pool.corners_px, pool.visible, pool.in_frame,
                                                 data_cfg, gen, (frames % n).to(device))
            prior = torch.tensor([uses.get(int(f), 0) for f in frames], dtype=torch.int64)
            batch["sample_id"] = torch.stack([frames, prior], dim=1).to(device)
            uses = {int(f): int(u) + 1 for f, u in zip(frames, prior)}  # the frames before f0 left for good
            max_uses = max(max_uses, max(uses.values()))
            if max_uses > k:
                raise RuntimeError(f"a frame was cropped {max_uses} times, more than uses_per_frame = {k}")
            step += 1
            state = dict(identity, step=step, next_frame=window_start(step, n, k), frames_taken=loaded,
                         max_uses=max_uses)
            yield batch, state

