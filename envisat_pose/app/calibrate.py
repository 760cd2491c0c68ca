"""`envisat calibrate`: fit the detector's covariance scale on held-out labelled frames and ship it in the weights;
on held-out sequences, also the error model a filter needs (issue 16, item 5).

The network's 2x2 covariance per corner is scaled by one factor s (C -> s C) so that the mean of e^T C^-1 e over
correctly named visible corners is 2, the chi-square-2 mean (perception/calibrate.py). The factor goes into the
weights file's metadata (`cov_scale`), where `load_detector` and the verbs that detect read it; the result per
corruption group is printed and stored beside it (`cov_calibration`).

When every --data folder is a sequence (`envisat generate --mode sequence`: consecutive frames of one simulated
truth), the frame-to-frame correlation of the errors, the AR(1) coefficient, the variance inflation for a filter
that takes them as white and the residual bias (apparent scale, radial error) are measured too
(perception/errormodel.py) and stored as `error_model` (the ErrorModel's JSON: what `load_detector` exposes as
`detector.error_model`) and `error_model_record` (every number measured). `--roi labels` detects in the region
of interest the labels give (the closed loop's, with a perfect prior) instead of the coarse pass.

`--refine` calibrates the sub-pixel refinement's covariance instead (DetectConfig.refine, perception/refine.py):
the variance floor f added to the line fits' covariances of the refined corners (C + f I; the fits see the
pixel noise, not the misfit of the model), written as `refine_cov_floor_px2` (with `refine_cov_calibration`);
the network's cov_scale and the error model are left as they are.
"""

from __future__ import annotations

import argparse
import json
import os

from envisat_pose.config import InputError
from envisat_pose.provenance import dataset_ref


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "calibrate",
        help="fit the detector's pixel-covariance scale (and, on sequences, its error model); write weights that "
        "carry it",
        description="Detect the corners of every frame of held-out labelled datasets (not used in training), "
        "take the correctly named visible corners, fit the scale s that brings the mean e^T (s C)^-1 e to 2, and "
        "write a copy of the weights with s in their metadata. Prints the calibration per corruption group. When "
        "every dataset is a sequence (envisat generate --mode sequence), also measures the errors' frame-to-frame "
        "autocorrelation, AR(1) coefficient, variance inflation and residual bias, stored as 'error_model'.",
    )
    p.add_argument("--weights", metavar="W.safetensors", help="detector weights (default: the shipped weights)")
    p.add_argument("--data", required=True, nargs="+", metavar="DIR",
                   help="held-out labelled dataset folder(s) (shards); one sequence per folder")
    p.add_argument("--out", required=True, metavar="OUT.safetensors", help="calibrated weights (may equal --weights)")
    p.add_argument("--roi", choices=("coarse", "labels"), default="coarse",
                   help="coarse: the detector's own coarse pass (default); labels: the region of interest of the "
                   "labelled corners (extent x the crop margin, at least 64 px), as the closed loop gives it")
    p.add_argument("--keep-scale", action="store_true",
                   help="leave the weights' cov_scale and cov_calibration as they are (write the error model only)")
    p.add_argument("--refine", action="store_true",
                   help="fit the sub-pixel refinement's covariance floor (refine_cov_floor_px2) on the refined "
                   "corners instead; cov_scale and the error model are kept")
    p.add_argument("--face-cue", action="store_true",
                   help="fit the half-turn's appearance cue (perception/facecue.py) on the labelled frames of --data "
                   "instead, its temperature on --held-out; stored as 'face_cue'")
    p.add_argument("--held-out", nargs="+", metavar="DIR",
                   help="with --face-cue: labelled folders (not in --data) that fit the cue's temperature and its "
                   "record (default: the odd frames of --data, the even ones fitting the cue)")
    p.add_argument("--max-lag", type=int, default=20, help="autocorrelation lags measured (default 20)")
    p.add_argument("--limit", type=int, help="only the first N frames of each dataset")
    p.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_calibrate_cli)


