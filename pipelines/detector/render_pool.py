"""The renderer processes of online training (pipelines/detector/online.py): each worker renders its frames of the look
mix (pipelines/detector/look_mix.py) into a ring of shared-memory slots, and RenderPool hands them to the trainer in order.

Workers. `workers` spawned processes, each with its own SceneRenderers (one per resolution and texture set
among the looks; its GL from gl_environment: MUJOCO_GL osmesa on a CPU, egl where the device is CUDA, unless set),
worker w rendering frames f = w, w + W, w + 2W, ... into its FrameRing (multiprocessing.shared_memory: image
(H, W) uint8, corners_px (K, 2) float64, visible, in_frame (K,) bool, frame index, side, and what the frame cost
(ms, FRAME_STAGES); K the looks' target's
keypoints, ENVISAT's 8 corners or another target's keypoints_px; every look shows the same target file). The trainer takes frames
in order f = 0, 1, 2, ... (frame f from worker f mod W) and gives the slot back. A slow worker stalls the trainer
rather than reorder anything. Frames of several sizes travel in the slots of the largest, top-left, zeros beyond,
with their side.

A frame f of a random-mode look is sample f of the dataset `envisat generate` would make of it: the factory's
view, appearance and corruption of seed sample_seed(gen_cfg.seed, f // shard_size, f % shard_size) (datagen/factory.py:
sample_view, then the render, then sample_arrays: the space camera applied on the CPU in the renderer process
unless storage is 'clean', the label by labels.make_label). Its pixels and label depend only on (gen_cfg, f):
they equal that dataset's PNG and JSON where the GL rasterizer is the same (llvmpipe here; another driver, an EGL
GPU, may differ by a few pixel levels along edges, and then so do the batches).
"""

from __future__ import annotations

import json
import os
import queue
import signal
import time
import traceback
import warnings
from dataclasses import dataclass

import numpy as np

from envisat_pose.config import check
from envisat_pose.config_errors import TargetFileWarning
from envisat_pose.datagen.factory import sample_arrays, sample_view
from envisat_pose.pipelines.detector.look_mix import (
    WeightedLook,
    as_looks,
    frame_look,
    look_pattern,
    look_sample,
    look_shares,
    max_side,
    renderer_key,
)
from envisat_pose.pools import thread_env, without_main_script
from envisat_pose.target import load_target

SLOTS_PER_WORKER = 4  # frames a worker may render ahead of the trainer
# a renderer process's memory for a default count (pools.default_processes): measured 1.06 GB PSS, 1.13 GB RSS at
# 1024 px (2026-12, `envisat train --online --render-workers 2`), with a margin
RENDERER_BYTES = 1_200_000_000
FRAME_STAGES = ("render_ms", "camera_label_ms")  # a frame's cost in its worker: the view and the GL passes; the
# space camera and the label (RenderPool.stage_ms: their means, beside the trainer's wait for frames)
WAIT_POLL_S = 1.0


def frame_sample(gen_cfg, frame: int) -> tuple[int, int]:
    """(shard index, index in the shard) of frame `frame` in the dataset of gen_cfg (its seed's location)."""
    return frame // gen_cfg.shard_size, frame % gen_cfg.shard_size


