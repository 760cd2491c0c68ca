"""Image factory speed: labelled images per second end to end (render, label, corrupt, encode, write shards)
at 512 and 1024 px with 1 and 2 workers, next to the raw MuJoCo render rate of the same scenes in the same run.

Protocol: one core per worker (LP_NUM_THREADS=1 for every renderer, the raw one included), random mode with
the default config, the same sample seeds for the raw renders and the dataset. The raw rate is the lit pass
alone (mjr_render of the sun-lit, shadowed, 4x multisampled scene plus the RGB read-back): what one image costs
before any label. For context it also times the stock mujoco.Renderer producing RGB, depth and segmentation.
End-to-end times are wall clock of `run_generate`, worker start-up included.

Scaling floors (`--scaling`; `--issue3` accepted): 1 worker >= 60 % of the raw render rate; 2 workers >= 1.7 x one. A CPU scaling probe
(zlib in 2 processes vs 1) tells what speedup the machine itself allows two processes.

The default mode: at 1024 px, labelled images/s of run_generate with 1 and 2
workers, appearance (materials, clutter) on and off, storage clean and corrupted (the space camera model), next
to the two-pass render (lit + segmentation/depth) of the same views measured in the same run, with and without
the appearance; bytes per image of every dataset.

Two-pass floor: appearance on, clean storage, 1 worker >= 1.0 x the two-pass render of the same views. Measured
in alternating rounds (two-pass render, factory, factory with FINISH_BESIDE_RENDER off) so the machine's load
drifts alike for all three; the median ratio is the floor's. The floor's factory runs --floor-images (200) in
shards of the default size (100), as a user's run does. The factory finishes sample k (the passes' pixel work,
labels, PNG, tar) on a helper thread while the GL passes of sample k + 1 wait on llvmpipe's rasterizer thread
(here, LP_NUM_THREADS=1 and 1 worker on a multi-core machine, factory.spare_core turns it on): it uses more CPU
than one core's wall time, so the rounds also give CPU ms per image (process time), and one more round runs
with every thread of the process pinned to one core (the ratio one core gives). Worker start-up: the seconds a
fresh process takes to import, build its renderer and make every texture a long run uses, one after the other
(a child process), and as counted in a run: a fresh process generating the floor's images (its wall time less
those images at the steady rate; the Earth textures are made beside the first renders from
factory.PREFETCH_EARTH_MIN_IMAGES images on, where a core is spare); with the steady rate, the rate and ratio of
a 1000-image run with start-up counted and excluded.
Targets (`--targets --baseline DIR`): ENVISAT's time per image against a baseline tree's and the shipped targets'
against ENVISAT's, in one run (TARGET_RUNS, main_targets).
Run: .venv/bin/python bench/datagen_speed.py [--scaling | --targets [--baseline DIR] [--current DIR]] [--images N]
     [--floor-images 200] [--rounds 3] [--seed 2024] [--tag TAG] [--out bench/results/datagen_speed.json]
Each mode merges its table into --out under its own key (default mode: issue18_TAG; --scaling: TAG; --targets:
KEY_TAG), TAG naming the machine (default: MUJOCO_GL and the core count), so runs on different machines and
earlier tables sit side by side.
"""

from __future__ import annotations

import os

os.environ["LP_NUM_THREADS"] = "1"  # before any GL context: one rasterizer thread per process
os.environ.setdefault("MUJOCO_GL", "osmesa")

import argparse
import functools
import json
import platform
import shutil
import statistics
import sys
import tempfile
import time

import numpy as np

IMAGES = {512: 160, 1024: 96}  # --scaling's images per resolution
SHARD_SIZE = 16
SEED = 2024  # --seed's default


def bench_config(resolution_px: int, n: int, **kw):
    from envisat_pose.config import from_dict
    from envisat_pose.datagen.generate_config import GenerateConfig

    return from_dict(GenerateConfig, {"resolution_px": resolution_px, "num_images": n, "shard_size": SHARD_SIZE,
                                      "seed": SEED, **kw})


