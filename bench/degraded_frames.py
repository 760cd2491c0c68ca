"""Degraded but honest frames, what a user's real camera gives, tracked with no truth and scored against the truth:
does the tracker ever claim "tracking" while wrong when its images are noisy, blurred, badly exposed, compressed,
smaller, fewer, occluded or flared?

One sequence (`envisat generate --mode sequence`, the scenario, seed, frames and resolution given) is degraded frame
by frame with numpy / OpenCV (each degradation seeded from --seed and its name) and written as a user would hand it
to `envisat track`: an image folder (PNG, or JPEG at the quality named), a timestamps CSV (file,t_s: the labels'
times, so dropped frames leave gaps) and, for frames downscaled whole, a camera file with the intrinsics scaled as
`track` asks for them (camera_file.default_camera's numbers). The track (`envisat track`'s pipeline function, the
shipped detector, the scenario's tuning) is then scored against the labels' truth on every frame it claims
"tracking" (pipelines/runs/scoring.py: wrong is attitude > 5 deg or position > 2 % of range). Per degradation:
frames claimed, claimed while wrong, the largest error over the claimed frames (deg, % of range), the first claim,
the median NIS per degree of freedom over the claimed frames, coasting frames and the coasting frames wrong.
The floor: no frame claimed while wrong, whatever the degradation; the unchanged frames (`none`) as in the
integrity round (default seed 21, 200 frames, 1024 px: 164 claimed, 0 wrong, first claim 35 s).

Run:  .venv/bin/python bench/degraded_frames.py --seed 21 --num-images 200
      (writes bench/results/degraded_frames.json; ~50 s a degradation on 2 cores, ~30 minutes in all)
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import zlib

os.environ.setdefault("MUJOCO_GL", "osmesa")

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

# name: (kind, parameter); see degrade() for what each does
DEGRADATIONS = {
    "none": ("none", 0),
    "gauss_noise_8": ("gauss", 8.0), "gauss_noise_20": ("gauss", 20.0), "gauss_noise_40": ("gauss", 40.0),
    "shot_noise_fw100": ("shot", 100.0), "shot_noise_fw25": ("shot", 25.0),
    "motion_blur_7": ("motion", 7), "motion_blur_15": ("motion", 15), "motion_blur_31": ("motion", 31),
    "defocus_3": ("defocus", 3), "defocus_7": ("defocus", 7), "defocus_13": ("defocus", 13),
    "gain_x4": ("gain", 4.0), "gain_x0.25": ("gain", 0.25), "gain_x16_saturated": ("gain", 16.0),
    "jpeg_q30": ("jpeg", 30), "jpeg_q20": ("jpeg", 20), "jpeg_q10": ("jpeg", 10),
    "resize_512": ("resize", 512), "resize_256": ("resize", 256),
    "drop_every_other": ("drop_alt", 0), "drop_random_30pct": ("drop_random", 0.3),
    "occlude_quadrant": ("quadrant", 0), "occlude_target_20": ("target_box", 20),
    "flare": ("flare", 0), "hot_pixels_dead_columns": ("hot_dead", 0),
}


def fixed_pattern(kind: str, shape: tuple[int, int], rng: np.random.Generator) -> dict:
    """What stays put over a sequence: the motion blur's direction, the flare's place, hot pixels and dead
    columns, the frames the target is occluded on."""
    h, w = shape
    return {"angle_deg": float(rng.uniform(0, 180)),
            "flare_uv": (float(rng.uniform(0.3, 0.7) * w), float(rng.uniform(0.3, 0.7) * h)),
            "hot": rng.random(shape) < 1e-3, "dead_cols": rng.choice(w, size=6, replace=False),
            "occluded_from": 80}


def line_kernel(length: int, angle_deg: float) -> np.ndarray:
    """A motion blur's kernel: a line of `length` px at angle_deg, normalized."""
    k = np.zeros((length, length), np.float32)
    c = (length - 1) / 2.0
    d = np.array([np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))])
    for s in np.linspace(-c, c, 4 * length):
        u, v = np.rint(c + s * d).astype(int)
        k[v, u] = 1.0
    return k / k.sum()


