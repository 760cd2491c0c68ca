"""The image factory: one validated config, one root seed, shards of rendered, labelled, corrupted images.

A shard is the unit of work: `generate_shard(cfg, index, out_dir)` renders samples from the shard's own
seeds (`SeedSequence(root, spawn_key=(shard,))`, then `(shard, i)` per sample) and publishes one tar
atomically. Where it runs (this process, a process pool, a Dask cluster) changes nothing in its bytes.
`run_generate` runs the dataset as the core runner's resumable job (`dataset_job`): it skips the finished shards
(their sha256 verified), runs the rest and keeps `manifest.json` current after each shard (or a few:
resumable.MANIFEST_REWRITE_WAIT), so a killed run resumes where it stopped. Its config lives in
datagen/generate_config.py, its views (seeds, random and sequence-mode view sampling) in datagen/views.py; here:
the appearance draws, the corruption draws, one sample, one shard and the job.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import os
import sys
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import numpy as np

from envisat_pose.config import InputError, check, config_arg, path_arg, to_dict, to_toml
from envisat_pose.datagen.appearance import (
    FACE_GEOMS,
    GEOM_CLASS,
    Appearance,
    draw_materials,
    draw_own_materials,
    takes_class_appearance,
)
from envisat_pose.datagen.clearance import TargetBoxes
from envisat_pose.datagen.generate_config import GenerateConfig, config_from_json, config_json, sequence_depth_m
from envisat_pose.datagen.gl_check import check_gl_platform
from envisat_pose.datagen.labels import DEPTH_MAX_CODE, encode_depth, make_label
from envisat_pose.datagen.render_view import APPENDAGE_MASK_VALUE, MASK_VALUES, View, target_mask_values
from envisat_pose.datagen.target_scene import target_scene
from envisat_pose.datagen.views import R_K_FROM_C, sample_random_view, sample_seed, sequence_frames, sequence_view, unit
from envisat_pose.io import atomic_write_text, sha256_file
from envisat_pose.out_dirs import PARTIAL_PREFIX, check_out_dir
from envisat_pose.out_lock import locks_output
from envisat_pose.pools import RunnerConfig, cpu_share, thread_env, warn_runner
from envisat_pose.provenance import source_line
from envisat_pose.resumable import ResumableJob
from envisat_pose.shard_reader import shard_problem
from envisat_pose.state import RATE, VEL
from envisat_pose.target import APPENDAGE_GROUP, load_target
from envisat_pose.written_target import with_target_sha256

MANIFEST_FORMAT = "envisat-pose shards v1"
# generate_shard's helper threads (same bytes either way): one draws the views, one finishes sample k (the
# passes' pixels, labels, corruption, PNG encoding, tar) while the calling thread renders sample k + 1, one makes
# the Earth textures from the start. They pay only where the worker has a core its rasterizer leaves idle
# (spare_core); where every core is busy they measured neutral to a few % slower. None: run_generate decides by
# spare_core; True/False: forced (benchmarks, tests).
FINISH_BESIDE_RENDER: bool | None = None
# While the helper threads run, the interpreter's GIL switch interval (s). The render thread gives up the GIL in
# every MuJoCo/GL call and must win it back from the helper; at Python's default 5 ms each call can wait that
# long (measured at 1024 px: a busy Python thread beside the render doubled its time at 5 ms, none at 50 us).
GIL_SWITCH_INTERVAL_S = 5e-5
# Rendered samples that may wait for the finishing thread (each holds its read-back passes, ~4 MB at 1024 px).
FINISH_QUEUE = 2
# Random-mode datasets of at least this many images make the Earth textures on a helper thread from the start
# (SceneRenderer.prefetch_earth_textures): a long run shows every one of them anyway.
PREFETCH_EARTH_MIN_IMAGES = 32


# ---------------------------------------------------------------------------------------------------------
# Appearance


def appearance_rng(cfg: GenerateConfig, seed: int) -> np.random.Generator:
    """The generator of a sample's appearance and light intensities: seeded by (sample seed, appearance.seed),
    apart from the pose's, so appearance on/off or another appearance seed leaves poses and labels alone."""
    return np.random.default_rng(np.random.SeedSequence([seed, cfg.appearance.seed]))