def two_pass_rate(cfg, appearance: bool) -> float:
    """Images/s of SceneRenderer.render (lit + segmentation/depth passes) over the dataset's own views, with
    the dataset's appearance draws (appearance on) or the MJCF's plain materials (off)."""
    import dataclasses

    from envisat_pose.datagen.factory import with_appearance
    from envisat_pose.datagen.render import SceneRenderer

    r = SceneRenderer(cfg.resolution_px, texture_set_size=cfg.appearance.texture_set_size if appearance else 0)
    views = []
    for k, (v, x, sc) in enumerate(sample_views(cfg, r.fovy_deg)):
        s, i = divmod(k, cfg.shard_size)
        from envisat_pose.datagen.views import sample_seed

        v2, _ = with_appearance(cfg, v, sc, sample_seed(cfg.seed, s, i))
        views.append(v2 if appearance else dataclasses.replace(v2, appearance=None, appendages=False))
    for v in views[:3]:
        r.render(v)
    t0 = time.perf_counter()
    for v in views:
        r.render(v)
    rate = len(views) / (time.perf_counter() - t0)
    r.close()
    return rate


def bytes_per_image(cfg) -> dict:
    """Mean bytes per image of the dataset's members (png, mask, depth, json), from one shard's samples."""
    import tempfile as _t

    from envisat_pose.datagen.factory import run_generate
    from envisat_pose.shard_reader import read_shard

    out = _t.mkdtemp(prefix="datagen_bytes_")
    try:
        m = run_generate(cfg, os.path.join(out, "ds"))
        sizes: dict[str, list[int]] = {}
        for e in m["shards"]:
            for _, members in read_shard(os.path.join(out, "ds", e["name"])):
                for k, v in members.items():
                    sizes.setdefault(k, []).append(len(v))
        res = {k: float(np.mean(v)) for k, v in sizes.items()}
        res["shard_bytes_per_image"] = sum(e["bytes"] for e in m["shards"]) / cfg.num_images
        return res
    finally:
        shutil.rmtree(out, ignore_errors=True)


def _pin_process(cpus: set[int]) -> None:
    """Every thread of this process (llvmpipe's rasterizer included) onto `cpus`; threads made later inherit."""
    for tid in os.listdir("/proc/self/task"):
        try:
            os.sched_setaffinity(int(tid), cpus)
        except OSError:
            pass


def floor_rounds(base, cfg, rounds: int) -> dict:
    """The two-pass floor: alternating rounds of the two-pass render of the same views, the factory (1 worker)
    and the factory finishing each sample after its render (FINISH_BESIDE_RENDER off); then one round pinned
    to one core. Rates img/s, CPU ms per image (process time: every thread), ratios to the round's render."""
    from envisat_pose.datagen import factory

    def one_round() -> dict:
        r = {}
        c0 = time.process_time()
        r["two_pass_img_s"] = two_pass_rate(base, True)
        c1 = time.process_time()
        r["factory_e2e_img_s"], r["factory_steady_img_s"] = end_to_end(cfg, 1)
        c2 = time.process_time()
        factory.FINISH_BESIDE_RENDER = False
        try:
            r["serial_e2e_img_s"], r["serial_steady_img_s"] = end_to_end(cfg, 1)
        finally:
            factory.FINISH_BESIDE_RENDER = None  # run_generate's choice (factory.spare_core)
        c3 = time.process_time()
        # the render's CPU includes its 3 warm-up views and the renderer's set-up: an upper bound
        r["two_pass_cpu_ms_per_img_upper"] = 1e3 * (c1 - c0) / (base.num_images + 3)
        r["factory_cpu_ms_per_img"] = 1e3 * (c2 - c1) / cfg.num_images
        r["serial_cpu_ms_per_img"] = 1e3 * (c3 - c2) / cfg.num_images
        r["ratio"] = r["factory_e2e_img_s"] / r["two_pass_img_s"]
        r["ratio_serial"] = r["serial_e2e_img_s"] / r["two_pass_img_s"]
        r["load_avg_1min"] = os.getloadavg()[0]
        print("  round: " + ", ".join(f"{k} {v:.2f}" for k, v in r.items()), flush=True)
        return r

    out = {"rounds": [one_round() for _ in range(rounds)]}
    out["median_ratio"] = statistics.median(r["ratio"] for r in out["rounds"])
    out["median_ratio_serial"] = statistics.median(r["ratio_serial"] for r in out["rounds"])
    cpus = os.sched_getaffinity(0)
    _pin_process({min(cpus)})
    try:
        print("  pinned to one core:", flush=True)
        out["one_core"] = one_round()
    finally:
        _pin_process(cpus)
    return out