def disk_kernel(radius: int) -> np.ndarray:
    """A defocus blur's kernel: a disk of `radius` px, normalized."""
    y, x = np.mgrid[-radius:radius + 1, -radius:radius + 1]
    k = (x * x + y * y <= radius * radius + 0.5).astype(np.float32)
    return k / k.sum()


def degrade(kind: str, p, img: np.ndarray, k: int, corners_px: np.ndarray, fixed: dict,
            rng: np.random.Generator) -> np.ndarray:
    """Frame k (uint8 gray) degraded by kind with parameter p (DEGRADATIONS); corners_px (8, 2): the truth's, for
    the occlusion over the target only."""
    import cv2

    f = img.astype(np.float32)
    if kind == "gauss":  # read noise of sigma p DN
        f = f + rng.normal(0.0, p, f.shape)
    elif kind == "shot":  # photon noise, p electrons at white (the project draws 8000-30000)
        f = rng.poisson(f / 255.0 * p) * (255.0 / p)
    elif kind == "motion":
        f = cv2.filter2D(f, -1, line_kernel(int(p), fixed["angle_deg"]), borderType=cv2.BORDER_REFLECT)
    elif kind == "defocus":
        f = cv2.filter2D(f, -1, disk_kernel(int(p)), borderType=cv2.BORDER_REFLECT)
    elif kind == "gain":
        f = f * p
    elif kind == "quadrant":  # the image's top-left quarter black
        h, w = f.shape
        f[: h // 2, : w // 2] = 0.0
    elif kind == "target_box" and fixed["occluded_from"] <= k < fixed["occluded_from"] + p:
        lo, hi = np.nanmin(corners_px, axis=0), np.nanmax(corners_px, axis=0)
        u0, v0 = np.maximum(np.floor(lo - 10).astype(int), 0)
        u1, v1 = np.ceil(hi + 10).astype(int)
        f[v0:v1 + 1, u0:u1 + 1] = 0.0
    elif kind == "flare":  # a bright glare blob and a streak through it, fixed in the image
        h, w = f.shape
        y, x = np.mgrid[0:h, 0:w].astype(np.float32)
        u, v = fixed["flare_uv"]
        r2 = (x - u) ** 2 + (y - v) ** 2
        s = 0.06 * w
        f = f + 400.0 * np.exp(-r2 / (2 * s * s)) + 120.0 * np.exp(-np.abs(y - v - 0.3 * (x - u)) / 3.0)
    elif kind == "hot_dead":
        f[fixed["hot"]] = 255.0
        f[:, fixed["dead_cols"]] = 0.0
    return np.clip(np.rint(f), 0, 255).astype(np.uint8)


def kept_frames(kind: str, p, n: int, rng: np.random.Generator) -> np.ndarray:
    """The indices of the frames handed on: every frame but where frames are dropped."""
    if kind == "drop_alt":
        return np.arange(0, n, 2)
    if kind == "drop_random":
        return np.sort(rng.choice(n, size=int(round(n * (1 - p))), replace=False))
    return np.arange(n)


def write_frames(source, frames: list[np.ndarray], name: str, seed: int, folder: str) -> tuple[str, str | None, dict]:
    """The sequence's frames degraded by `name` written as a user's input into folder: frames/, timestamps.csv,
    camera.toml where resized. Returns (timestamps path, camera path or None, the kept frames' truth)."""
    import cv2

    from envisat_pose.geometry import load_camera

    kind, p = DEGRADATIONS[name]
    rng = np.random.default_rng([seed, zlib.crc32(name.encode())])
    fixed = fixed_pattern(kind, frames[0].shape, rng)
    keep = kept_frames(kind, p, len(frames), rng)
    os.makedirs(os.path.join(folder, "frames"))
    rows, truth = ["file,t_s"], {key: v[keep] for key, v in source.truth.items()}
    for k in keep:
        img = degrade(kind, p, frames[k], int(k), source.truth["corners_px"][k], fixed, rng)
        if kind == "resize":
            img = cv2.resize(img, (int(p), int(p)), interpolation=cv2.INTER_AREA)
        file = f"frame_{k:05d}." + ("jpg" if kind == "jpeg" else "png")
        params = [cv2.IMWRITE_JPEG_QUALITY, int(p)] if kind == "jpeg" else []
        cv2.imwrite(os.path.join(folder, "frames", file), img, params)
        rows.append(f"{file},{float(source.t_s[k])!r}")
    stamps = os.path.join(folder, "timestamps.csv")
    with open(stamps, "w", encoding="utf-8") as fh:
        fh.write("\n".join(rows) + "\n")
    camera = None
    if kind == "resize":  # the default camera's intrinsics for frames resized whole, as track's refusal gives them
        cam, s = load_camera(), int(p) / frames[0].shape[1]
        truth["corners_px"] = (truth["corners_px"] + 0.5) * s - 0.5
        small = cam.scaled(int(p), int(p))
        camera = os.path.join(folder, "camera.toml")
        with open(camera, "w", encoding="utf-8") as fh:
            fh.write(f"fx = {small.f_px!r}\nfy = {small.f_px!r}\ncx = {small.cu_px!r}\ncy = {small.cv_px!r}\n"
                     f"width = {int(p)}\nheight = {int(p)}\n")
    return stamps, camera, truth


def score(out_dir: str) -> dict:
    """The track's claimed frames ("tracking") and coasting frames scored against the truth in est.npz."""
    from envisat_pose.io import open_npz
    from envisat_pose.pipelines.runs.scoring import correct_frames, frame_errors
    from envisat_pose.status import COASTING, LOST, TRACKING

    with open_npz(os.path.join(out_dir, "est.npz")) as z:
        t, x_hat, x_true, P = z["t_s"], z["x_hat"][0], z["x_true"][0], z["P"][0]
        status, nis, dof = z["status"][0], z["nis"][0], z["nis_dof"][0]
    claimed, coasting = status == TRACKING, status == COASTING
    has = np.isfinite(x_hat).all(axis=-1) & np.isfinite(P).all(axis=(-2, -1))
    err = frame_errors(x_true, np.where(has[:, None], x_hat, 0.0), np.where(has[:, None, None], P, np.eye(12)))
    wrong = ~correct_frames(err)
    pos_pct = 100.0 * err["position_m"] / err["range_true_m"]
    per_dof = np.where(dof > 0, nis / np.maximum(dof, 1), np.nan)[claimed]
    return {"frames": int(len(t)), "claimed": int(claimed.sum()), "claimed_wrong": int((claimed & wrong).sum()),
            "first_claim_s": float(t[claimed][0]) if claimed.any() else None,
            "first_wrong_claim_s": float(t[claimed & wrong][0]) if (claimed & wrong).any() else None,
            "max_att_deg_claimed": float(err["attitude_deg"][claimed].max()) if claimed.any() else None,
            "max_pos_pct_claimed": float(pos_pct[claimed].max()) if claimed.any() else None,
            "nis_per_dof_median": float(np.nanmedian(per_dof)) if np.isfinite(per_dof).any() else None,
            "frames_coasting": int(coasting.sum()), "coasting_wrong": int((coasting & wrong).sum()),
            "frames_lost": int((status == LOST).sum())}


def track_one(source, frames: list[np.ndarray], name: str, args, work: str) -> dict:
    """One degradation written, tracked and scored (module doc)."""
    import json

    from envisat_pose.pipelines.jobs import resolve_job
    from envisat_pose.pipelines.runs.frames import open_source
    from envisat_pose.pipelines.runs.track import track_frames

    folder = os.path.join(work, name)
    stamps, camera, truth = write_frames(source, frames, name, args.seed, folder)
    user = open_source(os.path.join(folder, "frames"), timestamps=stamps)
    user.truth, user.scenario = truth, args.scenario  # scoring only: the tracker never sees it
    cfg = resolve_job("track", args.scenario, None, dict(args.set))
    out = os.path.join(folder, "track")
    summary = track_frames(cfg, user, camera, None, out, progress=False)
    row = {"degradation": name, "kind": DEGRADATIONS[name][0], "parameter": DEGRADATIONS[name][1], **score(out),
           "last_cold_start_refusal": summary["last_cold_start_refusal"]}
    if args.work:  # kept: the row beside its frames and track
        with open(os.path.join(folder, "row.json"), "w", encoding="utf-8") as fh:
            json.dump(row, fh, indent=1)
    return row


def setting(text: str) -> tuple[str, object]:
    """An argparse type: KEY=VALUE, the value read as TOML's (a number, true/false, a quoted string) or as a bare
    string."""
    import tomllib

    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"{text!r}: expected KEY=VALUE")
    try:
        return key, tomllib.loads(f"v = {value}")["v"]
    except tomllib.TOMLDecodeError:
        return key, value


