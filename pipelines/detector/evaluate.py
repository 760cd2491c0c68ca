"""The pipeline of `envisat evaluate`: the corner detector scored against the labels, next to Harris and
Shi-Tomasi, by corruption group and range bin; every number in a JSON file.

Methods: 'detector' (full frames, no label used but K), 'detector_no_lines' (the same weights, corners named
without line verification: the ablation), 'harris' and 'shi_tomasi' (cv2.goodFeaturesToTrack refined by
cornerSubPix, named by oracle nearest-label association: generous to them). Pose: solvePnP (EPnP, then
iterative) from each method's named corners against the label's R_cam_from_target / t_cam_from_target_m.
Groups (perception/evaluate.corruption_groups): all; clean, noise_only, blur_only, combined (a partition);
noise=<level> and blur=<level> (marginals, overlapping the partition); and the range bins of the label's pose
(perception/evaluate.RANGE_GROUPS). Every method's residual bias (perception/evaluate.bias_stats): the apparent
scale of its correctly named corners about their centroid and their signed radial error, per group.
With --roi FILE or --roi-labels a method 'detector_roi' is added: the same detector given a region of interest
per frame (the file's, frames not in it get the coarse pass; or the labels' corners, as the closed loop's
converged prior gives it) instead of its coarse pass. With --refine, 'detector_refined' (and
'detector_roi_refined') are the same with the sub-pixel refinement of the named corners (perception/refine.py).
"""

from __future__ import annotations

import json
import math
import re

from envisat_pose.config import InputError, config_arg, path_arg
from envisat_pose.geometry import load_geometry
from envisat_pose.io import atomic_write_text, json_safe, sha256_file
from envisat_pose.out_dirs import check_out_file, make_out_file_dir
from envisat_pose.out_lock import locks_output
from envisat_pose.pipelines.common.job_defaults import weights_name
from envisat_pose.pipelines.detector.detect import DetectJobConfig, camera_samples, read_roi
from envisat_pose.shard_reader import checked_shards, read_shards, sample_total
from envisat_pose.target import require_envisat_dataset

METHODS = ("detector", "detector_no_lines", "harris", "shi_tomasi")


def make_detector(model, config, device: str):
    """The detector the verb scores (a function so a test can put an oracle network in its place)."""
    from envisat_pose.perception.detect import Detector

    return Detector(model, config, device=device)


def read_poses(paths: list[str]) -> dict[str, tuple]:
    """{sample key: (R_cam_from_target (3, 3), t_cam_from_target_m (3,))} from the shards' labels (the
    perception reader keeps only what detection needs)."""
    import numpy as np

    out = {}
    for _, key, members in read_shards(paths):
        try:
            lab = json.loads(members["json"])
            out[key] = (np.asarray(lab["R_cam_from_target"], float), np.asarray(lab["t_cam_from_target_m"], float))
        except (ValueError, KeyError, TypeError):
            continue  # a label without a pose: its pose error is left out
    return out