def worker_startup_s() -> float:
    """Seconds a fresh process needs to import, build its renderer (GL context, class textures) and make every
    Earth texture a long run shows, one after the other (a worker's start-up without the prefetch)."""
    import subprocess
    import sys

    code = ("from envisat_pose.datagen.render_cache import shared_renderer\n"
            "r = shared_renderer(1024, True, 8, 0, 0)\n"
            "[r._upload_earth_texture(kind, k) for kind in ('earth', 'earth_cap') for k in range(r.earth_texture_set_size)]\n")
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, env=dict(os.environ))
    return time.perf_counter() - t0


def fresh_process_s(n: int, shard_size: int = SHARD_SIZE, seed: int = SEED) -> float:
    """Wall seconds of a fresh process that imports the factory and runs run_generate (1 worker, appearance
    on, clean, 1024 px, n images), from its launch to its exit: the worker's start-up counted."""
    import subprocess

    code = ("import os, sys, tempfile, shutil\n"
            f"sys.path.insert(0, {os.path.dirname(os.path.abspath(__file__))!r})\n"
            "from datagen_speed import bench_config\n"
            "from envisat_pose.datagen.factory import run_generate\n"
            f"cfg = bench_config(1024, {n}, storage='clean', appearance={{'enabled': True}}, appendages=True, "
            f"shard_size={shard_size}, seed={seed})\n"
            "out = tempfile.mkdtemp()\n"
            "run_generate(cfg, os.path.join(out, 'ds'))\n"
            "shutil.rmtree(out)\n")
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, env=dict(os.environ))
    return time.perf_counter() - t0