def main() -> int:
    from _common import WholeFlagParser, count, description, out_file, provenance, results_path, write_json

    from envisat_pose.config import resolve_job_config
    from envisat_pose.datagen.factory import run_generate
    from envisat_pose.datagen.generate_config import GenerateConfig
    from envisat_pose.pipelines.runs.frames import open_source

    p = WholeFlagParser(description=description(__doc__))
    p.add_argument("--scenario", default="default")
    p.add_argument("--seed", type=int, default=21)
    p.add_argument("--num-images", type=count(20), default=200)
    p.add_argument("--resolution", type=count(64), default=1024)
    p.add_argument("--only", nargs="+", choices=list(DEGRADATIONS), metavar="NAME",
                   help=f"these degradations (default: all: {', '.join(DEGRADATIONS)})")
    p.add_argument("--set", type=setting, nargs="+", default=[], metavar="KEY=VALUE",
                   help="track config keys over the scenario's (tracker.bank.evidence_memory=long, say)")
    p.add_argument("--work", help="keep the sequence, the frames and the tracks in this folder (default: a "
                   "temporary one, removed)")
    p.add_argument("--out", type=out_file, default=results_path("degraded_frames"))
    args = p.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="degraded_") as tmp:
        work = args.work or tmp
        seq = os.path.join(work, "seq")
        if not os.path.isdir(seq):
            gcfg = resolve_job_config(GenerateConfig, {}, None, {
                "mode": "sequence", "num_images": args.num_images, "seed": args.seed,
                "resolution": args.resolution, "sequence.scenario": args.scenario})
            run_generate(gcfg, seq)
        source = open_source(seq)
        frames = [img for _, img in source.frames()]
        print(f"{'degradation':<24} {'frames':>6} {'claimed':>7} {'wrong':>5} {'max deg':>7} {'max %':>6} "
              f"{'first s':>7} {'NIS/dof':>7} {'coast':>5}", flush=True)
        for name in args.only or list(DEGRADATIONS):
            r = track_one(source, frames, name, args, work)
            rows.append(r)
            fmt = (lambda v, f: "-" if v is None else format(v, f))
            print(f"{name:<24} {r['frames']:6d} {r['claimed']:7d} {r['claimed_wrong']:5d} "
                  f"{fmt(r['max_att_deg_claimed'], '7.2f')} {fmt(r['max_pos_pct_claimed'], '6.2f')} "
                  f"{fmt(r['first_claim_s'], '7.0f')} {fmt(r['nis_per_dof_median'], '7.3f')} "
                  f"{r['coasting']:5d}", flush=True)
    write_json(args.out, {"bench": "degraded_frames", **provenance(args), "runs": rows}, indent=1)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    from _common import run_main

    run_main(main)