def collect_frames(detector, samples, limit: int | None = None, bar=None, roi: str = "coarse") -> dict:
    """Per frame: key (T,), err_px (T, 8, 2) = detected - label of the usable corners named right within the
    match radius (NaN elsewhere; an ambiguous frame with its better naming), cov_px (T, 8, 2, 2) as the detector
    gives them (their names follow the naming), group (T,) the corruption group, scale (T,) the apparent scale
    and radial_px (T, 8) (perception/errormodel.py), R_cam_from_target (T, 3, 3) the labels' view. roi
    'labels': detect in the labels' region of interest."""
    import numpy as np

    from envisat_pose.perception import errormodel as em
    from envisat_pose.perception import evaluate as ev

    rows = {k: [] for k in ("key", "err_px", "cov_px", "group", "scale", "radial_px", "refined", "R_cam_from_target")}
    for i, (key, image, label) in enumerate(samples):
        if limit is not None and i >= limit:
            break
        use = label["visible"] & label["in_frame"]
        true = label["corners_px"]
        if roi == "labels":
            f = detector.detect(image, label["K"], roi_px=ev.label_roi(true, image.shape))
        else:
            f = detector.detect(image, label["K"])
        chosen, used_alt = ev.better_naming(f.corners_px[None], f.alt_corners_px[None], np.array([f.ambiguous]),
                                            true[None], use[None])
        # the alternative naming's corners are the same candidates, renamed: their covariances follow them
        cov = f.cov_px[ev.HALF_TURN_PERM] if used_alt[0] else f.cov_px
        refined = np.zeros(8, bool) if getattr(f, "refined", None) is None else np.asarray(f.refined, bool)
        refined = refined[ev.HALF_TURN_PERM] if used_alt[0] else refined
        hit = ev.hits(chosen, true[None], use[None], ev.MATCH_PX)[0] & np.all(np.isfinite(cov), axis=(1, 2))
        wrong = use & np.isfinite(chosen[0, :, 0]) & ~hit
        rows["key"].append(key)
        rows["err_px"].append(np.where(hit[:, None], chosen[0] - true, np.nan))
        rows["cov_px"].append(cov)
        rows["group"].append(ev.corruption_groups(*ev.corruption_levels(label["corruption"], image.shape[1]))[1])
        rows["scale"].append(em.apparent_scale(chosen, true[None], hit[None], wrong[None])[0])
        rows["radial_px"].append(em.radial_errors(chosen, true[None], hit[None])[0])
        rows["refined"].append(refined & hit)
        rows["R_cam_from_target"].append(np.asarray(label["R_cam_from_target"], dtype=float))
        if bar is not None:
            bar.update(1)
    if not rows["key"]:
        raise InputError("no frames")
    return {k: np.array(v) for k, v in rows.items()}


def collect_errors(detector, samples, limit: int | None = None, bar=None, roi: str = "coarse"):
    """Errors e (M, 2) px, covariances C (M, 2, 2) px^2 (as the detector gives them) and the corruption group of
    the frame (M,) of every usable corner named right within the match radius (an ambiguous frame with its better
    naming)."""
    return flat_errors(collect_frames(detector, samples, limit, bar, roi))


def flat_errors(frames: dict, refined: bool | None = None):
    """collect_errors' (err (M, 2), cov (M, 2, 2), group (M,)) from collect_frames' per-frame arrays; only the
    refined corners with refined=True, only the others with refined=False."""
    import numpy as np

    hit = np.isfinite(frames["err_px"][..., 0])
    if refined is not None:
        hit = hit & (frames["refined"] if refined else ~frames["refined"])
    groups = np.repeat(frames["group"], hit.sum(axis=1)).astype(str)
    return frames["err_px"][hit], frames["cov_px"][hit], groups


def is_sequence(path: str) -> bool:
    """Whether a dataset folder was made by `envisat generate --mode sequence` (its manifest's config)."""
    try:
        with open(os.path.join(path, "manifest.json")) as fh:
            return json.load(fh).get("config", {}).get("mode") == "sequence"
    except (OSError, ValueError, AttributeError):
        return False


def frame_interval_s(path: str) -> float:
    """A sequence dataset's frame interval, s (its manifest's config)."""
    with open(os.path.join(path, "manifest.json")) as fh:
        return float(json.load(fh)["config"].get("frame_dt_s", 1.0))


def sequence_input(frames: dict, dt_s: float) -> dict:
    """One sequence of perception.errormodel.measure from collect_frames' arrays, in frame (key) order."""
    import numpy as np

    order = np.argsort(frames["key"].astype(str), kind="stable")
    sigma = np.sqrt(np.abs(np.diagonal(frames["cov_px"], axis1=-2, axis2=-1)))
    return {"err_px": frames["err_px"][order], "sigma_px": sigma[order], "scale": frames["scale"][order],
            "radial_px": frames["radial_px"][order], "dt_s": dt_s,
            "R_cam_from_target": frames["R_cam_from_target"][order]}