def default_mode_table(n: int, rounds: int, nf: int, seed: int) -> dict:
    """The default mode's table at 1024 px (n images per dataset) and the two-pass floor (rounds rounds of nf
    images), the datasets' root seed `seed` (module docstring)."""
    config = functools.partial(bench_config, seed=seed)
    res = 1024
    out = {"images": n, "resolution_px": res, "load_avg_start": os.getloadavg()}
    base = config(res, n)
    # the floor at the user's default shard size, over enough images for a steady state after the first shard
    from envisat_pose.datagen.generate_config import GenerateConfig

    floor_shard = GenerateConfig().shard_size
    out["floor_images"], out["floor_shard_size"] = nf, floor_shard
    base_floor = config(res, nf, shard_size=floor_shard)
    on_clean = config(res, nf, storage="clean", appearance={"enabled": True}, appendages=True,
                      shard_size=floor_shard)
    end_to_end(config(res, 16, storage="clean", appearance={"enabled": True}, appendages=True), 1)  # this
    # process's renderer, its textures and imports made once, outside the rounds
    print(f"two-pass floor (appearance on, clean, 1 worker, 1024 px, {nf} images in shards of {floor_shard}):",
          flush=True)
    out["floor_issue18"] = floor = floor_rounds(base_floor, on_clean, rounds)
    out["worker_startup_serial_s"] = worker_startup_s()
    fresh = fresh_process_s(nf, floor_shard, seed)
    steady_1w = steady = statistics.median([r["factory_steady_img_s"] for r in floor["rounds"]])
    # start-up as it costs in a run: the fresh process's wall time beyond its images at the steady rate
    out["fresh_process_e2e_img_s"] = nf / fresh
    out["worker_startup_counted_s"] = startup = max(0.0, fresh - nf / steady)
    out["long_run_1000_img_s_startup_counted"] = 1000.0 / (startup + 1000.0 / steady)
    out["long_run_1000_img_s_startup_excluded"] = steady
    peer = statistics.median([r["two_pass_img_s"] for r in floor["rounds"]])
    out["long_run_1000_ratio_startup_counted"] = out["long_run_1000_img_s_startup_counted"] / peer
    out["long_run_1000_ratio_startup_excluded"] = steady / peer
    out["two_pass_appearance_off_img_s"] = two_pass_rate(base, False)
    out["two_pass_appearance_on_img_s"] = two_pass_rate(base, True)
    rows = {}
    for appearance in (True, False):
        for storage in ("clean", "corrupted"):
            cfg = config(res, n, storage=storage, appearance={"enabled": appearance}, appendages=appearance)
            name = f"appearance_{'on' if appearance else 'off'}_{storage}"
            row = {"bytes": bytes_per_image(config(res, 16, storage=storage, appearance={"enabled": appearance},
                                                   appendages=appearance, shard_size=16))}
            for w in (1, 2):
                e2e, steady = end_to_end(cfg, w)
                row[f"e2e_{w}w_img_s"], row[f"steady_{w}w_img_s"] = e2e, steady
            peer = out["two_pass_appearance_on_img_s" if appearance else "two_pass_appearance_off_img_s"]
            row["ratio_1w_to_two_pass_same_look"] = row["e2e_1w_img_s"] / peer  # key as in bench/results
            row["ratio_1w_to_two_pass_plain"] = row["e2e_1w_img_s"] / out["two_pass_appearance_off_img_s"]
            rows[name] = row
            fmt = lambda v: "   n/a" if v is None else f"{v:6.2f}"  # noqa: E731
            print(f"{name:28s} 1w {row['e2e_1w_img_s']:6.2f} (steady {fmt(row['steady_1w_img_s'])})  2w "
                  f"{row['e2e_2w_img_s']:6.2f} (steady {fmt(row['steady_2w_img_s'])}) img/s; "
                  f"png {row['bytes']['png'] / 1e3:7.1f} kB, shard {row['bytes']['shard_bytes_per_image'] / 1e3:7.1f} kB/img",
                  flush=True)
    out["rows"] = rows
    out["floor_1_0x_same_look_met"] = floor["median_ratio"] >= 1.0
    out["load_avg_end"] = os.getloadavg()
    print(f"two-pass floor: factory / two-pass render of the same views, 1 worker: median {floor['median_ratio']:.2f}x "
          f"(finishing after each render: {floor['median_ratio_serial']:.2f}x; pinned to one core: "
          f"{floor['one_core']['ratio']:.2f}x, serial {floor['one_core']['ratio_serial']:.2f}x); floor 1.0x "
          f"{'met' if out['floor_1_0x_same_look_met'] else 'NOT met'}")
    print(f"worker start-up: {out['worker_startup_serial_s']:.1f} s made one after the other, {startup:.1f} s as "
          f"counted in a fresh {nf}-image run ({out['fresh_process_e2e_img_s']:.2f} img/s); 1000 images at the "
          f"steady {steady_1w:.2f} img/s: {out['long_run_1000_img_s_startup_counted']:.2f} img/s with start-up counted "
          f"({out['long_run_1000_ratio_startup_counted']:.2f}x the render), "
          f"{out['long_run_1000_ratio_startup_excluded']:.2f}x excluded")
    return out


def sample_views(cfg, fovy_deg: float) -> list:
    """The dataset's own views (same seeds as generate_shard)."""
    from envisat_pose.datagen.views import sample_random_view, sample_seed

    views = []
    for k in range(cfg.num_images):
        s, i = divmod(k, cfg.shard_size)
        views.append(sample_random_view(cfg, fovy_deg, np.random.default_rng(sample_seed(cfg.seed, s, i))))
    return views


