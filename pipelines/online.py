"""Training on frames as they are rendered: renderer processes hand raw frames and labels to the trainer, which
crops and augments them on its device (perception/batch_augment.py). No PNG, no tar.

Frames. With one GenerateConfig (random mode), frame f is sample f of the dataset `envisat generate` would make
of it: the factory's view, look and corruption of seed sample_seed(gen_cfg.seed, f // shard_size, f % shard_size)
(datagen/factory.py: sample_view, then the render, then sample_arrays: the space camera applied on the CPU in the
renderer process unless storage is 'clean', the label by labels.make_label). Its pixels and label depend only on
(gen_cfg, f): they equal that dataset's PNG and JSON where the GL rasterizer is the same (llvmpipe here; another
driver, an EGL GPU, may differ by a few pixel levels along edges, and then so do the batches).

A mix of looks (WeightedLook: a name, a weight and a GenerateConfig each; resolutions, cameras, scenarios may differ).
The weights are rounded to whole shares of LOOK_PERIOD frames (each look at least one), and the frames of a
period are dealt out evenly (look_pattern): frame f = c LOOK_PERIOD + p is sample i = c n_j + r_p of look j =
pattern[p], r_p the count of look j's entries before p. A random-mode look's sample i is its dataset's sample i,
as above; a sequence-mode look's is frame i mod L of its sequence q = i // L (L = its num_images), the sequence
of the look's config with seed sequence_seed(seed, q): fresh sequences as the run goes, each rendered in order of
its frames. Frames of several sizes travel in the slots of the largest, top-left, zeros beyond, with their side.

Workers. `workers` spawned processes, each with its own SceneRenderers (one per resolution and texture set
among the looks; MUJOCO_GL: osmesa on a CPU, egl where the device is CUDA, unless set), worker w rendering frames
f = w, w + W, w + 2W, ... into its ring of shared-memory slots (multiprocessing.shared_memory: image (H, W)
uint8, corners_px (8, 2) float64, visible, in_frame (8,) bool, frame index, side). The trainer takes frames in
order f = 0, 1, 2, ... (frame f from worker f mod W), copies each into its device pool (through pinned host
buffers on CUDA) and gives the slot back. A slow worker stalls the trainer
rather than reorder anything.

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
LOOK_PERIOD = 100  # a mix of looks repeats its order every LOOK_PERIOD frames: the weights in whole percent
SEQUENCE_KEY = 0x5E0  # a sequence look's q-th sequence: seed SeedSequence([seed, SEQUENCE_KEY, q])
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


def run_identity(looks, data_cfg, seed: int, batch_size: int, uses_per_frame: int) -> dict:
    """What a state must match to resume a run: seed, N, K and the sha256 of the configs (a GenerateConfig, or
    the looks with their shares of the period)."""
    looks = as_looks(looks)
    if len(looks) == 1:  # one look: its config alone (the record of runs made before mixes)
        source = {"generate": to_dict(looks[0].generate)}
    else:
        source = {"looks": [dict(look.record(), share=int(n)) for look, n in zip(looks, look_shares(looks))]}
    text = json.dumps(dict(source, data=data_cfg.to_dict()), sort_keys=True)
    return {"format": ONLINE_FORMAT, "seed": int(seed), "batch_size": int(batch_size),
            "uses_per_frame": int(uses_per_frame), "config_sha256": hashlib.sha256(text.encode()).hexdigest()}


# ---------------------------------------------------------------------------------------------------------
# The looks


@dataclass(frozen=True)
class WeightedLook:
    """One kind of frame in an online run: name, generate (a GenerateConfig, random or sequence mode: its
    resolution, looks, camera, scenario) and weight (its share of the frames, relative to the other looks')."""

    name: str
    generate: object
    weight: float = 1.0

    def __post_init__(self) -> None:
        mode = getattr(self.generate, "mode", None)
        check(mode in ("random", "sequence"), f"looks.{self.name}.mode", mode, "'random' or 'sequence'")
        check(isinstance(self.weight, (int, float)) and np.isfinite(self.weight) and self.weight > 0,
              f"looks.{self.name}.weight", self.weight, "a positive number")

    def record(self) -> dict:
        return {"name": self.name, "weight": float(self.weight), "generate": to_dict(self.generate)}

    @classmethod
    def from_record(cls, record: dict, where: str = "looks") -> "WeightedLook":
        """A look from its record ({name, weight, generate} as record() writes it; ConfigError naming the field)."""
        from envisat_pose.config import from_dict
        from envisat_pose.datagen.generate_config import GenerateConfig

        check(isinstance(record, dict) and isinstance(record.get("name"), str), f"{where}.name",
              record.get("name") if isinstance(record, dict) else record, "a look's name (a string)")
        name = record["name"]
        return cls(name, from_dict(GenerateConfig, record.get("generate", {}), f"{where}.{name}.generate"),
                   record.get("weight", 1.0))


def read_looks(path: str) -> tuple[WeightedLook, ...]:
    """The looks of a TOML file: each [[look]] table a name, a weight and the keys of `envisat generate
    --config` (mode 'random' unless given); keys outside the [[look]] tables are every look's defaults (a look's
    own win). InputError or ConfigError naming the file's field."""
    from envisat_pose.config import flatten, load_toml, resolve_job_config
    from envisat_pose.datagen.generate_config import GenerateConfig

    data = load_toml(path)
    entries = data.pop("look", None)
    check(isinstance(entries, list) and len(entries) >= 1 and all(isinstance(e, dict) for e in entries), "look",
          entries, f"one or more [[look]] tables in {path}")
    looks = []
    for n, entry in enumerate(entries):
        entry = dict(entry)
        name = entry.pop("name", None)
        check(isinstance(name, str) and name != "", f"look[{n}].name", name, "a look's name (a string)")
        weight = entry.pop("weight", 1.0)
        # the file's shared keys under the look's own (its tables key by key)
        cfg = resolve_job_config(GenerateConfig, {"mode": "random", **data}, None, flatten(entry),
                                 prefix=f"look.{name}")
        looks.append(WeightedLook(name, cfg, weight))
    return as_looks(looks)


def looks_toml(looks) -> str:
    """The looks as read_looks reads them back (each look's whole config)."""
    from envisat_pose.config import to_toml

    return "".join("[[look]]\n" + to_toml(dict(name=look.name, weight=float(look.weight),
                                                **to_dict(look.generate)), prefix="look.") + "\n"
                   for look in as_looks(looks))


def as_looks(looks) -> tuple[WeightedLook, ...]:
    """A GenerateConfig (one look, 'default') or a sequence of Looks, as a tuple of Looks with distinct names."""
    if hasattr(looks, "mode"):
        return (WeightedLook("default", looks),)
    looks = tuple(looks)
    check(1 <= len(looks) <= LOOK_PERIOD, "looks", len(looks), f"1 to {LOOK_PERIOD} looks")
    names = [look.name for look in looks]
    check(len(set(names)) == len(names), "looks", names, "looks with distinct names")
    return looks


def look_shares(looks) -> np.ndarray:
    """Each look's frames in a period of LOOK_PERIOD (int64, sum LOOK_PERIOD, each at least 1): the weights'
    shares rounded by largest remainder."""
    w = np.array([look.weight for look in as_looks(looks)], dtype=np.float64)
    exact = w / w.sum() * LOOK_PERIOD
    n = np.maximum(np.floor(exact).astype(np.int64), 1)
    while n.sum() < LOOK_PERIOD:
        n[np.argmax(exact - n)] += 1
    while n.sum() > LOOK_PERIOD:
        n[np.argmax(np.where(n > 1, n - exact, -np.inf))] -= 1
    return n


def look_pattern(shares: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The order of a period: (look (LOOK_PERIOD,) int64, rank (LOOK_PERIOD,) int64), look j's r-th entry placed
    at (r + 1/2) / n_j of the period (ties by look), so that every look is spread evenly over it."""
    entries = sorted(((r + 0.5) / n, j, r) for j, n in enumerate(shares) for r in range(int(n)))
    return (np.array([j for _, j, _ in entries], dtype=np.int64), np.array([r for _, _, r in entries],
                                                                         dtype=np.int64))


def frame_look(frame: int, shares: np.ndarray, pattern: tuple[np.ndarray, np.ndarray]) -> tuple[int, int]:
    """(look j, its sample i) of frame `frame` of the mix (the module doc)."""
    c, p = divmod(int(frame), LOOK_PERIOD)
    j = int(pattern[0][p])
    return j, c * int(shares[j]) + int(pattern[1][p])


def sequence_seed(seed: int, q: int) -> int:
    """The seed of a sequence look's q-th sequence."""
    return int(np.random.SeedSequence([seed, SEQUENCE_KEY, q]).generate_state(1, dtype=np.uint32)[0])


def max_side(looks) -> int:
    """The largest frame side among the looks (the slots' side)."""
    return max(look.generate.resolution_px for look in as_looks(looks))


def renderer_key(gen_cfg) -> tuple:
    """What a SceneRenderer is built from: (side, shadows, texture set size, texture seed, Earth seed)."""
    return (gen_cfg.resolution_px, gen_cfg.shadows,
            gen_cfg.appearance.texture_set_size if gen_cfg.appearance_on else 0, gen_cfg.appearance.texture_seed,
            gen_cfg.earth_seed)


# ---------------------------------------------------------------------------------------------------------
# Rendering one frame (in a worker)


def frame_sample(gen_cfg, frame: int) -> tuple[int, int]:
    """(shard index, index in the shard) of frame `frame` in the dataset of gen_cfg (its seed's location)."""
    return frame // gen_cfg.shard_size, frame % gen_cfg.shard_size


def look_sample(gen_cfg, i: int) -> tuple:
    """(config, index) of a look's sample i: a random-mode look's dataset sample i; a sequence-mode look's frame
    i mod L of its sequence i // L (the look's config with that sequence's seed)."""
    if gen_cfg.mode == "random":
        return gen_cfg, i
    from dataclasses import replace

    q, k = divmod(i, gen_cfg.num_images)
    return replace(gen_cfg, seed=sequence_seed(gen_cfg.seed, q)), k


def render_frame(renderer, gen_cfg, frame: int) -> tuple[np.ndarray, dict]:
    """Sample `frame` of gen_cfg's dataset, (image (H, W) uint8, label dict), nothing encoded; of a sequence-mode
    config, that frame of its sequence."""
    from envisat_pose.datagen.factory import sample_arrays, sample_view

    shard, i = frame_sample(gen_cfg, frame)
    _, seed, rng, view, x, scene = sample_view(gen_cfg, shard, i, renderer.fovy_deg, renderer.znear_m,
                                               renderer.target_boxes)
    out = renderer.render(view)
    return sample_arrays(renderer.K, renderer.target_boxes, gen_cfg, out, x, scene, rng, seed)


@dataclass
class FrameRing:
    """A worker's slots in one shared-memory block: images (n, H, W) uint8 (a smaller frame top-left, zeros
    beyond), corners_px (n, 8, 2) float64, flags (n, 2, 8) bool (visible, in_frame), frame (n,) int64, side (n,)
    int64 (the frame's own side)."""

    shm: object
    images: np.ndarray
    corners_px: np.ndarray
    flags: np.ndarray
    frame: np.ndarray
    side: np.ndarray

    @staticmethod
    def nbytes(n: int, res: int) -> int:
        return n * res * res + n * 16 * 8 + n * 16 + n * 8 * 2

    @classmethod
    def view(cls, shm, n: int, res: int) -> "FrameRing":
        buf, a = shm.buf, 0
        images = np.ndarray((n, res, res), np.uint8, buf, a)
        a += n * res * res
        corners = np.ndarray((n, 8, 2), np.float64, buf, a)
        a += n * 16 * 8
        frame = np.ndarray((n,), np.int64, buf, a)
        a += n * 8
        side = np.ndarray((n,), np.int64, buf, a)
        a += n * 8
        flags = np.ndarray((n, 2, 8), np.bool_, buf, a)
        return cls(shm, images, corners, flags, frame, side)

    def write(self, slot: int, frame: int, image: np.ndarray, label: dict) -> None:
        h, w = image.shape
        if (h, w) == self.images.shape[1:]:
            self.images[slot] = image
        else:
            self.images[slot, :h, :w] = image
            self.images[slot, h:] = 0
            self.images[slot, :h, w:] = 0
        self.corners_px[slot] = np.asarray(label["corners_px"], dtype=np.float64)
        self.flags[slot, 0] = np.asarray(label["visible"], dtype=bool)
        self.flags[slot, 1] = np.asarray(label["in_frame"], dtype=bool)
        self.frame[slot] = frame
        self.side[slot] = h


def gl_environment(device_type: str, workers: int) -> dict[str, str]:
    """The renderer processes' environment: MUJOCO_GL (the caller's, else egl for a CUDA device, osmesa
    otherwise), EGL_PLATFORM surfaceless with egl, LP_NUM_THREADS (llvmpipe's threads) the machine's cores shared
    among the workers unless set."""
    from envisat_pose.runner import thread_env

    env = {"MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl" if device_type == "cuda" else "osmesa")}
    if env["MUJOCO_GL"].lower() == "egl":
        env["EGL_PLATFORM"] = os.environ.get("EGL_PLATFORM", "surfaceless")
    env.update({name: os.environ.get(name, n) for name, n in thread_env(workers).items()})
    return env


def render_worker(looks_json: str, worker: int, workers: int, first_frame: int, shm_name: str, n_slots: int,
                  res: int, free_q, ready_q, env: dict[str, str]) -> None:
    """A renderer process: frames first_frame' = the first f >= first_frame with f mod workers == worker, then
    every workers-th, each into a slot the trainer gave back (free_q; None ends it), announced on ready_q as
    (slot, frame); an error as ('error', worker, traceback text). looks_json: the looks' records (a JSON list);
    res: the slots' side (the largest look's)."""
    os.environ.update(env)
    from multiprocessing import shared_memory

    try:
        import cv2

        from envisat_pose.datagen.render import SceneRenderer

        cv2.setNumThreads(1)
        looks = [WeightedLook.from_record(r) for r in json.loads(looks_json)]
        shares = look_shares(looks)
        pattern = look_pattern(shares)
        shm = shared_memory.SharedMemory(name=shm_name)
        ring = FrameRing.view(shm, n_slots, res)
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
                                               texture_seed=cfg.appearance.texture_seed, earth_seed=cfg.earth_seed)
            image, label = render_frame(renderers[key], cfg, k)
            ring.write(slot, f, image, label)
            ready_q.put((slot, f))
            f += workers
        for renderer in renderers.values():
            renderer.close()
        del ring
        shm.close()
    except BaseException:  # the trainer raises it
        ready_q.put(("error", worker, traceback.format_exc()))