def with_appearance(cfg: GenerateConfig, view, scene: dict, seed: int) -> tuple:
    """The view with its appearance (materials if appearance is on, sun intensity, Earth-shine) and clutter,
    and the scene dict with every choice needed to render it again (view_from_scene). Returns (View, scene)."""
    import dataclasses

    rng = appearance_rng(cfg, seed)
    lit = cfg.lighting
    sun_i = round(float(rng.uniform(*lit.sun_intensity)), 6)
    albedo = float(rng.uniform(*lit.earth_albedo))
    a = cfg.appearance
    target = load_target(cfg.target)
    classes = dict(GEOM_CLASS)
    by_class = takes_class_appearance(g.name for g in target.geoms)
    if not by_class:  # another target: each geom's own material, varied (appearance.draw_own_materials)
        base_rgb = target_scene(target).base_rgb
        materials = draw_own_materials(rng, base_rgb, a.specular, a.shininess, a.reflectance, a.brightness) \
            if cfg.appearance_on else {}
    else:
        geoms = tuple(g for g in GEOM_CLASS if cfg.appendages_on or MASK_VALUES[g] != APPENDAGE_MASK_VALUE)
        if a.one_covering is not None:
            classes.update({g: a.one_covering for g in FACE_GEOMS})
        materials = draw_materials(rng, a.texture_set_size, a.specular, a.shininess, a.reflectance, a.brightness,
                                   geoms, classes) if cfg.appearance_on else {}
    phase = 0.0
    if view.sun_dir_C is not None and view.earth_dir_C is not None:
        # lit fraction of the Earth's disc seen from the target: 1 with the sun behind us, 0 toward it
        phase = 0.5 * (1.0 - float(unit(view.sun_dir_C) @ unit(view.earth_dir_C)))
    earth_i = round(sun_i * albedo * lit.earth_view_factor * phase, 6) if lit.earthshine else 0.0
    appearance = Appearance(materials, sun_i, earth_i)
    view = dataclasses.replace(view, appearance=appearance, appendages=cfg.appendages_on)
    scene = dict(scene)
    scene.update({
        "appearance": cfg.appearance_on,
        # drawn where the switch is on and the target has such geoms (APPENDAGE_GROUP: ENVISAT's ASAR and boxes)
        "appendages": cfg.appendages_on and any(g.group == APPENDAGE_GROUP for g in target.geoms),
        **({"face_classes": {g: classes[g] for g in FACE_GEOMS}} if by_class else {}),
        "earthshine": {"intensity": earth_i, "earth_phase": round(phase, 6), "albedo": round(albedo, 6),
                       "dir_cam": None if view.earth_dir_C is None else (-R_K_FROM_C @ unit(view.earth_dir_C)).tolist()},
        "look": appearance.to_json(),  # the label's key, unchanged (shards written carry it)
        "render": render_inputs(view),
    })
    return view, scene


def render_inputs(view) -> dict:
    """What the renderer needs of a view, exactly (floats round-trip through JSON), for the label."""
    def vec(v):
        return None if v is None else [float(c) for c in np.asarray(v, dtype=float)]

    return {"rho_C_m": vec(view.rho_C_m), "R_C_from_T": [vec(r) for r in np.asarray(view.R_C_from_T)],
            "sun_dir_C": vec(view.sun_dir_C), "earth_dir_C": vec(view.earth_dir_C),
            "earth_distance_m": float(view.earth_distance_m), "earth_backdrop": bool(view.earth_backdrop),
            "earth_quat_C": vec(view.earth_quat_C), "earth_texture": int(view.earth_texture),
            "appendages": bool(view.appendages)}