def raw_rates(cfg) -> dict:
    """Images/s of the lit pass alone, of our two-pass render, and of the stock Renderer's rgb+depth+seg;
    plus the per-stage milliseconds of one labelled sample."""
    import mujoco

    from envisat_pose.config import to_dict
    from envisat_pose.datagen.corrupt import apply_corruption, draw_corruption
    from envisat_pose.datagen.factory import render_sample
    from envisat_pose.datagen.labels import encode_depth
    from envisat_pose.datagen.render import SceneRenderer
    from envisat_pose.datagen.render_model import render_model_xml
    from envisat_pose.datagen.shards import encode_png

    r = SceneRenderer(cfg.resolution_px)
    views = sample_views(cfg, r.fovy_deg)
    for v in views[:3]:
        r.render_rgb_only(v[0])
    t0 = time.perf_counter()
    for v in views:
        r.render_rgb_only(v[0])
    raw = len(views) / (time.perf_counter() - t0)
    t0 = time.perf_counter()
    outs = [r.render(v[0]) for v in views]
    two_pass = len(views) / (time.perf_counter() - t0)
    stages = {"render_two_passes_ms": 1e3 / two_pass, "render_lit_pass_ms": 1e3 / raw}
    rngs = [np.random.default_rng(k) for k in range(len(views))]
    sev = to_dict(cfg.corruption)
    t0 = time.perf_counter()
    imgs = [apply_corruption(o.gray_u8, draw_corruption(sev, cfg.resolution_px, g)) for o, g in zip(outs, rngs)]
    stages["corrupt_ms"] = (time.perf_counter() - t0) * 1e3 / len(views)
    t0 = time.perf_counter()
    for o, im in zip(outs, imgs):
        encode_png(im), encode_png(o.mask_u8), encode_png(encode_depth(o.depth_m, cfg.depth_scale_m), "depth")
    stages["png_encode_ms"] = (time.perf_counter() - t0) * 1e3 / len(views)
    # raw render and full sample interleaved view by view: their ratio is robust to the machine's load drifting
    t_raw = t_sample = 0.0
    for k, v in enumerate(views):
        t0 = time.perf_counter()
        r.render_rgb_only(v[0])
        t1 = time.perf_counter()
        render_sample(r, cfg, v[0], v[1], v[2], np.random.default_rng(k), k)
        t_raw, t_sample = t_raw + t1 - t0, t_sample + time.perf_counter() - t1
    stages["render_sample_in_process_ms"] = t_sample * 1e3 / len(views)
    stages["interleaved_raw_lit_ms"] = t_raw * 1e3 / len(views)
    r.close()

    # the stock Renderer making the three raw products of a labelled image, same model and views
    model = mujoco.MjModel.from_xml_string(render_model_xml(cfg.resolution_px))
    data = mujoco.MjData(model)
    stock = mujoco.Renderer(model, cfg.resolution_px, cfg.resolution_px)
    adr = model.joint("target_free").qposadr[0]
    from envisat_pose.attitude import rotmat_to_quat

    n_stock = min(len(views), 40)
    t0 = time.perf_counter()
    for v in views[:n_stock]:
        data.qpos[adr : adr + 3] = v[0].rho_C_m
        data.qpos[adr + 3 : adr + 7] = rotmat_to_quat(v[0].R_C_from_T)
        mujoco.mj_forward(model, data)
        stock.update_scene(data, camera="chaser_cam")
        stock.render()
        stock.enable_depth_rendering()
        stock.render()
        stock.disable_depth_rendering()
        stock.enable_segmentation_rendering()
        stock.render()
        stock.disable_segmentation_rendering()
    stock_rate = n_stock / (time.perf_counter() - t0)
    stock.close()
    return {"raw_lit_render_img_s": raw, "two_pass_render_img_s": two_pass,
            "stock_renderer_rgb_depth_seg_img_s": stock_rate, "stages_ms": stages}


def end_to_end(cfg, workers: int) -> tuple[float, float]:
    """Labelled images/s of run_generate into a fresh folder: (wall clock with worker start-up, steady state).

    Steady state: the images finished after each worker's first shard, over the time since then.
    """
    from envisat_pose.datagen.factory import run_generate

    out = tempfile.mkdtemp(prefix="datagen_speed_")
    stamps = []
    try:
        t0 = time.perf_counter()
        manifest = run_generate(cfg, os.path.join(out, "ds"), workers=workers,
                                on_shard=lambda e: stamps.append((time.perf_counter(), e["count"])))
        dt = time.perf_counter() - t0
        assert manifest["complete"]
        # a steady state needs a shard after each worker's first; with several workers, two rounds of them
        # (with one round the last shards overlap the first ones and the interval means nothing)
        if len(stamps) <= workers or (workers > 1 and len(stamps) < 2 * workers + 1):
            return cfg.num_images / dt, None
        t_w = stamps[workers - 1][0]
        n_after = sum(c for _, c in stamps[workers:])
        steady = n_after / (stamps[-1][0] - t_w)
        return cfg.num_images / dt, steady
    finally:
        shutil.rmtree(out, ignore_errors=True)


def _zlib_work(_: int = 0) -> float:
    """A fixed CPU load (zlib level 1 on 40 MB of noise), seconds."""
    import zlib

    data = np.random.default_rng(0).integers(0, 255, 1 << 20, dtype=np.uint8).tobytes()
    t0 = time.perf_counter()
    for _ in range(40):
        zlib.compress(data, 1)
    return time.perf_counter() - t0


