"""The pipeline of `envisat calibrate`: the detector over held-out labelled frames, the fits of what a filter needs
of its corners, written into a copy of the weights' metadata.

- run_calibration: the network's covariance scale s (C -> s C: mean e^T (s C)^-1 e = 2 over the correctly named
  visible corners; `cov_scale`, `cov_calibration`), and when every folder is a sequence the error model
  (perception/errormodel.py: frame-to-frame correlation, AR(1), inflation, residual bias; `error_model`,
  `error_model_record`); with refine, the sub-pixel refinement's covariance floor instead
  (`refine_cov_floor_px2`, `refine_cov_calibration`).
- fit_face_cue: the half-turn's appearance cue (perception/facecue.py; `face_cue`, `face_cue_record`).
The fits themselves are the stage's (perception/calibrate.py: the chi-square scale and floor; errormodel.py;
facecue.py); here: label matching (collect_frames: which detected corner is which labelled one, the better of the
two half-turn namings), the per-sequence inputs and the job. The verb (app/calibrate.py) parses
the flags and prints.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass

from envisat_pose.config import Config, InputError, check, config_arg, path_arg, paths_arg
from envisat_pose.datagen.generate_config import nest_moved_keys
from envisat_pose.geometry import load_geometry
from envisat_pose.out_dirs import check_out_file, make_out_file_dir
from envisat_pose.out_lock import locks_output
from envisat_pose.perception import errormodel as em
from envisat_pose.perception import weights_keys as wk
from envisat_pose.perception.box_symmetry import face_windings
from envisat_pose.perception.calibrate import calibration_by_group, fit_cov_scale, fit_floor
from envisat_pose.pipelines.common.job_defaults import job_weights
from envisat_pose.pipelines.detector.detect import camera_samples
from envisat_pose.provenance import dataset_ref
from envisat_pose.shard_reader import checked_shards, load_dataset_manifest, sample_total
from envisat_pose.target import require_envisat_dataset

# The most autocorrelation lags measured: the sums are arrays of max_lag + 1, allocated after every frame was
# detected (2^63 - 1: a traceback then, the detection's minutes lost); a lag beyond the frames holds no pair, and
# the longest run the jobs make is MAX_RUN_FRAMES = 200000 frames (pipelines/tracking/tracker_bounds.py)
MAX_LAG = 200_000


@dataclass(frozen=True)
class CalibrateJobConfig(Config):
    """One `envisat calibrate` job. weights: the detector's weights file ("": the shipped ones; the fits go into a
    copy of it); roi:
    "coarse" (the detector's own coarse pass) or "labels" (the labels' region of interest, as the closed loop
    gives it); keep_scale: leave the file's cov_scale and cov_calibration (write the error model only); refine:
    fit the refinement's covariance floor instead; max_lag: autocorrelation lags measured; limit: only the first N
    frames of each folder (None: all); skip_damaged: go on without the shards that do not match their folder's
    manifest (named in the record), instead of refusing the folder."""

    weights: str = ""
    roi: str = "coarse"
    keep_scale: bool = False
    refine: bool = False
    max_lag: int = 20
    limit: int | None = None
    skip_damaged: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "weights", job_weights(self.weights))  # "": the shipped ones; checked, before work

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        check(self.roi in ("coarse", "labels"), f"{p}roi", self.roi, "'coarse' or 'labels'")
        check(1 <= self.max_lag <= MAX_LAG, f"{p}max_lag", self.max_lag, f"1 to {MAX_LAG} lags")
        check(self.limit is None or self.limit >= 1, f"{p}limit", self.limit, "at least 1 frame (or unset: all)")


def collect_frames(detector, samples, limit: int | None = None, bar=None, roi: str = "coarse") -> dict:
    """Per frame: key (T,), err_px (T, 8, 2) = detected - label of the usable corners named right within the
    match radius (NaN elsewhere; an ambiguous frame with its better naming), cov_px (T, 8, 2, 2) as the detector
    gives them (their names follow the naming), group (T,) the corruption group, scale (T,) the apparent scale
    and radial_px (T, 8) (perception/errormodel.py), R_cam_from_target (T, 3, 3) the labels' view. roi
    'labels': detect in the labels' region of interest."""
    import numpy as np

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


def is_sequence(path: str, field: str = "data") -> bool:
    """Whether a dataset folder was made by `envisat generate --mode sequence` (its manifest's config; a folder
    without a manifest is not). InputError naming the field when its manifest is not a dataset's."""
    manifest = load_dataset_manifest(path, field, required=False)
    return manifest is not None and (manifest.get("config") or {}).get("mode") == "sequence"