def _print_groups(before: dict, after: dict) -> None:
    print(f"{'group':12s} {'corners':>8s} {'NEES raw':>9s} {'NEES calibrated':>16s}")
    for g in before:
        print(f"{g:12s} {before[g]['count']:8d} {before[g]['mean_nees']:9.2f} {after[g]['mean_nees']:16.2f}")


def run_calibrate_cli(args: argparse.Namespace) -> int:
    import dataclasses

    import numpy as np
    from tqdm import tqdm

    from envisat_pose.app.detect import camera_samples, detector_inputs
    from envisat_pose.io import check_writable_output
    from envisat_pose.perception import errormodel as em
    from envisat_pose.perception.calibrate import calibration_by_group, fit_floor, fit_scale
    from envisat_pose.perception.data import shard_paths
    from envisat_pose.perception.detect import DetectConfig, load_detector
    from envisat_pose.perception.weights import with_metadata

    detector_inputs(args)
    if args.max_lag < 1:
        raise InputError(f"--max-lag {args.max_lag}: expected at least 1")
    if os.path.abspath(args.out) != os.path.abspath(args.weights):
        check_writable_output(args.out)
    paths = {d: shard_paths(d) for d in args.data}
    if args.held_out and not args.face_cue:
        raise InputError("--held-out belongs to --face-cue")
    if args.face_cue:
        if args.refine or args.keep_scale or args.roi != "coarse":
            raise InputError("--face-cue fits the appearance cue alone: drop --refine, --keep-scale and --roi")
        return fit_face_cue_cli(args, paths)
    sequences = all(is_sequence(d) for d in args.data)
    # the network's own covariances (scale 1), whatever the file carried before; the refinement's the same
    det = load_detector(args.weights, config=dataclasses.replace(DetectConfig(), cov_scale=1.0, refine=args.refine,
                                                                 refine_cov_floor_px2=0.0))
    bar = tqdm(disable=args.quiet, desc="calibrate", unit="frame")
    # one entry per --data folder, in order (a folder given twice counts twice)
    per_data = [(d, collect_frames(det, camera_samples(paths[d]), args.limit, bar, args.roi)) for d in args.data]
    bar.close()
    flat = [flat_errors(f, True if args.refine else None) for _, f in per_data]
    err, cov, groups = (np.concatenate([f[i] for f in flat]) for i in range(3))
    # named by folder and manifest sha256, not by a path of this machine (the record travels with the weights)
    data_names = " ".join(dataset_ref(d) for d in args.data)
    if len(err) < 20:
        raise InputError(f"--data {data_names!r}: only {len(err)} correctly named corners; calibration needs more "
                         "held-out frames (at least 20 corners)")
    if args.refine:  # the floor added to the line fits' covariances
        floor = fit_floor(err, cov)
        before = calibration_by_group(err, cov, groups)
        after = calibration_by_group(err, cov + floor * np.eye(2), groups)
        _print_groups(before, after)
        record = {"floor_px2": floor, "data": data_names, "corners": int(len(err)), "roi": args.roi,
                  "mean_nees_by_group": {g: v["mean_nees"] for g, v in after.items()},
                  "mean_nees_by_group_without_floor": {g: v["mean_nees"] for g, v in before.items()},
                  "count_by_group": {g: v["count"] for g, v in after.items()},
                  "refined_share": float(sum(f["refined"].sum() for _, f in per_data) / max(
                      sum(np.isfinite(f["err_px"][..., 0]).sum() for _, f in per_data), 1))}
        with_metadata(args.weights, args.out, {"refine_cov_floor_px2": floor,
                                               "refine_cov_calibration": json.dumps(record, sort_keys=True)})
        print(f"refine_cov_floor_px2 {floor:.4g} (mean e^T C^-1 e 2.00 on {len(err)} refined corners, "
              f"{record['refined_share']:.0%} of those named right); wrote {args.out}")
        return 0
    scale = fit_scale(err, cov)
    before = calibration_by_group(err, cov, groups)
    after = calibration_by_group(err, cov * scale, groups)
    _print_groups(before, after)
    meta = {}
    if not args.keep_scale:
        record = {"scale": scale, "data": data_names, "corners": int(len(err)), "roi": args.roi,
                  "mean_nees_by_group": {g: v["mean_nees"] for g, v in after.items()},
                  "count_by_group": {g: v["count"] for g, v in after.items()}}
        meta.update({"cov_scale": scale, "cov_calibration": json.dumps(record, sort_keys=True)})
    if sequences:
        seqs = [sequence_input(f, frame_interval_s(d)) for d, f in per_data]
        model, record = em.measure(seqs, scale, max_lag=args.max_lag, source=f"roi={args.roi}; {data_names}")
        record["mean_nees_by_group"] = {g: v["mean_nees"] for g, v in after.items()}
        meta.update({"error_model": model.to_json(), "error_model_record": json.dumps(record, sort_keys=True)})
        r = record["autocorr_normalized"]
        print("autocorrelation of the normalized errors, lags 0..: " +
              " ".join("-" if v is None else f"{v:.3f}" for v in r))
        print(f"rho_lag1 {model.rho_lag1:.3f}; fitted rho_k = {model.ar1_share:.3f} x {model.ar1_phi:.3f}^k: "
              f"inflation {model.inflation:.3f} (pure AR(1) from lag 1: {record['pure_ar1']['inflation']:.3f}; "
              f"measured r_k summed: {record['acf_inflation']:.3f}), correlation time {model.corr_time_s:.2f} s")
        if model.corr_angle_rad > 0:
            rates = ", ".join(f"{v:.2f}" for v in record["autocorr_by_angle"]["view_rate_deg_s"])
            print(f"in the view's rotation: rho(theta) = {model.angle_share:.3f} x exp(-theta / "
                  f"{np.degrees(model.corr_angle_rad):.1f} deg) (sequences turning at {rates} deg/s)")
        print(f"apparent scale {record['scale']['mean']:.5f} +- {record['scale']['se']:.5f} "
              f"({record['scale']['frames']} frames), radial error {record['radial_px']['mean']:+.3f} +- "
              f"{record['radial_px']['se']:.3f} px ({record['radial_px']['corners']} corners)")
    else:
        print("not every --data folder is a sequence (envisat generate --mode sequence): no error model")
    with_metadata(args.weights, args.out, meta)
    kept = " (kept the file's cov_scale)" if args.keep_scale else ""
    print(f"cov_scale {scale:.4g} (mean e^T C^-1 e 2.00 on {len(err)} corners){kept}; wrote {args.out}")
    return 0