def cpu_scaling_probe() -> float:
    """How much two processes gain over one on this machine for a plain CPU load (ideal 2.0): the ceiling
    for the 2-worker speedup, independent of the factory."""
    import multiprocessing as mp

    one = _zlib_work()
    with mp.get_context("spawn").Pool(2) as pool:
        pool.map(_zlib_work, [0, 0])  # warm the workers
        t0 = time.perf_counter()
        pool.map(_zlib_work, [0, 1])
        two = time.perf_counter() - t0
    return 2.0 * one / two


# Targets (`--targets [--baseline DIR] [--current DIR]`): seconds per image of run_generate, 1 worker, 1024 px,
# random mode with the default config, for ENVISAT at this tree (or at --current DIR: a `git archive` of the commit
# measured, so edits in the working tree stay out) and at a baseline tree (DIR: a `git archive` of the commit before
# the target work, its plugin's .so copied in), and for the shipped targets at ranges where they fill the image about as ENVISAT
# does at 20-80 m (the random mode's default ranges follow the target's size); alternating rounds, each run in a
# fresh process after a warm-up dataset, medians. Floors:
# ENVISAT at most 5 % slower than the baseline, each shipped target within 1.5x of ENVISAT's time per image.
TARGET_RUNS = {
    "envisat": {},
    "cubesat_3u": {"target": "models/cubesat_3u.xml"},
    "upper_stage": {"target": "models/upper_stage.xml"},
}