def frame_interval_s(path: str, field: str = "data") -> float:
    """A sequence dataset's frame interval, s (its manifest's config)."""
    config = load_dataset_manifest(path, field).get("config") or {}
    return float(nest_moved_keys(config).get("sequence", {}).get("frame_dt_s", 1.0))


def sequence_input(frames: dict, dt_s: float) -> dict:
    """One sequence of perception.errormodel.measure_error_model from collect_frames' arrays, in frame (key) order."""
    import numpy as np

    order = np.argsort(frames["key"].astype(str), kind="stable")
    sigma = np.sqrt(np.abs(np.diagonal(frames["cov_px"], axis1=-2, axis2=-1)))
    return {"err_px": frames["err_px"][order], "sigma_px": sigma[order], "scale": frames["scale"][order],
            "radial_px": frames["radial_px"][order], "dt_s": dt_s,
            "R_cam_from_target": frames["R_cam_from_target"][order]}


def data_shards(data: list[str], skip_damaged: bool, field: str = "data") -> tuple[dict[str, list[str]], list[str]]:
    """Each folder's shard files, checked against its manifest (shard_reader.checked_shards), and the damaged ones
    left out as 'folder/shard' (skip_damaged; else a damaged shard is one InputError). A sequence with a shard
    left out is refused: its frame-to-frame error model needs consecutive frames."""

    paths, skipped = {}, []
    for d in data:
        if d in paths:
            continue
        require_envisat_dataset(d, field, "calibrate")
        paths[d], left_out = checked_shards(d, skip_damaged, field)
        if left_out and is_sequence(d, field):
            raise InputError(f"{field} {d!r}: a sequence with damaged shard(s) {', '.join(left_out)}: left out, its "
                             "frames would no longer follow each other; regenerate them (`envisat generate` with the "
                             "same settings on the folder redoes them)")
        skipped += [os.path.join(os.path.basename(os.path.normpath(d)), name) for name in left_out]
    return paths, skipped


