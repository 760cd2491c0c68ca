"""Where the foreign frames' scale bias comes from: the shipped detector's corners against the true
projected corners, frame by frame, under conditions that add the foreign frames' differences one at a time.

The poses and sun are those of bench/foreign_frames.py (`envisat generate --mode sequence`'s truth, the seed's lit
sun); every condition sees the same frames:
- own:              the project's own render of the poses (`envisat generate`, storage clean, the space camera of
                    its labels applied on read, as `envisat track` sees a generate folder);
- filament_ideal:   Filament's render (bench/foreign_frames.FilamentRenderer), no habits at all;
- filament_sensor:  Filament + the sensor (Poisson-Gaussian noise, pedestal) + JPEG, an ideal lens;
- filament_lens:    Filament + the lens alone (distortion, principal point offset; rounded to 8 bits), then the
                    tracker's own path back to a pinhole (camera.toml -> pipelines/tracking/camera_file.py -> cv2.remap);
- filament_full:    every habit (the frames bench/foreign_frames.py writes), the tracker's path back.
The truth of each condition is the labels' projection through the camera the tracker uses (the MJCF's pinhole, or
camera_file's pinhole of camera.toml). The detector runs as in a converged track: its region of interest from the
true pose (tracker.predicted_roi), the true pose as the naming's prior. Per frame, over the corners both visible
in the truth and found: the radial scale s about the true corners' centroid c (least squares, (d - c) = s (t - c)),
the mean offset d - t, and the errors |d - t|. s < 1: the target looks small, the range comes out long by
about (1/s - 1) x range.

Geometry apart from shading and materials, per Filament frame: the box's silhouette in Filament's segmentation pass
(draw mode SEGMENTATION_BY_ID) against the true corners' outline, and the lit frame's box edges against it (the area method
of bench/silhouette_bias.edge_offsets, offsets px, + outward); the same for the project's renders (its mask and
its clean lit frame).

Run:  .venv/bin/python bench/foreign_scale.py --seed 0 --num-images 300 --stride 6 --resolution 512
      (every 6th frame of bench/adapt.py's sequence; writes bench/results/foreign_scale.json; a few minutes on 2
      cores). The sensor's noise is drawn per scored frame, so with a stride above 1 its draws differ from the
      frames foreign_frames writes (the same distribution).
"""

from __future__ import annotations

import json
import os
import platform
import sys
import tempfile
import time

os.environ.setdefault("MUJOCO_GL", "osmesa")

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

OUTLIER_PX = 2.0  # a corner found farther than this from its truth is another feature, not a biased corner
CONDITIONS = ("own", "filament_ideal", "filament_sensor", "filament_lens", "filament_full")


def frame_scale(det_px: np.ndarray, true_px: np.ndarray) -> tuple[float, np.ndarray] | None:
    """(s, mean offset (2,)) of one frame's detected corners det_px (K, 2) against the true ones true_px (K, 2)
    (rows both finite), or None below 4 corners: s minimizes |(d - c) - s (t - c)|^2 with c the true centroid."""
    if len(det_px) < 4:
        return None
    c = true_px.mean(axis=0)
    a, b = true_px - c, det_px - c
    return float(np.sum(a * b) / np.sum(a * a)), (det_px - true_px).mean(axis=0)


def summarize(rows: list[dict]) -> dict:
    """The condition's figures over its frames' rows (frame_scale per frame, and the per-corner errors)."""
    s = np.array([r["s"] for r in rows if r["s"] is not None])
    off = np.array([r["offset"] for r in rows if r["s"] is not None]).reshape(-1, 2)
    err = np.concatenate([r["err"] for r in rows]) if rows else np.zeros(0)
    rad = np.array([r["radius_px"] for r in rows if r["s"] is not None])
    n = len(s)
    return {"frames_scored": int(n), "corners": int(len(err)), "outliers": int(sum(r["outliers"] for r in rows)),
            "scale_median": float(np.median(s)) if n else None,
            "scale_mean": float(s.mean()) if n else None,
            "scale_se": float(s.std(ddof=1) / np.sqrt(n)) if n > 1 else None,
            "scale_pct": float(100 * (np.median(s) - 1)) if n else None,
            "radial_px_median": float(np.median((s - 1) * rad)) if n else None,
            "offset_px_mean": off.mean(axis=0).tolist() if n else None,
            "err_px_median": float(np.median(err)) if len(err) else None,
            "err_px_mean": float(err.mean()) if len(err) else None}