def target_run_s(extra: dict, n: int, tree: str | None, seed: int = SEED) -> tuple[float, float]:
    """Seconds per image of run_generate (n images, 1024 px, shards of SHARD_SIZE, root seed `seed`) in a fresh
    process whose envisat_pose comes from `tree` (None: the installed one), after a 4-image warm-up dataset of the
    same config: (wall, CPU), CPU the process's and its children's user + system time (less sensitive to other
    load)."""
    import subprocess

    code = ("import json, os, resource, sys, tempfile, shutil, time\n"
            + (f"sys.path.insert(0, {tree!r})\n" if tree else "")
            + "from envisat_pose.config import from_dict\n"
            "from envisat_pose.datagen.generate_config import GenerateConfig\n"
            "from envisat_pose.datagen.factory import run_generate\n"
            f"base = dict(resolution_px=1024, shard_size={SHARD_SIZE}, seed={seed}, **json.loads({json.dumps(extra)!r}))\n"
            "out = tempfile.mkdtemp()\n"
            "run_generate(from_dict(GenerateConfig, dict(base, num_images=4)), os.path.join(out, 'warm'))\n"
            "def cpu():\n"
            "    a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)\n"
            "    return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime\n"
            "t0, c0 = time.perf_counter(), cpu()\n"
            f"run_generate(from_dict(GenerateConfig, dict(base, num_images={n})), os.path.join(out, 'ds'))\n"
            f"print(json.dumps([(time.perf_counter() - t0) / {n}, (cpu() - c0) / {n}]))\n"
            "shutil.rmtree(out)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=dict(os.environ), cwd=tree or os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    if res.returncode != 0:
        raise RuntimeError(f"the run of {extra} in {tree or 'this tree'} failed:\n{res.stderr[-2000:]}")
    wall, cpu = json.loads(res.stdout.strip().splitlines()[-1])
    return float(wall), float(cpu)


def main_targets(args: argparse.Namespace) -> dict:
    """--targets: ENVISAT's time per image against the baseline tree's and the shipped targets' against ENVISAT's
    (the comment above TARGET_RUNS); the results' entry."""
    n = args.images or 24
    out = {"images": n, "rounds": [], "resolution_px": 1024, "seed": args.seed, "baseline": args.baseline,
           "current": args.current, "load_avg_start": os.getloadavg(),
           "machine": {"cpus": os.cpu_count(), "platform": platform.platform()}}
    for r in range(args.rounds):
        row = {}
        if args.baseline:
            row["envisat_baseline"], row["envisat_baseline_cpu"] = target_run_s({}, n, args.baseline, args.seed)
        for name, extra in TARGET_RUNS.items():
            row[name], row[f"{name}_cpu"] = target_run_s(extra, n, args.current, args.seed)
        row["load_avg_1min"] = os.getloadavg()[0]
        out["rounds"].append(row)
        print(f"round {r}: " + ", ".join(f"{k} {v:.3f}" + (" s/img" if k != "load_avg_1min" else "")
                                         for k, v in row.items()), flush=True)
    med = {k: statistics.median(row[k] for row in out["rounds"]) for k in out["rounds"][0] if k != "load_avg_1min"}
    out["median_s_per_image"] = med
    if args.baseline:
        out["envisat_vs_baseline"] = med["envisat"] / med["envisat_baseline"]
        out["envisat_vs_baseline_cpu"] = med["envisat_cpu"] / med["envisat_baseline_cpu"]
        # the floor bounds a slowdown: a faster tree meets it (the two trees differ by every commit between them)
        out["floor_envisat_at_most_5pct_slower_met"] = out["envisat_vs_baseline"] <= 1.05
    for name in TARGET_RUNS:
        if name != "envisat":
            out[f"{name}_vs_envisat"] = med[name] / med["envisat"]
            out[f"floor_{name}_within_1_5x_met"] = out[f"{name}_vs_envisat"] <= 1.5
    out["load_avg_end"] = os.getloadavg()
    print(json.dumps({k: v for k, v in out.items() if k not in ("rounds", "machine")}, indent=1))
    return out


def main_scaling(args: argparse.Namespace) -> dict:
    """--scaling: the scaling floors' table at 512 and 1024 px (module docstring); the results' entry."""
    results = {
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
                    "load_avg_start": os.getloadavg()},
        "protocol": "LP_NUM_THREADS=1 per process; random mode, default config; shard size %d" % SHARD_SIZE,
        "resolutions": {},
    }
    results["machine"]["cpu_scaling_probe_2_processes"] = probe = cpu_scaling_probe()
    print(f"CPU scaling probe (zlib, 2 processes vs 1): {probe:.2f}x")
    rows = []
    for res, n in IMAGES.items():
        n = args.images or n
        cfg = bench_config(res, n, seed=args.seed)
        raw = raw_rates(cfg)
        e1, s1 = end_to_end(cfg, 1)
        e2, s2 = end_to_end(cfg, 2)
        entry = {**raw, "images": n, "e2e_1_worker_img_s": e1, "e2e_2_workers_img_s": e2,
                 "steady_1_worker_img_s": s1, "steady_2_workers_img_s": s2,
                 "ratio_1_worker_to_raw": e1 / raw["raw_lit_render_img_s"], "speedup_2_workers": e2 / e1,
                 "steady_speedup_2_workers": s2 / s1 if s1 and s2 else None}  # None: too few shards
        st = raw["stages_ms"]
        entry["interleaved_ratio_sample_to_raw"] = st["interleaved_raw_lit_ms"] / st["render_sample_in_process_ms"]
        entry["floor_60pct_met"] = entry["ratio_1_worker_to_raw"] >= 0.6
        entry["floor_1_7x_met"] = entry["speedup_2_workers"] >= 1.7
        results["resolutions"][str(res)] = entry
        rows.append((res, raw["raw_lit_render_img_s"], raw["stock_renderer_rgb_depth_seg_img_s"], e1, e2,
                     entry["ratio_1_worker_to_raw"], entry["speedup_2_workers"], s1, s2))
    results["machine"]["load_avg_end"] = os.getloadavg()
    print(f"{'px':>5} {'raw lit':>9} {'stock 3x':>9} {'e2e 1w':>8} {'e2e 2w':>8} {'1w/raw':>7} {'2w/1w':>6}"
          f" {'steady 1w':>10} {'steady 2w':>10}  (images/s)")
    steady = lambda v: f"{'n/a':>10}" if v is None else f"{v:>10.1f}"  # noqa: E731
    for res, raw, stock, e1, e2, ratio, speed, s1, s2 in rows:
        print(f"{res:>5} {raw:>9.1f} {stock:>9.1f} {e1:>8.1f} {e2:>8.1f} {ratio:>7.2f} {speed:>6.2f} {steady(s1)} "
              f"{steady(s2)}")
    for res, entry in results["resolutions"].items():
        print(f"{res} px stages (ms/image, 1 core): " + ", ".join(f"{k} {v:.1f}" for k, v in entry["stages_ms"].items()))
        print(f"{res} px interleaved in-process ratio (sample rate / raw rate): "
              f"{entry['interleaved_ratio_sample_to_raw']:.2f}")
    return results