def evaluate_frames(detector, ablation, samples, poses: dict, corners_T_m, bar=None, limit: int | None = None,
                    roi=None, refined=None) -> tuple[dict, list[list[str]]]:
    """Run every method on every frame. samples: (key, image, label) as perception.data.read_samples gives them,
    images as the camera saw them. roi: None; 'labels'; or {key: (x0, y0, side)}: adds 'detector_roi'. refined:
    a detector with the sub-pixel refinement, adds 'detector_refined' (and 'detector_roi_refined'). Returns
    per-method arrays and each frame's groups (with its range bin where the pose is known)."""
    import numpy as np

    from envisat_pose.perception import evaluate as ev

    methods = METHODS + (("detector_roi",) if roi is not None else ())
    if refined is not None:
        methods += ("detector_refined",) + (("detector_roi_refined",) if roi is not None else ())
    rows = {m: {"pred": [], "alt": [], "amb": [], "vis": [], "cov": [], "pose": []} for m in methods}
    true, usable, groups = [], [], []
    for i, (key, image, label) in enumerate(samples):
        if limit is not None and i >= limit:
            break
        use = label["visible"] & label["in_frame"]
        true.append(label["corners_px"])
        usable.append(use)
        frame_groups = ev.corruption_groups(*ev.corruption_levels(label["corruption"], image.shape[1]))
        rg = ev.range_group(float(np.linalg.norm(poses[key][1]))) if key in poses else None
        groups.append(frame_groups + ([rg] if rg else []))
        found = {}
        for name, det in (("detector", detector), ("detector_no_lines", ablation)):
            f = det.detect(image, label["K"])
            found[name] = (f.corners_px, f.alt_corners_px, f.ambiguous, f.visible, f.cov_px)
        box = None
        if roi is not None:
            box = ev.label_roi(label["corners_px"], image.shape) if roi == "labels" else roi.get(key)
        for name, det, b in (("detector_roi", detector, box), ("detector_refined", refined, None),
                             ("detector_roi_refined", refined, box)):
            if name in methods:
                f = det.detect(image, label["K"], roi_px=b)
                found[name] = (f.corners_px, f.alt_corners_px, f.ambiguous, f.visible, f.cov_px)
        for name, harris in (("harris", True), ("shi_tomasi", False)):
            pts = ev.associate_nearest(ev.classical_corners(image, harris), label["corners_px"], use)
            found[name] = (pts, pts, False, np.isfinite(pts[:, 0]), np.full((8, 2, 2), np.nan))
        for name, (pred, alt, amb, vis, cov) in found.items():
            r = rows[name]
            for k, v in zip(("pred", "alt", "amb", "vis", "cov"), (pred, alt, amb, vis, cov)):
                r[k].append(v)
            chosen, _ = ev.better_naming(pred[None], alt[None], np.array([amb]), label["corners_px"][None],
                                         use[None])
            pose = ev.pose_from_corners(chosen[0], label["K"], corners_T_m)
            err = (np.nan, np.nan)
            if pose is not None and key in poses:
                err = ev.pose_errors(*pose, *poses[key])
            r["pose"].append(err)
        if bar is not None:
            bar.update(1)
    arrays = {m: {k: np.array(v) for k, v in r.items()} for m, r in rows.items()}
    arrays["truth"] = {"true": np.array(true), "usable": np.array(usable)}
    return arrays, groups


def summarize(arrays: dict, groups: list[list[str]]) -> dict:
    """{group: {method: metrics}} for every group of perception.evaluate.GROUP_ORDER ({'frames': 0} when empty)."""
    import numpy as np

    from envisat_pose.perception import evaluate as ev

    out = {}
    methods = [m for m in arrays if m != "truth"]
    for g in list(ev.GROUP_ORDER) + list(ev.RANGE_GROUPS):
        sel = np.array([g in gs for gs in groups], bool)
        out[g] = {}
        for m in methods:
            if not sel.any():
                out[g][m] = {"frames": 0}
                continue
            a, t = arrays[m], arrays["truth"]
            classical = m in ("harris", "shi_tomasi")
            out[g][m] = ev.score_method(
                a["pred"][sel], t["true"][sel], t["usable"][sel], alt_px=a["alt"][sel], ambiguous=a["amb"][sel],
                pred_visible=None if classical else a["vis"][sel], cov_px=None if classical else a["cov"][sel],
                pose_err=a["pose"][sel])
    return out