def fit_face_cue_cli(args: argparse.Namespace, paths: dict) -> int:
    """`envisat calibrate --face-cue`: the cue's regions under each frame's labelled pose; --data fits it and
    --held-out tempers and scores it (without --held-out: the even frames of each --data folder fit, the odd ones
    temper); written into the weights' metadata."""
    from tqdm import tqdm

    from envisat_pose.app.detect import camera_samples
    from envisat_pose.geometry import load_geometry
    from envisat_pose.perception import facecue as fc
    from envisat_pose.perception.data import shard_paths
    from envisat_pose.perception.naming import face_windings
    from envisat_pose.perception.weights import with_metadata

    g = load_geometry()
    windings = face_windings(g)
    held_paths = {d: shard_paths(d) for d in (args.held_out or [])}
    fit, held = [], []
    bar = tqdm(disable=args.quiet, desc="face cue", unit="frame")
    for flag, folders in (("--data", paths), ("--held-out", held_paths)):
        for d, shards in folders.items():
            for i, (key, image, label) in enumerate(camera_samples(shards)):
                if args.limit is not None and i >= args.limit:
                    break
                if "R_cam_from_target" not in label:
                    raise InputError(f"{flag} {d!r}: sample {key} has no labelled pose (R_cam_from_target, "
                                     "t_cam_from_target_m); the face cue needs them")
                regions = fc.frame_regions(image, label["R_cam_from_target"], label["t_cam_from_target_m"],
                                           label["K"], g, windings)
                to_fit = flag == "--data" and (bool(held_paths) or i % 2 == 0)
                (fit if to_fit else held).append(regions)
                bar.update(1)
    bar.close()
    try:
        cue, record = fc.fit_and_temper(fit, held)
    except ValueError as err:
        raise InputError(f"--data: {err}") from None
    record["data"] = " ".join(dataset_ref(d) for d in args.data)
    record["held_out"] = " ".join(dataset_ref(d) for d in held_paths) or "the odd frames of data"
    with_metadata(args.weights, args.out, {"face_cue": cue.to_json(),
                                           "face_cue_record": json.dumps(record, sort_keys=True)})
    print(f"face cue: {record['fit_regions']} regions fitted; on {record['held_out_frames_with_a_face']} held-out "
          f"frames: right {record['right_share']:.1%}, decided {record['decided_share_at_0.1']:.1%} "
          f"(wrongly {record['decided_wrong_share_at_0.1']:.1%}), temperature {record['temperature']:.3g}; "
          f"wrote {args.out}")
    return 0