def main_default_mode(args: argparse.Namespace) -> dict:
    """The default mode's table with the two-pass floor; the results' entry."""
    return {"machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
            "protocol": "LP_NUM_THREADS=1 per process; random mode, default config (sensor camera model), "
                        "shard size %d; e2e = wall clock of run_generate in this process (its renderer made once before); "
                        "worker_startup_serial_s: a fresh process's imports, renderer and Earth textures one after the other; "
                        "worker_startup_counted_s: a fresh process's run less its images at the steady rate; "
                        "floor_issue18: alternating rounds, median ratio" % SHARD_SIZE,
            **default_mode_table(args.images or 64, args.rounds, args.floor_images, args.seed)}


def is_results(data: dict) -> bool:
    """Whether a JSON object is this bench's results: tables each with its machine (or the older "resolutions")."""
    return "resolutions" in data or all(isinstance(v, dict) and "machine" in v for v in data.values())


def write_entry(path: str, key: str, entry: dict) -> None:
    """The results file at `path` with `entry` under `key`, its other keys kept (other machines, other modes,
    earlier tables), atomically; an older single-platform file (a top-level "resolutions") is started afresh."""
    from _common import existing_results, write_json

    everything = existing_results(path, is_results)
    everything = {} if "resolutions" in everything else everything
    write_json(path, everything | {key: entry}, indent=1, sort_keys=True)
    print(f"wrote {path} [{key}]")


def main(argv: list[str] | None = None) -> None:
    from _common import (
        WholeFlagParser,
        count,
        description,
        existing_dir,
        existing_results,
        out_file,
        provenance,
        results_path,
    )

    ap = WholeFlagParser(description=description(__doc__))
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--scaling", "--issue3", action="store_true",
                      help="the scaling floors' table at 512 and 1024 px instead of the default mode's")
    mode.add_argument("--targets", action="store_true",
                      help="the shipped targets' time per image against ENVISAT's (and --baseline's) instead")
    ap.add_argument("--baseline", metavar="DIR", type=existing_dir,
                    help="with --targets: an earlier tree (a git archive, its plugin's .so copied in)")
    ap.add_argument("--current", metavar="DIR", type=existing_dir,
                    help="with --targets: the tree measured (default: the installed one)")
    ap.add_argument("--images", type=count(), help="images per dataset (default: 64; with --targets 24; with --scaling "
                    + " and ".join(f"{n} at {res} px" for res, n in IMAGES.items()) + ")")
    ap.add_argument("--floor-images", type=count(), default=200, help="the two-pass floor's images (default mode)")
    ap.add_argument("--rounds", type=count(), default=3, help="alternating rounds (default mode and --targets)")
    ap.add_argument("--seed", type=count(0), default=SEED, help="the datasets' root seed")
    ap.add_argument("--tag", help="names this machine in the results' key (default: MUJOCO_GL_<cores>cpu)")
    ap.add_argument("--key", default="targets", help="with --targets: the results' key before the tag")
    ap.add_argument("--out", type=out_file, default=results_path("datagen_speed"),
                    help="the results file the table is merged into")
    args = ap.parse_args(argv)
    if (args.baseline or args.current) and not args.targets:
        ap.error("--baseline and --current go with --targets")
    from envisat_pose.datagen.generate_config import GenerateConfig

    if args.floor_images <= GenerateConfig().shard_size:  # a steady rate needs a shard after the first
        ap.error(f"--floor-images {args.floor_images}: expected more than one shard of the default size "
                 f"({GenerateConfig().shard_size} images)")
    existing_results(args.out, is_results)  # a wrong --out refused before the benchmark runs
    tag = args.tag or f"{os.environ['MUJOCO_GL']}_{os.cpu_count()}cpu"
    if args.targets:
        key, entry = f"{args.key}_{tag}", main_targets(args)
    elif args.scaling:
        key, entry = tag, main_scaling(args)  # one entry per platform (GL backend and core count)
    else:
        key, entry = f"issue18_{tag}", main_default_mode(args)  # issue9_* keys: earlier runs, kept
    write_entry(args.out, key, entry | {"provenance": provenance(args)})


if __name__ == "__main__":
    from _common import run_main  # bench/_common.py, beside this script

    run_main(main)