@locks_output("out", "calibrate", folder=False)
def run_calibration(cfg: CalibrateJobConfig, data: list[str], out: str, progress: bool = False) -> dict:
    """The covariance calibration of the detector in cfg.weights on the held-out folders `data` (one sequence per
    folder when they are sequences), written into out (a copy of the weights with the fits in its metadata; may
    be the weights file itself). Returns what was fitted: {"refine": bool, "corners": M, "before", "after":
    calibration_by_group without and with the fit, "scale" or "floor", "record", and, for sequences,
    "error_model" (the ErrorModel) and "error_model_record" (None when not every folder is a sequence),
    "skipped": the damaged shards left out (cfg.skip_damaged), "removed_error_model": the line saying an earlier
    error model was removed (a new scale on data not all sequences), or None}. A new scale replaces the file's
    whole calibration (weights_keys.COV_CALIBRATION_KEYS), --refine its floor's (REFINE_CALIBRATION_KEYS)."""
    import dataclasses

    import numpy as np
    from tqdm import tqdm

    from envisat_pose.perception.detect import DetectConfig, load_detector
    from envisat_pose.perception.weights import with_metadata

    cfg, out = config_arg(cfg, CalibrateJobConfig), path_arg(out, "out")
    data = paths_arg(data, "data")  # one folder (a str or a Path) or several
    check_out_file(out, "out", data)
    paths, skipped = data_shards(data, cfg.skip_damaged)
    sequences = all(is_sequence(d) for d in data)
    # the network's own covariances (scale 1), whatever the file carried before; the refinement's the same
    det = load_detector(cfg.weights, config=dataclasses.replace(DetectConfig(), cov_scale=1.0, refine=cfg.refine,
                                                                refine_cov_floor_px2=0.0))
    totals = [sample_total(paths[d], cfg.limit) for d in data]
    bar = tqdm(disable=not progress, desc="calibrate", unit="frame", total=None if None in totals else sum(totals))
    # one entry per data folder, in order (a folder given twice counts twice)
    per_data = [(d, collect_frames(det, camera_samples(paths[d]), cfg.limit, bar, cfg.roi)) for d in data]
    bar.close()
    flat = [flat_errors(f, True if cfg.refine else None) for _, f in per_data]
    err, cov, groups = (np.concatenate([f[i] for f in flat]) for i in range(3))
    # named by folder and manifest sha256, not by a path of this machine (the record travels with the weights)
    data_names = " ".join(dataset_ref(d) for d in data)
    if len(err) < 20:
        raise InputError(f"data {data_names!r}: only {len(err)} correctly named corners; calibration needs more "
                         "held-out frames (at least 20 corners)")
    if cfg.refine:  # the floor added to the line fits' covariances
        floor = fit_floor(err, cov)
        before = calibration_by_group(err, cov, groups)
        after = calibration_by_group(err, cov + floor * np.eye(2), groups)
        record = {"floor_px2": floor, "data": data_names, "corners": int(len(err)), "roi": cfg.roi,
                  "skipped_damaged_shards": skipped,
                  "mean_nees_by_group": {g: v["mean_nees"] for g, v in after.items()},
                  "mean_nees_by_group_without_floor": {g: v["mean_nees"] for g, v in before.items()},
                  "count_by_group": {g: v["count"] for g, v in after.items()},
                  "refined_share": float(sum(f["refined"].sum() for _, f in per_data) / max(
                      sum(np.isfinite(f["err_px"][..., 0]).sum() for _, f in per_data), 1))}
        make_out_file_dir(out, "out")  # only now: a refused calibration leaves no folder behind
        with_metadata(cfg.weights, out, {wk.REFINE_FLOOR_KEY: floor,
                                         wk.REFINE_CALIBRATION_KEY: json.dumps(record, sort_keys=True)},
                      drop=wk.REFINE_CALIBRATION_KEYS)
        return {"refine": True, "corners": int(len(err)), "before": before, "after": after, "floor": floor,
                "record": record, "skipped": skipped}
    scale = fit_cov_scale(err, cov)
    before = calibration_by_group(err, cov, groups)
    after = calibration_by_group(err, cov * scale, groups)
    meta, record = {}, None
    if not cfg.keep_scale:
        record = {"scale": scale, "data": data_names, "corners": int(len(err)), "roi": cfg.roi,
                  "skipped_damaged_shards": skipped,
                  "mean_nees_by_group": {g: v["mean_nees"] for g, v in after.items()},
                  "count_by_group": {g: v["count"] for g, v in after.items()}}
        meta.update({wk.COV_SCALE_KEY: scale, wk.COV_CALIBRATION_KEY: json.dumps(record, sort_keys=True)})
    model = model_record = None
    if sequences:
        seqs = [sequence_input(f, frame_interval_s(d)) for d, f in per_data]
        model, model_record = em.measure_error_model(seqs, scale, max_lag=cfg.max_lag, source=f"roi={cfg.roi}; {data_names}")
        model_record["mean_nees_by_group"] = {g: v["mean_nees"] for g, v in after.items()}
        meta.update({wk.ERROR_MODEL_KEY: model.to_json(),
                     wk.ERROR_MODEL_RECORD_KEY: json.dumps(model_record, sort_keys=True)})
    make_out_file_dir(out, "out")  # only now: a refused calibration leaves no folder behind
    # a new scale replaces the earlier calibration's keys, its error model too (kept: the scale, and the error
    # model unless measured again, which the kept scale's error model belongs to)
    removed = with_metadata(cfg.weights, out, meta, drop=() if cfg.keep_scale else wk.COV_CALIBRATION_KEYS)
    return {"refine": False, "corners": int(len(err)), "before": before, "after": after, "scale": scale,
            "record": record, "error_model": model, "error_model_record": model_record, "skipped": skipped,
            "removed_error_model": removed_error_model_line(removed)}