# ---------------------------------------------------------------------------------------------------------
# The trainer's side


class RenderPool:
    """Renderer processes and their shared-memory rings; frames handed out in order from first_frame.
    Use as a context manager (close() ends the processes and frees the memory)."""

    def __init__(self, looks, workers: int, first_frame: int, device_type: str = "cpu",
                 slots_per_worker: int = SLOTS_PER_WORKER):
        import multiprocessing
        from multiprocessing import shared_memory

        ctx = multiprocessing.get_context("spawn")  # a clean process: no GL, torch or OpenCV state inherited
        looks = as_looks(looks)
        looks_json = json.dumps([look.record() for look in looks])
        self.workers, self.next_frame, self.res = workers, first_frame, max_side(looks)
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
                                args=(looks_json, w, workers, first_frame, shm.name, slots_per_worker, self.res,
                                      free_q, ready_q, env))
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
        zeros beyond) and its slot given back: (frame, corners_px (8, 2) float64, visible (8,) bool, in_frame
        (8,) bool, its side)."""
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
            ring.images = ring.corners_px = ring.flags = ring.frame = ring.side = None
            shm.close()
            shm.unlink()
        self.rings, self.procs, self.free_qs, self.ready_qs = [], [], [], []


class DevicePool:
    """The window's frames on the device, frame f in slot f mod N: frames (N, H, W) uint8, corners_px (N, 8, 2)
    float64, visible and in_frame (N, 8) bool, frame (N,) int64, hw (N, 2) int64 (each frame's own size). New
    frames go through a pinned host buffer on CUDA (copied without waiting for the device; two buffers in turn,
    each reused after its copy is done)."""

    def __init__(self, n: int, res: int, device):
        import torch

        self.n, self.device = n, device
        self.frames = torch.zeros((n, res, res), dtype=torch.uint8, device=device)
        self.corners_px = torch.zeros((n, 8, 2), dtype=torch.float64, device=device)
        self.visible = torch.zeros((n, 8), dtype=torch.bool, device=device)
        self.in_frame = torch.zeros((n, 8), dtype=torch.bool, device=device)
        self.frame = torch.full((n,), -1, dtype=torch.int64, device=device)
        self.hw = torch.full((n, 2), res, dtype=torch.int64, device=device)
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
                "visible": t((n, 8), torch.bool), "in_frame": t((n, 8), torch.bool), "frame": t((n,), torch.int64),
                "hw": t((n, 2), torch.int64)}

    def load(self, source: RenderPool, count: int) -> None:
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
            frame, corners, visible, in_frame, side = source.take(images[i])
            host["corners_px"][i] = torch.from_numpy(corners)
            host["visible"][i] = torch.from_numpy(visible)
            host["in_frame"][i] = torch.from_numpy(in_frame)
            host["frame"][i] = frame
            host["hw"][i] = side
        slots = (host["frame"][:count] % self.n).to(self.device)
        blocking = self.device.type != "cuda"
        for name in ("frames", "corners_px", "visible", "in_frame", "frame", "hw"):
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


def online_batches(looks, data_cfg, seed: int, batch_size: int, workers: int, device,
                   uses_per_frame: int = DEFAULT_USES_PER_FRAME, start_state: dict | None = None):
    """Training batches from frames rendered as training goes (the module doc): yields (batch, state) forever.

    looks: a random-mode GenerateConfig (frame f is its dataset's sample f), or a sequence of Looks (a mix of
    configs, random or sequence mode, by weight). data_cfg: the perception DataConfig (input size, crop rule,
    augmentation). seed: the crops' and augmentation's root seed.
    batch_size N, uses_per_frame K in [1, 8], workers renderer processes, device a torch device (name).
    batch: perception/batch_augment.training_batch's dict on the device (the keys of make_sample stacked) plus
    sample_id (N, 2) int64: (frame index, how many crops of that frame came before this one). state: a JSON-able
    dict, {format, seed, batch_size, uses_per_frame, config_sha256, step (the next), next_frame (the first frame
    a resumed run renders), frames_taken (frames handed to the trainer, all sessions), max_uses (the most crops
    of any frame so far)}; start_state: such a state, to continue after it.
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
    pool = DevicePool(n, max_side(looks), device)
    with RenderPool(looks, workers, first, device.type) as source:
        loaded = first
        while True:
            f0 = window_start(step, n, k)
            pool.load(source, f0 + n - loaded)
            loaded = f0 + n
            frames = torch.arange(f0, f0 + n, dtype=torch.int64)
            gen = torch.Generator().manual_seed(step_seed(seed, step))
            batch = batch_augment.training_batch(pool.frames, pool.corners_px, pool.visible, pool.in_frame,
                                                 data_cfg, gen, (frames % n).to(device),
                                                 pool.hw if len(looks) > 1 else None)
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