def _fmt(x, spec: str) -> str:
    """x in its column's format; an absent value as '-' padded to the column's width (the spec's leading digits)."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        width = re.match(r"[+-]?(\d*)", spec).group(1)
        return "-".rjust(int(width) if width else 1)
    return format(x, spec)


def groups_table(summary: dict) -> str:
    """One line per non-empty group and method."""
    head = (f"{'group':14s} {'method':18s} {'frames':>6s} {'med px':>7s} {'p95 px':>7s} {'PCK@2':>6s} {'PCK@5':>6s} "
            f"{'swaps':>6s} {'ambig':>6s} {'vis P':>6s} {'vis R':>6s} {'NEES':>6s} {'t m':>7s} {'rot deg':>7s} "
            f"{'scale':>7s} {'radial px':>9s}")
    lines = [head, "-" * len(head)]
    for g, per in summary.items():
        for m, s in per.items():
            if not s.get("frames"):
                continue
            vis, cal, pose, bias = (s.get(k, {}) for k in ("visibility", "calibration", "pose", "bias"))
            lines.append(
                f"{g:14s} {m:18s} {s['frames']:6d} {_fmt(s['errors']['all']['median_px'], '7.2f')} "
                f"{_fmt(s['errors']['all']['p95_px'], '7.2f')} {_fmt(s['pck_2px'], '6.1%')} "
                f"{_fmt(s['pck_5px'], '6.1%')} {_fmt(s['swap_rate_strict'], '6.1%')} "
                f"{_fmt(s['ambiguous_share'], '6.1%')} {_fmt(vis.get('precision'), '6.1%')} "
                f"{_fmt(vis.get('recall'), '6.1%')} {_fmt(cal.get('mean_nees'), '6.2f')} "
                f"{_fmt(pose.get('translation_m_median'), '7.3f')} {_fmt(pose.get('rotation_deg_median'), '7.2f')} "
                f"{_fmt(bias.get('scale_mean'), '7.4f')} {_fmt(bias.get('radial_px_mean'), '+9.3f')}")
    return "\n".join(lines)


def evaluate_detector(weights: str, samples, poses: dict, json_path: str, *, device: str = "cpu",
                      limit: int | None = None, roi=None, refine: bool = False, data_name: str = "",
                      roi_name: str | None = None, progress: bool = False, skipped_shards: list[str] = (),
                      total: int | None = None) -> dict:
    """Score the detector of `weights` on samples ((key, image, label) as the camera saw them) and write every
    number to json_path (its folder made then, parents too). poses: {key: (R, t)} (read_poses); roi: None,
    'labels', or {key: (x0, y0, side)} (adds detector_roi; roi_name: how the JSON names a dict roi, its file);
    refine: adds the refined methods; data_name: the dataset as the JSON names it; skipped_shards: the damaged
    shards the samples left out (shard_reader.checked_shards), recorded; total: the samples' count for the progress
    bar (None: unknown). Returns the JSON's content (its 'groups'
    is the summary)."""
    import dataclasses

    from tqdm import tqdm

    from envisat_pose.perception.detect import DetectConfig, weights_cov_scale, weights_refine_floor
    from envisat_pose.perception.evaluate import corruption_groups
    from envisat_pose.perception.weights import load_model

    check_out_file(json_path, "json_path")
    model = load_model(weights, device)
    cfg = DetectConfig(cov_scale=weights_cov_scale(weights), refine_cov_floor_px2=weights_refine_floor(weights))
    detector = make_detector(model, cfg, device)
    ablation = make_detector(model, dataclasses.replace(cfg, line_verification=False), device)
    refined = make_detector(model, dataclasses.replace(cfg, refine=True), device) if refine else None
    bar = tqdm(disable=not progress, desc="evaluate", unit="frame", total=total if limit is None or total is None
               else min(total, limit))
    arrays, groups = evaluate_frames(detector, ablation, samples, poses, load_geometry().corners_T_m, bar=bar,
                                     limit=limit, roi=roi, refined=refined)
    bar.close()
    if not groups:
        raise InputError(f"data {data_name!r}: no frames")
    summary = summarize(arrays, groups)
    result = {"weights": weights_name(weights), "weights_sha256": sha256_file(weights), "data": data_name,
              "frames": len(groups), "model": model.cfg.to_dict(),
              "detect_config": dataclasses.asdict(cfg), "match_px": 5.0,
              "roi": roi if isinstance(roi, str) or roi is None else (roi_name or "given"),
              "grouping": corruption_groups.__doc__ + " Levels: perception.evaluate.corruption_levels.",
              "skipped_damaged_shards": list(skipped_shards), "groups": summary}
    make_out_file_dir(json_path, "json_path")
    atomic_write_text(json_path, json.dumps(json_safe(result), indent=1, allow_nan=False) + "\n")
    return result


@locks_output("json_path", "evaluate", folder=False)
def run_evaluate(cfg: DetectJobConfig, data: str, json_path: str, *, roi_labels: bool = False,
                 progress: bool = False) -> dict:
    """`envisat evaluate` as one call (ENVISAT's corner detector; another target's keypoint detector:
    evaluate_target.evaluate_target_detector): the labelled dataset folder `data` (an ENVISAT dataset; with
    cfg.skip_damaged its damaged shards left out and named) as the camera saw it, scored by evaluate_detector with
    cfg's weights, device, limit and refine; cfg.roi (a regions-of-interest file) or roi_labels (the labelled
    corners' region) adds the method detector_roi. Every number goes to json_path; returns the JSON's content."""
    cfg, data = config_arg(cfg, DetectJobConfig), path_arg(data, "data")
    json_path = path_arg(json_path, "json_path")
    if cfg.roi is not None and roi_labels:
        raise InputError(f"roi {cfg.roi!r} and roi_labels: one region of interest at most")
    check_out_file(json_path, "json_path", data)
    require_envisat_dataset(data, "data", "evaluate")
    paths, skipped = checked_shards(data, cfg.skip_damaged, "data")
    roi = read_roi(cfg.roi) if cfg.roi else ("labels" if roi_labels else None)
    return evaluate_detector(cfg.weights, camera_samples(paths), read_poses(paths), json_path, device=cfg.device,
                             limit=cfg.limit, roi=roi, refine=cfg.refine, data_name=data, roi_name=cfg.roi,
                             progress=progress, skipped_shards=skipped, total=sample_total(paths))