def render_frame(renderer, gen_cfg, frame: int, ms: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Sample `frame` of gen_cfg's dataset, (image (H, W) uint8, label dict), nothing encoded; of a sequence-mode
    config, that frame of its sequence. ms: (2,) filled with the wall time of FRAME_STAGES, when given."""

    t0 = time.perf_counter()
    shard, i = frame_sample(gen_cfg, frame)
    _, seed, rng, view, x, scene = sample_view(gen_cfg, shard, i, renderer.fovy_deg, renderer.znear_m,
                                               renderer.target_boxes)
    out = renderer.render(view)
    t1 = time.perf_counter()
    image, label = sample_arrays(renderer.K, renderer.target_boxes, gen_cfg, out, x, scene, rng, seed)
    if ms is not None:
        ms[:] = (1e3 * (t1 - t0), 1e3 * (time.perf_counter() - t1))
    return image, label


@dataclass
class FrameRing:
    """A worker's slots in one shared-memory block: images (n, H, W) uint8 (a smaller frame top-left, zeros
    beyond), corners_px (n, K, 2) float64, flags (n, 2, K) bool (visible, in_frame), frame (n,) int64, side (n,)
    int64 (the frame's own side), ms (n, len(FRAME_STAGES)) float64 (what it cost); K keypoints a frame (8:
    ENVISAT's corners)."""

    shm: object
    images: np.ndarray
    corners_px: np.ndarray
    flags: np.ndarray
    frame: np.ndarray
    side: np.ndarray
    ms: np.ndarray

    @staticmethod
    def nbytes(n: int, res: int, k: int = 8) -> int:
        return n * res * res + n * 2 * k * 8 + n * 16 + n * len(FRAME_STAGES) * 8 + n * 2 * k

    @classmethod
    def view(cls, shm, n: int, res: int, k: int = 8) -> "FrameRing":
        buf, a = shm.buf, 0
        images = np.ndarray((n, res, res), np.uint8, buf, a)
        a += n * res * res
        corners = np.ndarray((n, k, 2), np.float64, buf, a)
        a += n * 2 * k * 8
        frame = np.ndarray((n,), np.int64, buf, a)
        a += n * 8
        side = np.ndarray((n,), np.int64, buf, a)
        a += n * 8
        ms = np.ndarray((n, len(FRAME_STAGES)), np.float64, buf, a)
        a += n * len(FRAME_STAGES) * 8
        flags = np.ndarray((n, 2, k), np.bool_, buf, a)
        return cls(shm, images, corners, flags, frame, side, ms)

    def write(self, slot: int, frame: int, image: np.ndarray, label: dict) -> None:
        h, w = image.shape
        if (h, w) == self.images.shape[1:]:
            self.images[slot] = image
        else:
            self.images[slot, :h, :w] = image
            self.images[slot, h:] = 0
            self.images[slot, :h, w:] = 0
        points = label["keypoints_px"] if "keypoints_px" in label else label["corners_px"]  # another target's names
        self.corners_px[slot] = np.asarray(points, dtype=np.float64)
        self.flags[slot, 0] = np.asarray(label["visible"], dtype=bool)
        self.flags[slot, 1] = np.asarray(label["in_frame"], dtype=bool)
        self.frame[slot] = frame
        self.side[slot] = h


def gl_environment(device_type: str, workers: int) -> dict[str, str]:
    """The renderer processes' environment: MUJOCO_GL (the caller's, else egl for a CUDA device, osmesa
    otherwise), EGL_PLATFORM surfaceless with egl, LP_NUM_THREADS (llvmpipe's threads) the machine's cores shared
    among the workers unless set."""

    env = {"MUJOCO_GL": os.environ.get("MUJOCO_GL", "").strip() or ("egl" if device_type == "cuda" else "osmesa")}
    if env["MUJOCO_GL"].lower() == "egl":
        env["EGL_PLATFORM"] = os.environ.get("EGL_PLATFORM", "surfaceless")
    env.update({name: os.environ.get(name, n) for name, n in thread_env(workers).items()})
    return env


def render_worker(looks_json: str, worker: int, workers: int, first_frame: int, shm_name: str, n_slots: int,
                  res: int, free_q, ready_q, env: dict[str, str], keypoints: int = 8) -> None:
    """A renderer process: frames first_frame' = the first f >= first_frame with f mod workers == worker, then
    every workers-th, each into a slot the trainer gave back (free_q; None ends it), announced on ready_q as
    (slot, frame); an error as ('error', worker, traceback text). looks_json: the looks' records (a JSON list);
    res: the slots' side (the largest look's); keypoints: K, the looks' target's."""
    # SIGINT and SIGTERM are the trainer's to handle (it stops after its step with a checkpoint, then ends the
    # workers): a terminal's Ctrl-C reaches the whole process group and must not kill a renderer first
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    os.environ.update(env)
    warnings.simplefilter("ignore", TargetFileWarning)  # the trainer said its target file's warnings once
    from multiprocessing import shared_memory

    try:
        import cv2

        from envisat_pose.datagen.render import SceneRenderer

        cv2.setNumThreads(1)
        looks = [WeightedLook.from_record(r) for r in json.loads(looks_json)]
        shares = look_shares(looks)
        pattern = look_pattern(shares)
        shm = shared_memory.SharedMemory(name=shm_name)
        ring = FrameRing.view(shm, n_slots, res, keypoints)
        renderers = {}
        f = first_frame + (worker - first_frame) % workers
        while True:
            slot = free_q.get()
            if slot is None:
                break
            j, i = frame_look(f, shares, pattern)
            cfg, k = look_sample(looks[j].generate, i)
            key = renderer_key(cfg)
            if key not in renderers:  # built when a look first needs it
                renderers[key] = SceneRenderer(cfg.resolution_px, cfg.shadows, texture_set_size=key[2],
                                               texture_seed=cfg.appearance.texture_seed, earth_seed=cfg.earth_seed,
                                               target=cfg.target)
            image, label = render_frame(renderers[key], cfg, k, ring.ms[slot])
            ring.write(slot, f, image, label)
            ready_q.put((slot, f))
            f += workers
        for renderer in renderers.values():
            renderer.close()
        del ring
        shm.close()
    except BaseException:  # the trainer raises it
        ready_q.put(("error", worker, traceback.format_exc()))


def looks_keypoints(looks) -> int:
    """K, the keypoints of the looks' one target (ConfigError naming the look whose target file differs)."""
    looks = as_looks(looks)
    first = load_target(looks[0].generate.target)
    for look in looks[1:]:
        check(load_target(look.generate.target).sha256 == first.sha256, f"looks.{look.name}.generate.target",
              look.generate.target, f"the other looks' target ({looks[0].generate.target!r}): one target a run")
    return first.num_keypoints


class RenderPool:
    """Renderer processes and their shared-memory rings; frames handed out in order from first_frame.
    keypoints: K of every frame (looks_keypoints). Use as a context manager (close() ends the processes and frees
    the memory)."""

    def __init__(self, looks, workers: int, first_frame: int, device_type: str = "cpu",
                 slots_per_worker: int = SLOTS_PER_WORKER):
        import multiprocessing
        from multiprocessing import shared_memory

        ctx = multiprocessing.get_context("spawn")  # a clean process: no GL, torch or OpenCV state inherited
        looks = as_looks(looks)
        looks_json = json.dumps([look.record() for look in looks])
        self.workers, self.next_frame, self.res = workers, first_frame, max_side(looks)
        self.ms_sum, self.taken = np.zeros(len(FRAME_STAGES)), 0
        self.keypoints = looks_keypoints(looks)
        self.rings, self.free_qs, self.ready_qs, self.procs = [], [], [], []
        env = gl_environment(device_type, workers)
        try:
            for w in range(workers):
                size = FrameRing.nbytes(slots_per_worker, self.res, self.keypoints)
                shm = shared_memory.SharedMemory(create=True, size=size)
                self.rings.append(FrameRing.view(shm, slots_per_worker, self.res, self.keypoints))
                free_q, ready_q = ctx.Queue(), ctx.Queue()
                for slot in range(slots_per_worker):
                    free_q.put(slot)
                p = ctx.Process(target=render_worker, name=f"envisat-render-{w}", daemon=True,
                                args=(looks_json, w, workers, first_frame, shm.name, slots_per_worker, self.res,
                                      free_q, ready_q, env, self.keypoints))
                with without_main_script():  # a plain script's top level is not run again in the worker
                    p.start()
                self.free_qs.append(free_q)
                self.ready_qs.append(ready_q)
                self.procs.append(p)
        except BaseException:
            self.close()
            raise

    def __enter__(self) -> "RenderPool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def take(self, out_image: np.ndarray) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, int]:
        """The next frame in order, its image copied into out_image (res, res) uint8 (a smaller frame top-left,
        zeros beyond) and its slot given back: (frame, corners_px (K, 2) float64, visible (K,) bool, in_frame
        (K,) bool, its side)."""
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
        label = (ring.corners_px[slot].copy(), ring.flags[slot, 0].copy(), ring.flags[slot, 1].copy(),
                 int(ring.side[slot]))
        self.ms_sum += ring.ms[slot]
        self.taken += 1
        self.free_qs[w].put(slot)
        self.next_frame += 1
        return (frame, *label)

    def stage_ms(self) -> dict[str, float]:
        """The mean cost of the frames taken so far in their workers, ms per FRAME_STAGES stage (NaN before the
        first): with W workers they render at most W x 1000 / (the stages' sum) frames a second."""
        mean = self.ms_sum / self.taken if self.taken else np.full(len(FRAME_STAGES), np.nan)
        return {name: round(float(v), 2) for name, v in zip(FRAME_STAGES, mean)}

    def close(self) -> None:
        """End the workers (they finish the frame at hand) and free the shared memory."""
        for q in self.free_qs:
            q.put(None)
        deadline = time.monotonic() + 10.0
        for p in self.procs:
            p.join(max(0.0, deadline - time.monotonic()))
            if p.is_alive():
                p.kill()  # it ignores SIGTERM (render_worker)
                p.join(2.0)
        for q in self.free_qs + self.ready_qs:
            q.close()
            q.cancel_join_thread()
        for ring in self.rings:
            shm = ring.shm
            ring.images = ring.corners_px = ring.flags = ring.frame = ring.side = None
            shm.close()
            shm.unlink()
        self.rings, self.procs, self.free_qs, self.ready_qs = [], [], [], []