class Detection:
    """The shipped detector run as in a converged track: ROI and prior pose from the truth."""

    def __init__(self):
        from envisat_pose.perception.detect import load_detector
        from envisat_pose.perception.weights import shipped_weights_path
        from envisat_pose.pipelines.tracking.tracker_config import RoiConfig

        self.det = load_detector(shipped_weights_path())
        self.roi_cfg = RoiConfig()

    def corners(self, image: np.ndarray, x: np.ndarray, camera) -> np.ndarray:
        """(8, 2) detected corners (NaN: not found) in image (H, W) uint8 for the true state x (12,)."""
        from envisat_pose.attitude import mrp_to_dcm
        from envisat_pose.pipelines.tracking.tracker_frame import predicted_roi
        from envisat_pose.state import MRP

        roi = predicted_roi(x, np.eye(12) * 1e-6, camera, self.roi_cfg)
        R_K = camera.R_K_from_C @ mrp_to_dcm(x[MRP]).T
        t_K = camera.R_K_from_C @ (x[:3] - camera.pos_C_m)
        fd = self.det.detect(image, camera.K, roi_px=roi, prior_R_cam_from_target=R_K, prior_t_cam_from_target_m=t_K)
        if int(np.sum(fd.visible)) < self.roi_cfg.min_keypoints:
            fd = self.det.detect(image, camera.K, roi_px=None, prior_R_cam_from_target=R_K,
                                 prior_t_cam_from_target_m=t_K)
        return np.where(fd.visible[:, None], fd.corners_px, np.nan)


def score_frame(det_px: np.ndarray, true_px: np.ndarray, use: np.ndarray) -> dict:
    """One frame's row: the scale and offset over the inliers (found, visible in the truth, within OUTLIER_PX of
    it: a corner hidden behind the array is 'visible' to the face test and the detector puts it where the
    array's edge crosses the box's, pixels away), the inliers' errors, the outlier count."""
    found = use & np.isfinite(det_px).all(axis=1)
    e = np.linalg.norm(np.nan_to_num(det_px - true_px, nan=1e9), axis=1)
    ok = found & (e < OUTLIER_PX)
    d, t = det_px[ok], true_px[ok]
    fs = frame_scale(d, t)
    return {"s": None if fs is None else fs[0], "offset": None if fs is None else fs[1].tolist(),
            "radius_px": float(np.linalg.norm(t - t.mean(axis=0), axis=1).mean()) if len(t) else 0.0,
            "err": e[ok], "outliers": int((found & ~ok).sum())}


def edge_rows(image: np.ndarray, mask: np.ndarray, corners_px: np.ndarray, use: np.ndarray) -> dict:
    """Edge offsets (px, + outward) of the lit image and of the mask's box against the true outline."""
    from silhouette_bias import edge_offsets

    body = np.where((mask >= 1) & (mask <= 6), 200, 0).astype(np.uint8)
    return {"lit": [o for o, _ in edge_offsets(image, mask, corners_px, use)],
            "mask": [o for o, _ in edge_offsets(body, mask, corners_px, use)]}


def edge_summary(v: list[float]) -> dict:
    a = np.asarray(v, float)
    return {"n": int(len(a)), "mean_px": float(a.mean()) if len(a) else None,
            "median_px": float(np.median(a)) if len(a) else None,
            "se_px": float(a.std() / np.sqrt(len(a))) if len(a) > 1 else None}


def own_frames(cfg_json: str, n: int, work: str):
    """The project's renders of the sequence: (what the tracker sees, clean frame, mask, label) per frame."""
    from envisat_pose.config import from_dict
    from envisat_pose.datagen.corrupt import apply_corruption
    from envisat_pose.datagen.factory import run_generate
    from envisat_pose.datagen.generate_config import GenerateConfig, nest_moved_keys
    from envisat_pose.datagen.shards import decode_png
    from envisat_pose.shard_reader import read_shard

    d = nest_moved_keys(json.loads(cfg_json))
    d.update(storage="clean", shard_size=n)
    cfg = from_dict(GenerateConfig, {k: v for k, v in d.items() if k in GenerateConfig.__dataclass_fields__})
    out = os.path.join(work, "own")
    manifest = run_generate(cfg, out)
    for entry in manifest["shards"]:
        for _, members in read_shard(os.path.join(out, entry["name"])):
            label = json.loads(members["json"])
            clean = decode_png(members["png"])
            yield apply_corruption(clean, label["corruption"]), clean, decode_png(members["mask.png"]), label