def view_from_scene(scene: dict):
    """The View a label's scene records (with_appearance): the same render, bit for bit."""
    r = scene["render"]
    arr = lambda v: None if v is None else np.array(v, dtype=float)  # noqa: E731
    return View(arr(r["rho_C_m"]), arr(r["R_C_from_T"]), arr(r["sun_dir_C"]), arr(r["earth_dir_C"]),
                r["earth_distance_m"], Appearance.from_json(scene["look"]), r["appendages"], r["earth_backdrop"],
                arr(r.get("earth_quat_C")), int(r.get("earth_texture", 0)))


# ---------------------------------------------------------------------------------------------------------
# One sample, one shard


def image_motion(out, x: np.ndarray, f_px: float, boxes: TargetBoxes) -> tuple[float, float]:
    """The target's image motion (speed px/s, angle deg) from the state's relative rates: w_r (in T) turns the
    target about its centre, rho' (in C) moves it; the camera is fixed in C."""
    from envisat_pose.datagen.sensor import image_velocity_px_s

    w_K = out.R_K_from_T @ x[RATE]
    v_K = R_K_FROM_C @ x[VEL]
    return image_velocity_px_s(boxes.corners_T_m, out.R_K_from_T, out.t_K_from_T_m, w_K, v_K, f_px)


def draw_corruption_params(cfg: GenerateConfig, out, x: np.ndarray, f_px: float, boxes: TargetBoxes,
                           rng: np.random.Generator) -> dict:
    """The corruption parameters of one image: the space camera's (with the true image motion), none when
    every kind is 'none', or the paper's severities."""
    from envisat_pose.datagen.corrupt import KINDS, corruption_off, draw_corruption, no_corruption
    from envisat_pose.datagen.sensor import draw_sensor

    if cfg.corruption.model == "sensor":
        if corruption_off({k: getattr(cfg.corruption, k) for k in KINDS}):
            return no_corruption()  # every kind 'none': the user asked for uncorrupted frames
        speed, angle = image_motion(out, x, f_px, boxes)
        return draw_sensor(to_dict(cfg.corruption.sensor), cfg.resolution_px, f_px, speed, angle, rng)
    return draw_corruption(to_dict(cfg.corruption), cfg.resolution_px, rng)


def sample_view(cfg: GenerateConfig, shard_index: int, i: int, fovy_deg: float, znear_m: float,
                boxes: TargetBoxes) -> tuple:
    """Sample i of shard `shard_index`: its view with its appearance, from its own seed (sample_seed); no GL.
    Returns (k, seed, rng, view, x, scene): k the sample's index in the dataset, rng its Generator after the
    view's draws (the corruption draw continues it)."""
    k = shard_index * cfg.shard_size + i
    seed = sample_seed(cfg.seed, shard_index, i)
    rng = np.random.default_rng(seed)
    if cfg.mode == "random":
        view, x, scene = sample_random_view(cfg, fovy_deg, rng, znear_m, boxes)
    else:
        view, x, scene = sequence_view(cfg, k)
    view, scene = with_appearance(cfg, view, scene, seed)
    return k, seed, rng, view, x, scene


def render_sample(renderer, cfg: GenerateConfig, view, x: np.ndarray, scene: dict, rng: np.random.Generator,
                  seed: int) -> dict[str, bytes]:
    """Render, label, corrupt (unless storage is 'clean') and encode one sample: {suffix: bytes} per the
    shard contract. `view` carries its appearance (with_appearance)."""
    return finish_sample(renderer.K, renderer.target_boxes, cfg, renderer.render(view), x, scene, rng, seed)


