"""The pipeline of `envisat calibrate --target FILE.xml`: the pixel covariance of another target's keypoint
detector, fitted on held-out labelled frames of that target, written into a copy of the weights' metadata (as
ENVISAT's calibrate writes its cov_scale: perception/weights.with_metadata).

The model (perception/keypoint_cov.py): per keypoint an isotropic sigma_k, robust (the median absolute error of
the correct detections, both axes about zero, over 0.6745), from the correct detections: usable (visible and
in frame), called visible, within the match radius of their own label under each frame's best twin naming (the
tracker settles the twins, so the errors it sees are those of the right naming). A keypoint with fewer than
MIN_CORRECT (20) correct detections gets none (null: detect --target gives it a NaN covariance); each sigma's
standard error is recorded (18 % of it at 20 detections, 5 % at 300). Written as
`keypoint_sigma_px` (a JSON list in the weights' keypoint order) and `keypoint_cov_calibration` (the record:
every sigma and count, the check, the data). The check, on the same held-out frames: mean e^T C^-1 e over the
correct detections (2 when the model holds) and the share within the chi-square's 95 % gate. Also recorded: the
median error of the correct detections below and above their median heatmap score (a score-dependent model
would need the two to differ), and what a correct track's gate rejects (perception/keypoint_cov.reject_curve:
over every detection the tracker is given, right or wrong, the share beyond each whitened radius), written as
`keypoint_reject_curve`: the tracker's rejection test expects that share instead of a fixed one.

When every folder is a sequence (`envisat generate --mode sequence --target`), the frame-to-frame error model
too, as ENVISAT's calibrate measures it (perception/errormodel.py): the correct detections' errors over the
sigma per keypoint, their correlation from frame to frame and in the view's rotation, the apparent scale and the
radial bias; written as `error_model` and `error_model_record`, which the tracker reads as for ENVISAT (R
inflated for the correlation at the filter's memory, the windowed NIS's dispersion, the scale undone).
"""

from __future__ import annotations

import json
import warnings

import numpy as np

from envisat_pose.config import InputError, config_arg, path_arg, paths_arg
from envisat_pose.gates import GATE_PROB, chi2_gate
from envisat_pose.io import json_safe
from envisat_pose.out_dirs import check_out_file, make_out_file_dir
from envisat_pose.out_lock import locks_output
from envisat_pose.perception import errormodel as em
from envisat_pose.perception import keypoint_metrics as km
from envisat_pose.perception.keypoint_cov import (
    GAUSS_ABS_MEDIAN,
    MIN_CORRECT,
    fit_keypoint_sigma,
    nees_check,
    reject_curve,
    reject_share,
    sigma_standard_error,
)
from envisat_pose.perception.weights_keys import (
    ERROR_MODEL_KEY,
    ERROR_MODEL_RECORD_KEY,
    KEYPOINT_CALIBRATION_KEYS,
    REJECT_KEY,
    SIGMA_KEY,
    SIGMA_RECORD_KEY,
)
from envisat_pose.pipelines.detector.calibrate import frame_interval_s, is_sequence, removed_error_model_line
from envisat_pose.pipelines.detector.detect_target import TargetDetectJobConfig
from envisat_pose.pipelines.detector.evaluate_target import detect_labelled
from envisat_pose.provenance import dataset_ref