def run(scenario: str, seed: int, n: int, res: int, work: str, stride: int = 1) -> dict:
    import cv2
    import foreign_frames as ff

    from envisat_pose.attitude import mrp_to_dcm
    from envisat_pose.geometry import load_camera
    from envisat_pose.pipelines.adaptation.pseudo_labels import corner_labels
    from envisat_pose.pipelines.tracking.camera_file import camera_from_intrinsics
    from envisat_pose.state import MRP, POS

    t_s, x, sun_C, eclipse, cfg_json = ff.sequence_truth(scenario, seed, n, res)
    det = Detection()
    rows = {c: [] for c in CONDITIONS}
    edges = {"own": {"lit": [], "mask": []}, "filament": {"lit": [], "mask": []}}
    timing = {}

    t0 = time.perf_counter()
    cam_own = load_camera().scaled(res, res)
    picked = np.arange(0, len(t_s), stride)
    for k, (seen, clean, mask, label) in enumerate(own_frames(cfg_json, n, work)):
        if k % stride:
            continue
        q = np.asarray(label["corners_px"], float)
        use = np.asarray(label["visible"], bool) & np.asarray(label["in_frame"], bool)
        if not np.allclose(np.asarray(label["x"]), x[k], atol=1e-9):
            raise RuntimeError(f"frame {k}: the generate labels' pose is not the foreign frames' pose")
        rows["own"].append(score_frame(det.corners(seen, x[k], cam_own), q, use))
        for key, v in edge_rows(clean, mask, q, use).items():
            edges["own"][key] += v
    timing["own_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    renderer = ff.FilamentRenderer(res)
    habits = ff.Habits()
    K_i = ff.ideal_K(res, renderer.f_px)
    K_c = ff.foreign_K(res, renderer.f_px, habits)
    maps = ff.distortion_maps(res, K_i, K_c, habits.distortion)
    toml = os.path.join(work, "camera.toml")
    with open(toml, "w") as fh:
        fh.write(ff.camera_toml_text(K_c, res, habits.distortion))
    cam_user, remap = camera_from_intrinsics(toml)
    no_lens = ff.Habits(distortion=(0.0, 0.0, 0.0, 0.0), principal_offset_frac=(0.0, 0.0))
    rng_full = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0xF0E1,)))  # foreign_frames' own
    rng_sensor = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0xF0E1,)))
    identity = tuple(np.meshgrid(np.arange(res, dtype=np.float32), np.arange(res, dtype=np.float32)))
    ideal_lab = corner_labels(x, cam_own)
    user_lab = corner_labels(x, cam_user)
    use_all = ideal_lab["visible"] & ideal_lab["in_frame"]
    use_user = user_lab["visible"] & user_lab["in_frame"]

    def decode(frame: np.ndarray, quality: int) -> np.ndarray:
        data, _ = ff.encode_frame(frame, quality)
        return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)

    def to_pinhole(frame: np.ndarray) -> np.ndarray:
        return cv2.remap(frame, remap[0], remap[1], cv2.INTER_LINEAR)

    for k in picked:
        ideal = renderer.render(x[k, POS], mrp_to_dcm(x[k, MRP]).T, None if eclipse[k] else sun_C[k])
        mask = renderer.segmentation()
        lens = np.clip(np.rint(cv2.remap(ideal.astype(np.float32), maps[0], maps[1], cv2.INTER_LINEAR,
                                         borderValue=0.0)), 0, 255).astype(np.uint8)
        sensor = decode(ff.camera_habits(ideal, identity, no_lens, rng_sensor), habits.jpeg_quality)
        full = decode(ff.camera_habits(ideal, maps, habits, rng_full), habits.jpeg_quality)
        q_i, q_u = ideal_lab["corners_px"][k], user_lab["corners_px"][k]
        rows["filament_ideal"].append(score_frame(det.corners(ideal, x[k], cam_own), q_i, use_all[k]))
        rows["filament_sensor"].append(score_frame(det.corners(sensor, x[k], cam_own), q_i, use_all[k]))
        rows["filament_lens"].append(score_frame(det.corners(to_pinhole(lens), x[k], cam_user), q_u, use_user[k]))
        rows["filament_full"].append(score_frame(det.corners(to_pinhole(full), x[k], cam_user), q_u, use_user[k]))
        for key, v in edge_rows(ideal, mask, q_i, use_all[k]).items():
            edges["filament"][key] += v
    timing["filament_s"] = time.perf_counter() - t0
    rng_m = float(np.median(np.linalg.norm(x[picked][:, POS], axis=1)))
    out = {"scenario": scenario, "seed": seed, "sequence_frames": int(len(t_s)), "stride": stride,
           "frames": int(len(picked)), "resolution_px": res,
           "median_range_m": rng_m, "f_px_filament": float(renderer.f_px), "f_px_project": float(cam_own.f_px),
           "conditions": {c: summarize(rows[c]) for c in CONDITIONS},
           "per_frame": {c: {"scale": [r["s"] for r in rows[c]], "offset_px": [r["offset"] for r in rows[c]]}
                         for c in CONDITIONS},
           "edges_px": {who: {k: edge_summary(v) for k, v in e.items()} for who, e in edges.items()},
           "timing_s": timing}
    for c in CONDITIONS:
        s = out["conditions"][c]["scale_median"]
        out["conditions"][c]["range_bias_m"] = None if s is None else float((1.0 / s - 1.0) * rng_m)
    return out