@locks_output("out", "calibrate", folder=False)
def fit_face_cue(weights: str, data: list[str], held_out: list[str], out: str, limit: int | None = None,
                 progress: bool = False, skip_damaged: bool = False) -> dict:
    """The half-turn's appearance cue: its regions under each frame's labelled pose; `data` fits it and
    `held_out` tempers and scores it (without held_out: the even frames of each data folder fit, the odd ones
    temper); written into out (a copy of weights with `face_cue` and `face_cue_record`; "" the shipped ones).
    limit: only the first N frames of each folder. skip_damaged: go on without the shards that do not match their
    manifest (named in the record). Returns the record. weights and limit are checked as the verb's --weights and
    --limit, before any frame is read."""
    from tqdm import tqdm

    from envisat_pose.perception import facecue as fc
    from envisat_pose.perception.weights import with_metadata

    check(limit is None or (type(limit) is int and limit >= 1), "limit", limit, "at least 1 frame (or unset: all)")
    weights = job_weights(weights)  # a missing file failed once every frame was read; limit 0 or -1 read none
    check_out_file(out, "out", data)
    check_out_file(out, "out", held_out or (), "held_out")
    paths, skipped = data_shards(data, skip_damaged)
    held_paths, held_skipped = data_shards(held_out or [], skip_damaged, "held_out")
    g = load_geometry()
    windings = face_windings(g)
    fit, held = [], []
    bar = tqdm(disable=not progress, desc="face cue", unit="frame")
    for flag, folders in (("data", paths), ("held_out", held_paths)):
        for d, shards in folders.items():
            for i, (key, image, label) in enumerate(camera_samples(shards)):
                if limit is not None and i >= limit:
                    break
                if "R_cam_from_target" not in label:
                    raise InputError(f"{flag} {d!r}: sample {key} has no labelled pose (R_cam_from_target, "
                                     "t_cam_from_target_m); the face cue needs them")
                regions = fc.frame_regions(image, label["R_cam_from_target"], label["t_cam_from_target_m"],
                                           label["K"], g, windings)
                to_fit = flag == "data" and (bool(held_paths) or i % 2 == 0)
                (fit if to_fit else held).append(regions)
                bar.update(1)
    bar.close()
    try:
        cue, record = fc.fit_and_temper(fit, held)
    except ValueError as err:
        raise InputError(f"data: {err}") from None
    record["data"] = " ".join(dataset_ref(d) for d in data)
    record["held_out"] = " ".join(dataset_ref(d) for d in held_paths) or "the odd frames of data"
    record["skipped_damaged_shards"] = skipped + held_skipped
    make_out_file_dir(out, "out")
    with_metadata(weights, out, {wk.FACE_CUE_KEY: cue.to_json(),
                                 wk.FACE_CUE_RECORD_KEY: json.dumps(record, sort_keys=True)}, drop=wk.FACE_CUE_KEYS)
    return record


def removed_error_model_line(removed: dict[str, str]) -> str | None:
    """The line saying the earlier calibration's error model was removed (with_metadata's removed entries: a
    recalibration on data not all sequences), naming what it was measured on; None when none was removed."""
    if not set(removed) & set(wk.ERROR_MODEL_KEYS):
        return None
    try:
        model = em.ErrorModel.from_json(removed.get(wk.ERROR_MODEL_KEY))
        what = f"{model.source or 'data it did not record'} ({model.n_frames} frames)"
    except (ValueError, TypeError):
        what = "data it did not record (unreadable)"
    return (f"error model from the earlier calibration removed: measured on sequences of {what} for the fit this "
            "one replaces; not every --data folder is a sequence, so none is written (the tracker takes the errors "
            "as white)")


def error_model_lines(model, record: dict) -> list[str]:
    """The error model measured on sequences (perception/errormodel.ErrorModel and its record) as the calibrate
    verb prints it: the autocorrelation, the fitted white + AR(1) and its inflation, the correlation in the view's
    rotation where fitted, the apparent scale and the radial error."""
    import numpy as np

    r = record["autocorr_normalized"]
    lines = ["autocorrelation of the normalized errors, lags 0..: " + " ".join("-" if v is None else f"{v:.3f}"
                                                                            for v in r),
             f"rho_lag1 {model.rho_lag1:.3f}; fitted rho_k = {model.ar1_share:.3f} x {model.ar1_phi:.3f}^k: "
             f"inflation {model.inflation:.3f} (pure AR(1) from lag 1: {record['pure_ar1']['inflation']:.3f}; "
             f"measured r_k summed: {record['acf_inflation']:.3f}), correlation time {model.corr_time_s:.2f} s"]
    if model.corr_angle_rad > 0:
        rates = ", ".join(f"{v:.2f}" for v in record["autocorr_by_angle"]["view_rate_deg_s"])
        lines.append(f"in the view's rotation: rho(theta) = {model.angle_share:.3f} x exp(-theta / "
                     f"{np.degrees(model.corr_angle_rad):.1f} deg) (sequences turning at {rates} deg/s)")
    lines.append(f"apparent scale {record['scale']['mean']:.5f} +- {record['scale']['se']:.5f} "
                 f"({record['scale']['frames']} frames), radial error {record['radial_px']['mean']:+.3f} +- "
                 f"{record['radial_px']['se']:.3f} px ({record['radial_px']['corners']} corners)")
    return lines