def sample_arrays(K: np.ndarray, boxes: TargetBoxes, cfg: GenerateConfig, out, x: np.ndarray, scene: dict,
                  rng: np.random.Generator, seed: int) -> tuple[np.ndarray, dict]:
    """A sample's image and label before any encoding (finish_sample encodes them; the online trainer,
    pipelines/detector/online.py, takes them as they are): the corruption draw, the image ((H, W) uint8, corrupted
    unless storage is 'clean') and the label (plain JSON data, labels.make_label). No GL state."""
    from envisat_pose.datagen.corrupt import apply_corruption

    params = draw_corruption_params(cfg, out, x, K[0, 0], boxes, rng)
    image = out.gray_u8 if cfg.storage == "clean" else apply_corruption(out.gray_u8, params)
    target = load_target(cfg.target)
    visible = target.visible(out.R_K_from_T, out.t_K_from_T_m, cfg.appendages_on)
    label = make_label(out.corners_K_m, visible, K, out.R_K_from_T, out.t_K_from_T_m, x, cfg.depth_scale_m, params,
                       seed, scene, target.keypoint_names if target.labels_name_keypoints else None)
    label["image_stored"] = cfg.storage
    return image, label


def finish_sample(K: np.ndarray, boxes: TargetBoxes, cfg: GenerateConfig, out, x: np.ndarray, scene: dict,
                  rng: np.random.Generator, seed: int) -> dict[str, bytes]:
    """Everything of a sample after its render (`out`, a RenderOutput of the renderer whose intrinsics are K
    and whose target is `boxes`): the corruption draw, the label, the corruption (unless storage is 'clean')
    and the PNG and JSON encoding. Touches no GL state, so it may run beside the next render."""
    from envisat_pose.datagen.shards import encode_png, label_bytes

    image, label = sample_arrays(K, boxes, cfg, out, x, scene, rng, seed)
    members = {"png": encode_png(image), "json": label_bytes(label)}
    if cfg.write_mask:
        members["mask.png"] = encode_png(out.mask_u8)
    if cfg.write_depth:
        members["depth.png"] = encode_png(encode_depth(out.depth_m, cfg.depth_scale_m), "depth")
    return members


@contextlib.contextmanager
def gil_switch_interval(interval_s: float):
    """Set the interpreter's GIL switch interval (s) inside the block, restore it after."""
    before = sys.getswitchinterval()
    sys.setswitchinterval(interval_s)
    try:
        yield
    finally:
        sys.setswitchinterval(before)


def spare_core(workers: int, backend: str = "local", scheduler: str | None = None) -> bool:
    """Whether each of `workers` workers has a core its renderer leaves idle: LP_NUM_THREADS (llvmpipe's
    rasterizer threads, set before the run) below the worker's share of the usable cores. Unset, the run
    sets it to that share (no core spare); an existing Dask scheduler's machines are unknown (False)."""
    lp = os.environ.get("LP_NUM_THREADS", "")
    if scheduler or not lp.isdigit():
        return False
    return int(lp) < cpu_share(workers)