def table(r: dict) -> str:
    f = (lambda v, fmt: "-" if v is None else format(v, fmt))
    lines = [f"{r['scenario']} seed {r['seed']}, {r['frames']} frames (every {r['stride']} of "
             f"{r['sequence_frames']}) at {r['resolution_px']} px, median range "
             f"{r['median_range_m']:.1f} m",
             "| condition | frames | corners (outliers) | scale (median) | +- se | radial px | range bias | mean offset px "
             "| median err px |", "|---|---|---|---|---|---|---|---|---|"]
    for c, s in r["conditions"].items():
        off = s["offset_px_mean"]
        lines.append(f"| {c} | {s['frames_scored']} | {s['corners']} ({s['outliers']}) | {f(s['scale_pct'], '+.3f')} % | "
                     f"{f(s['scale_se'] and 100 * s['scale_se'], '.3f')} % | {f(s['radial_px_median'], '+.3f')} | "
                     f"{f(s['range_bias_m'] and 100 * s['range_bias_m'], '+.1f')} cm | "
                     f"{'-' if off is None else f'({off[0]:+.2f}, {off[1]:+.2f})'} | {f(s['err_px_median'], '.3f')} |")
    lines.append("| edges (px, + outward) | n | mean | median | se |")
    lines.append("|---|---|---|---|---|")
    for who, e in r["edges_px"].items():
        for k, s in e.items():
            lines.append(f"| {who} {k} | {s['n']} | {f(s['mean_px'], '+.3f')} | {f(s['median_px'], '+.3f')} | "
                         f"{f(s['se_px'], '.3f')} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from _common import WholeFlagParser, count, description, out_file, provenance, write_json  # bench/_common.py

    ap = WholeFlagParser(description=description(__doc__))
    ap.add_argument("--scenario", default="default")
    ap.add_argument("--seed", type=count(0), default=0)
    ap.add_argument("--num-images", type=count(), default=300, help="the sequence's frames")
    ap.add_argument("--stride", type=count(), default=6, help="score every stride-th frame")
    ap.add_argument("--resolution", type=count(), default=512)
    ap.add_argument("--threads", type=count(), default=2)
    ap.add_argument("--work", help="folder for the project's renders (default: a temporary one)")
    ap.add_argument("--out", type=out_file, default=os.path.join(HERE, "results", "foreign_scale.json"))
    a = ap.parse_args(argv)
    import foreign_frames as ff
    import torch

    problem = ff.filament_problem()
    if problem:
        print(f"foreign_scale: {problem}", file=sys.stderr)
        return 2
    torch.set_num_threads(a.threads)
    with tempfile.TemporaryDirectory() as tmp:
        r = run(a.scenario, a.seed, a.num_images, a.resolution, a.work or tmp, a.stride)
    r["machine"] = {"cpus": os.cpu_count(), "platform": platform.platform(), "python": sys.version.split()[0]}
    r["provenance"] = provenance(a)
    r["argv"] = sys.argv[1:] if argv is None else argv
    write_json(a.out, r, indent=1)
    print(table(r))
    return 0


if __name__ == "__main__":
    from _common import run_main  # bench/_common.py, beside this script

    run_main(main)