def calibration_errors(arrays: dict, perms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(err (N, K, 2) px of the correct detections under each frame's best naming among perms (P, K), NaN
    elsewhere; chosen (N,) the row of perms each frame took) from evaluate_target.collect_keypoints' arrays."""
    chosen = km.best_relabeling(arrays["pred_px"], arrays["true_px"], arrays["usable"], perms)
    pred = km.relabeled(arrays["pred_px"], perms, chosen)
    called = km.relabeled(arrays["called"], perms, chosen)
    return km.correct_errors(pred, arrays["true_px"], arrays["usable"], called), chosen


def given_detections(arrays: dict, perms: np.ndarray, chosen: np.ndarray, sigma_px: np.ndarray, cfg) -> np.ndarray:
    """(N, K) bool: the detections the tracker is given (perception/keypoint_detect.KeypointFrameDetector's rule:
    visibility and peak score at cfg's thresholds, a calibrated sigma), under each frame's naming `chosen`."""
    called = (arrays["visible_prob"] >= cfg.visible_threshold) & (arrays["score"] >= cfg.coarse_threshold)
    return km.relabeled(called, perms, chosen) & np.isfinite(np.asarray(sigma_px, float))[None]


def error_by_score(err: np.ndarray, score: np.ndarray) -> dict:
    """The median error, px, of the correct detections (err (N, K, 2), NaN elsewhere) whose heatmap score (N, K)
    lies below their median score, and of the others, with the median score: whether a score-dependent sigma
    would pay (None with fewer than 2 correct detections)."""
    ok = np.all(np.isfinite(err), axis=-1)
    if ok.sum() < 2:
        return {"median_score": None, "below": None, "at_or_above": None}
    d, s = np.linalg.norm(err[ok], axis=-1), np.asarray(score, float)[ok]
    m = float(np.median(s))
    return {"median_score": m, "below": float(np.median(d[s < m])) if np.any(s < m) else None,
            "at_or_above": float(np.median(d[s >= m]))}


def sequence_inputs(arrays: dict, pred_px: np.ndarray, err: np.ndarray, given: np.ndarray, sigma_px: np.ndarray,
                    dt_s: list[float]) -> list[dict]:
    """One perception.errormodel.measure_error_model sequence per folder (dt_s its frame interval, s), its frames
    in key order, from collect_keypoints' arrays (with detect_labelled's folder index), the frames' named
    predictions pred_px (N, K, 2), the correct detections' errors err (N, K, 2) (NaN elsewhere), the detections
    the tracker is given (N, K) and the sigma per keypoint (K,) px. A frame's apparent scale counts where at least
    3 keypoints are right and none it is given is wrong."""
    right = np.all(np.isfinite(err), axis=-1)
    scale = em.apparent_scale(pred_px, arrays["true_px"], right, given & arrays["usable"] & ~right)
    radial = em.radial_errors(pred_px, arrays["true_px"], right)
    sigma = np.broadcast_to(np.asarray(sigma_px, float)[None, :, None], err.shape)
    out = []
    for i, dt in enumerate(dt_s):
        idx = np.flatnonzero(arrays["folder"] == i)
        idx = idx[np.argsort(arrays["key"][idx].astype(str), kind="stable")]
        out.append({"err_px": err[idx], "sigma_px": sigma[idx], "scale": scale[idx], "radial_px": radial[idx],
                    "dt_s": float(dt), "R_cam_from_target": arrays["R"][idx]})
    return out


def sequence_error_model(folders: list[str], skipped: list[str], arrays: dict, pred_px: np.ndarray, err: np.ndarray,
                         given: np.ndarray, sigma_px: np.ndarray, names: tuple[str, ...], refs: str):
    """(the ErrorModel, its record) of the error model (module doc) when every folder is a sequence, else (None,
    None). InputError when a damaged shard was left out of one: its frames would no longer follow each other."""
    if not all(is_sequence(d) for d in folders):
        return None, None
    if skipped:
        raise InputError(f"data: sequence shard(s) {', '.join(skipped)} damaged and left out, their frames would no "
                         "longer follow each other; regenerate them (`envisat generate` with the same settings on "
                         "the folder redoes them)")
    seqs = sequence_inputs(arrays, pred_px, err, given, sigma_px, [frame_interval_s(d) for d in folders])
    return em.measure_error_model(seqs, 1.0, source=refs, names=names)


@locks_output("out", "calibrate", folder=False)
def run_calibrate_target(cfg: TargetDetectJobConfig, data: list[str], out: str, progress: bool = False) -> dict:
    """Fit the sigma per keypoint of the keypoint detector in cfg.weights on the held-out folders `data` of
    cfg.target and write out (a copy of the weights with keypoint_sigma_px and keypoint_cov_calibration in its
    metadata; may be the weights file itself), replacing the earlier calibration's keys as a whole
    (weights_keys.KEYPOINT_CALIBRATION_KEYS: an error model measured for other sigmas removed). Returns the record
    (module doc) with 'corners' (the correct detections), 'calibrated' (the keypoints given a sigma) and
    'removed_error_model' (the line saying an earlier error model was removed, or None)."""
    from envisat_pose.perception.keypoint_detect import KeypointDetectConfig
    from envisat_pose.perception.keypoint_loss import relabelings
    from envisat_pose.perception.weights import with_metadata

    cfg, out = config_arg(cfg, TargetDetectJobConfig), path_arg(out, "out")
    folders = list(dict.fromkeys(paths_arg(data, "data")))  # one folder (a str or a Path) or several
    check_out_file(out, "out", folders)
    target, _, arrays, skipped = detect_labelled(cfg, folders, progress, desc="calibrate")
    names = target.keypoint_names
    perms = relabelings(target.symmetries, target.num_keypoints)
    err, chosen = calibration_errors(arrays, perms)
    sigma, count = fit_keypoint_sigma(err)
    refs = " ".join(dataset_ref(d) for d in folders)
    if not np.isfinite(sigma).any():
        raise InputError(f"data {' '.join(folders)!r}: at most {int(count.max())} correct detections of any "
                         f"keypoint in {len(chosen)} frames; calibration needs {MIN_CORRECT} of a keypoint "
                         "(more held-out frames, or a detector that finds the keypoints within "
                         f"{km.MATCH_PX:g} px)")
    given = given_detections(arrays, perms, chosen, sigma, KeypointDetectConfig())
    pred = km.relabeled(arrays["pred_px"], perms, chosen)
    curve = reject_curve(pred - arrays["true_px"], given, arrays["usable"], sigma)
    clean = [None if not np.isfinite(v) else float(v) for v in sigma]
    se = [None if not np.isfinite(v) else float(v) for v in sigma_standard_error(sigma, count)]
    record = {"model": f"isotropic sigma per keypoint: median(|e_x|, |e_y|) about 0 / {GAUSS_ABS_MEDIAN:.4f}",
              "data": refs, "frames": int(len(chosen)), "match_px": km.MATCH_PX, "min_correct": MIN_CORRECT,
              "sigma_px": dict(zip(names, clean)), "sigma_se_px": dict(zip(names, se)),
              "count": {n: int(c) for n, c in zip(names, count)},
              "twin_share": float(np.mean(chosen > 0)) if len(perms) > 1 else None,
              "check": nees_check(err, sigma, names), "error_by_score": error_by_score(err, arrays["score"]),
              "reject_share_at_gate": reject_share(curve, chi2_gate(GATE_PROB, 2)),
              "skipped_damaged_shards": skipped}
    model, model_record = sequence_error_model(folders, skipped, arrays, pred, err, given, sigma, names, refs)
    meta = {} if model is None else {ERROR_MODEL_KEY: model.to_json(),
                                     ERROR_MODEL_RECORD_KEY: json.dumps(json_safe(model_record), sort_keys=True)}
    make_out_file_dir(out, "out")
    # the earlier calibration's keys replaced as a whole: its error model, measured for its sigmas, goes with them
    removed = with_metadata(cfg.weights, out, {SIGMA_KEY: json.dumps(clean),
                                               SIGMA_RECORD_KEY: json.dumps(json_safe(record), sort_keys=True),
                                               REJECT_KEY: json.dumps(json_safe(curve)), **meta},
                            drop=KEYPOINT_CALIBRATION_KEYS)
    calibrated = int(np.isfinite(sigma).sum())
    if calibrated < km.PNP_MIN_POINTS:
        warnings.warn(f"only {calibrated} of {len(sigma)} keypoints calibrated (each needs {MIN_CORRECT} correct "
                      f"detections): the tracker's cold start needs {km.PNP_MIN_POINTS} for PnP, so `track` and "
                      "`run` refuse these weights; calibrate on more held-out frames, or train longer", stacklevel=2)
    return {**record, "corners": int(count.sum()), "calibrated": calibrated, "error_model": model,
            "error_model_record": model_record, "removed_error_model": removed_error_model_line(removed)}


def sigma_table(record: dict) -> str:
    """The fit as a table: a line per keypoint (correct detections, sigma px, mean e^T C^-1 e, share within the
    gate) and one over all."""
    check = record["check"]
    head = f"{'keypoint':14s} {'correct':>7s} {'sigma px':>16s} {'NEES':>6s} {'in gate':>7s}"
    lines = [head, "-" * len(head)]
    for name, c in check["per_keypoint"].items():
        s, se = record["sigma_px"][name], record["sigma_se_px"][name]
        sigma = "-" if s is None else f"{s:.3f} +- {se:.3f}"
        lines.append(f"{name:14s} {record['count'][name]:7d} {sigma:>16s} {_num(c['mean_nees'], '6.2f')} "
                     f"{_num(c['within_gate'], '7.1%')}")
    a = check["all"]
    lines.append(f"{'all calibrated':14s} {a['count']:7d} {'':>16s} {_num(a['mean_nees'], '6.2f')} "
                 f"{_num(a['within_gate'], '7.1%')}")
    if record.get("reject_share_at_gate") is not None:
        lines.append(f"a correct track's gate rejects at most {_num(record['reject_share_at_gate'], '.1%')} of the "
                     "keypoints it is given (right or wrong, at the tracker's gate without inflation)")
    return "\n".join(lines)


def _num(x, spec: str) -> str:
    return "-".rjust(int(spec.split(".")[0])) if x is None or not np.isfinite(x) else format(x, spec)