def generate_shard(cfg: GenerateConfig, shard_index: int, out_dir: str, beside: bool = False) -> dict:
    """Write shard `shard_index` of the dataset into out_dir (atomically). Returns its manifest entry:
    index, name, count, sha256, bytes. beside: use the helper threads (FINISH_BESIDE_RENDER; same bytes)."""
    import cv2

    from envisat_pose.datagen.render_cache import shared_renderer
    from envisat_pose.datagen.shards import ShardWriter, sample_key, shard_name

    cv2.setNumThreads(1)  # one core per worker; also keeps filters on one code path
    renderer = shared_renderer(cfg.resolution_px, cfg.shadows, cfg.appearance.texture_set_size if cfg.appearance_on
                               else 0, cfg.appearance.texture_seed, cfg.earth_seed, cfg.target)
    beside = bool(beside if FINISH_BESIDE_RENDER is None else FINISH_BESIDE_RENDER)
    if (beside and cfg.mode == "random" and cfg.earth_probability > 0
            and cfg.num_images >= PREFETCH_EARTH_MIN_IMAGES):
        renderer.prefetch_earth_textures()  # a worker's start-up beside its first renders (no-op once made)
    path = os.path.join(out_dir, shard_name(shard_index))
    count = cfg.shard_count(shard_index)
    K, boxes = renderer.K.copy(), renderer.target_boxes
    fovy_deg, znear_m = renderer.fovy_deg, renderer.znear_m

    def prepare(i: int) -> tuple:
        return sample_view(cfg, shard_index, i, fovy_deg, znear_m, boxes)

    def finish_and_write(k, out, x, scene, rng, seed):
        writer.write(sample_key(k), finish_sample(K, boxes, cfg, out, x, scene, rng, seed))

    def decode_finish_and_write(k, passes, x, scene, rng, seed):
        finish_and_write(k, renderer.decode(passes), x, scene, rng, seed)

    if not beside:
        with ShardWriter(path) as writer:
            for i in range(count):
                k, seed, rng, view, x, scene = prepare(i)
                finish_and_write(k, renderer.render(view), x, scene, rng, seed)
    else:
        # This thread only renders (the GL passes). One helper thread draws the next samples' views; another
        # finishes the rendered ones (the passes' pixel work, corruption draw, label, corruption, PNG encoding,
        # tar) while the next render runs: the render spends most of its time waiting in GL calls that release
        # the GIL (llvmpipe's rasterizer thread does the work), so they overlap. Up to FINISH_QUEUE samples wait
        # to be finished, so a slow finish (a tar flush, another process) does not stall the render. Each
        # sample's own generator is used in the same order (its view, then after its render its corruption draw)
        # and one finishing thread writes first in first out: the same bytes in the same order as doing it all
        # one after the other. The pools close (every sample written or failed) before the writer publishes or
        # discards the shard.
        with gil_switch_interval(GIL_SWITCH_INTERVAL_S), ShardWriter(path) as writer, \
                ThreadPoolExecutor(1, thread_name_prefix="finish") as finisher, \
                ThreadPoolExecutor(1, thread_name_prefix="prepare") as preparer:
            upcoming = preparer.submit(prepare, 0)
            pending: collections.deque = collections.deque()
            for i in range(count):
                k, seed, rng, view, x, scene = upcoming.result()
                if i + 1 < count:
                    upcoming = preparer.submit(prepare, i + 1)
                passes = renderer.render_passes(view)
                pending.append(finisher.submit(decode_finish_and_write, k, passes, x, scene, rng, seed))
                while len(pending) > FINISH_QUEUE:
                    pending.popleft().result()  # its error surfaces here
            while pending:
                pending.popleft().result()
    return {"index": shard_index, "name": shard_name(shard_index), "count": count, "sha256": sha256_file(path),
            "bytes": os.path.getsize(path)}


def shard_task(cfg_json: str, shard_index: int, out_dir: str, beside: bool = False) -> dict:
    """generate_shard for workers: the config travels as JSON text."""
    return generate_shard(config_from_json(cfg_json), shard_index, out_dir, beside)


# ---------------------------------------------------------------------------------------------------------
# Planning, resuming, running


def check_sequence_depth(cfg: GenerateConfig) -> None:
    """Sequence mode: the simulated truth's keep-out check, then with write_depth a ConfigError on depth_scale_m
    unless 65535 x depth_scale_m covers the farthest target point of every frame (a scale given too small: one
    not given is sized to them, generate_config.sequence_depth_m)."""
    sequence_frames(config_json(cfg))
    if not cfg.write_depth:
        return
    far_m = sequence_depth_m(cfg)
    k = int(np.argmax(far_m))
    check(DEPTH_MAX_CODE * cfg.depth_scale_m >= far_m[k], "depth_scale_m", cfg.depth_scale_m,
          f"a scale whose 16-bit range (65535 x scale = {DEPTH_MAX_CODE * cfg.depth_scale_m:.1f} m) covers "
          f"{far_m[k]:.1f} m, the farthest target point of scenario {cfg.sequence.scenario!r} (frame {k})")


def warn_if_dark(cfg: GenerateConfig) -> None:
    """Sequence mode: a warning when half the frames or more are in the Earth's shadow (black but for the Earth's
    own light), with the sun drawn from the seed where the config gives none (`envisat run` lights its first
    frame instead): a sequence meant for tracking may show nothing."""
    dark = sequence_frames(config_json(cfg))[3]
    if dark.size and dark.mean() >= 0.5:
        import warnings

        sun = "drawn from the seed; set sun_dir to choose it" if cfg.sun_dir is None else f"sun_dir {cfg.sun_dir}"
        warnings.warn(f"{int(dark.sum())} of {dark.size} frames are in the Earth's shadow, the target unlit ({sun})",
                      stacklevel=3)


def dataset_job(cfg: GenerateConfig, out_dir: str) -> ResumableJob:
    """The dataset in out_dir as the core's resumable job: one unit per shard, the config and root seed as its
    identity, a shard kept on resume only when its sha256 matches (the job's own check) and it passes the core's
    one shard check against the rest of its entry (shard_reader.shard_problem: size, the recorded count of
    complete samples from the tar's headers; not the sha256 again: a rerun read every shard twice)."""
    from envisat_pose.datagen.shards import SHARD_GLOB, shard_name

    target = load_target(cfg.target)
    masks = target_mask_values(target)
    return ResumableJob(
        out_dir, MANIFEST_FORMAT, "dataset", {"config": to_dict(cfg), "root_seed": cfg.seed}, "shards",
        cfg.num_shards, shard_name,
        header={"num_images": cfg.num_images, "num_shards": cfg.num_shards, "target": target.record(cfg.target),
                "mask_values": {"background": 0, **masks},
                "members": ["png", "json"] + (["mask.png"] if cfg.write_mask else [])
                + (["depth.png"] if cfg.write_depth else [])},
        verify_unit=lambda entry, path: shard_problem(path, {k: v for k, v in entry.items() if k != "sha256"}) is None,
        compared_by={"config.target": "target.sha256"},  # the file, however its path is written
        unit_glob=SHARD_GLOB)  # dataset verify's stray shards: refused, never removed (not the job's)


def run_generate(cfg: GenerateConfig, out_dir: str, workers: int = 1, backend: str = "local",
                 scheduler: str | None = None, progress: bool = False,
                 on_shard: Callable[[dict], None] | None = None) -> dict:
    """Generate (or finish) the dataset of `cfg` in out_dir; returns the final manifest.

    on_shard, if given, is called with each finished shard's manifest entry once it is recorded. A finished
    dataset in a folder this process cannot write (read-only media) is returned as it is, nothing written, and
    such a folder holding an unfinished one (or a partial file) is refused saying what is there
    (`finished_unwritable`); anywhere else the run holds the folder's lock (out_lock) while it works.
    """

    cfg, out_dir = config_arg(cfg, GenerateConfig), path_arg(out_dir, "out_dir")
    check(backend in ("local", "dask"), "backend", backend, "'local' or 'dask'")
    check(type(workers) is int and workers >= 1, "workers", workers, "at least 1 worker process (an integer)")
    check(scheduler is None or backend == "dask", "scheduler", scheduler, "an address only with backend 'dask'")
    finished = finished_unwritable(cfg, out_dir)
    if finished is not None:
        return finished
    return _generate(cfg, out_dir, workers, backend, scheduler, progress, on_shard)


def finished_unwritable(cfg: GenerateConfig, out_dir: str) -> dict | None:
    """The manifest of cfg's finished dataset in out_dir when this process cannot write the folder (a read-only
    copy, another user's) and the dataset verifies whole (datagen.dataset.verify_dataset: every shard's sha256,
    no stray or partial file): a rerun has nothing to do there, and a run's writes (its lock file, the manifest
    and config rewritten with what they hold) would only refuse it. InputError in one line when the read-only
    folder holds anything else of cfg's dataset (its finished shards of an unfinished run, a partial file an
    interrupted run left, a damaged shard): what is there, and that a rerun cannot finish or tidy it there. None
    otherwise (a writable folder, an empty one): the run goes on, refused where it must write. InputError as a
    rerun's: a folder of another config or seed, a stray shard."""
    if not os.path.isdir(out_dir) or os.access(out_dir, os.W_OK):  # root: False on a read-only mount only
        return None
    from envisat_pose.datagen.dataset import verify_dataset

    job = dataset_job(cfg, out_dir)
    previous = job.previous()
    problems = [] if previous is None else verify_dataset(out_dir)
    if previous is not None and previous.get("complete") and not problems:
        return previous
    partials = sorted(n for n in os.listdir(out_dir) if n.startswith(PARTIAL_PREFIX))
    if previous is None and not partials:
        return None
    raise InputError(unwritable_line(out_dir, previous, partials, problems))


def unwritable_line(out_dir: str, previous: dict | None, partials: list[str], problems: list[str]) -> str:
    """finished_unwritable's refusal: the read-only folder's finished shards, the partial files an interrupted run
    left (a rerun removes them), a finished dataset's first other problem (dataset verify's line), what to do."""
    shards = [] if previous is None else previous.get("shards", [])
    n_shards = int(previous.get("num_shards", len(shards))) if previous is not None else 0
    complete = previous is not None and bool(previous.get("complete"))
    held = ("no finished shard" if not shards else f"the dataset's {len(shards)} shard{'s' * (len(shards) > 1)}, all "
            "finished" if complete else f"{len(shards)} of the dataset's {n_shards} shards finished")
    if partials:
        more = f" and {len(partials) - 1} more" if len(partials) > 1 else ""
        held += (f", and {partials[0]}{more} ({'partial files' if more else 'a partial file'} an interrupted run "
                 "left, which a rerun removes)")
    others = [p for p in problems if not p.startswith(PARTIAL_PREFIX) and p != "manifest marked incomplete"]
    if complete and others:
        held += f"; dataset verify: {others[0]}"
    todo = ("remove it there (the finished shards read as they are); rerun on a writable copy of the folder to tidy "
            "it" if complete and not others else
            f"{'redo' if complete else 'finish'} it there; rerun on a writable copy of the folder, or use another one")
    return f"out_dir {out_dir!r} is read-only (this process cannot write there) and holds {held}: generate cannot {todo}"


@locks_output("out_dir", "generate")
def _generate(cfg: GenerateConfig, out_dir: str, workers: int, backend: str, scheduler: str | None,
              progress: bool, on_shard: Callable[[dict], None] | None) -> dict:
    """run_generate's work under the folder's lock."""
    runner = RunnerConfig(backend, workers, scheduler)  # checked before the folder is touched
    if scheduler is None:  # this machine's renderer (a cluster's workers have their own)
        check_gl_platform()
    check_out_dir(out_dir)
    if cfg.mode == "sequence":  # before anything is written: the truth's keep-out and the depth range
        check_sequence_depth(cfg)
        warn_if_dark(cfg)
    job = dataset_job(cfg, out_dir)
    done = job.resume(job.open())
    left = len(job.todo())  # the shards this run makes, one a process: a resume's, not the dataset's
    # one rasterizer thread count per worker: the usable cores shared among the workers that start for them
    runner = dataclasses.replace(runner, env=thread_env(workers, units=left))
    warn_runner(runner, left)  # none on a finished rerun
    atomic_write_text(os.path.join(out_dir, "generate.config.toml"),
                      "# envisat generate: the full validated config of this dataset\n" + source_line()
                      + to_toml(with_target_sha256(to_dict(cfg), "generate", job.header["target"]["sha256"])))
    bar, n_done = None, sum(e["count"] for e in done.values())
    if progress and n_done < cfg.num_images:  # nothing to do draws no bar (the verb says so in its line)
        from tqdm import tqdm

        bar = tqdm(total=cfg.num_images, initial=n_done, unit="img",
                   desc="generate", mininterval=0.5)

    def on_unit(entry: dict) -> None:
        if bar is not None:
            bar.update(entry["count"])
        if on_shard is not None:
            on_shard(entry)

    try:
        cfg_text, where = config_json(cfg), os.path.abspath(out_dir)
        beside = spare_core(min(workers, left), backend, scheduler)
        return job.run(shard_task, lambda idx: (cfg_text, idx, where, beside), runner, on_unit)
    finally:
        if bar is not None:
            bar.close()
