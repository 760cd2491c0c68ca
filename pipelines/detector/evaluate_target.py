"""The pipeline of `envisat evaluate --target FILE.xml`: another target's keypoint detector scored against the
labels of a dataset of that target (`envisat generate --target FILE.xml`); a table on stdout and every number in a
JSON file.

The scores (perception/keypoint_metrics.py) per keypoint name and over all: PCK at 2 and 5 px, median and p95 error
over the labels' usable (visible and in-frame) keypoints, visibility precision and recall, the keypoints named
wrongly (called visible within the match radius of another usable keypoint's label, not of their own), and the pose
after PnP (solvePnPRansac on the keypoints called visible, the Target's keypoints_T_m and the label's K): rotation
error deg and translation error in % of the range over the poses found (plausible ones: km.pose_found), and the
shares of all frames PnP solved, with a pose found and with a correct one (found, within 5 deg and 5 % of the
range). Each is given as the network names the keypoints ('as_named') and, where the Target has symmetries its
materials keep, under each frame's best twin naming ('twin_aware', with the share of frames a twin's naming won):
no image tells the twins apart, the tracker settles them. Weights calibrated by `envisat calibrate --target` (their
sigma per keypoint) are checked on the same frames ('calibration': mean e^T C^-1 e over the correct detections, 2
when honest).

The weights and the dataset are checked against the target before any work; frames are read as `envisat detect
--target` reads them (pipelines/detector/detect_target.py). The detection over labelled folders (detect_labelled)
is calibrate --target's too (pipelines/detector/calibrate_target.py).
"""

from __future__ import annotations

import json

import numpy as np

from envisat_pose.config import InputError, config_arg, path_arg
from envisat_pose.io import atomic_write_text, json_safe, sha256_file
from envisat_pose.out_dirs import check_out_file, make_out_file_dir
from envisat_pose.out_lock import locks_output
from envisat_pose.perception import keypoint_metrics as km
from envisat_pose.perception.keypoint_cov import nees_check
from envisat_pose.pipelines.common.job_defaults import weights_name
from envisat_pose.pipelines.detector.detect_target import TargetDetectJobConfig, require_dataset_of, target_frames
from envisat_pose.provenance import dataset_ref
from envisat_pose.shard_reader import checked_shards, sample_total
from envisat_pose.target import load_target


def make_keypoint_detector(model, device: str):
    """The detector evaluate and calibrate --target run (a function so a test can put an oracle in its place)."""
    from envisat_pose.perception.keypoint_detect import KeypointDetector

    return KeypointDetector(model, device=device)


def label_keypoint_arrays(label: dict, names: tuple[str, ...], where: str) -> dict:
    """A label's keypoints in the weights' order: true_px (K, 2), usable (K,) (visible and in frame), K (3, 3),
    R (3, 3) and t (3,) the labelled pose (NaN where the label has none). InputError when the label does not name
    the weights' keypoints."""
    if list(label.get("keypoint_names", [])) != list(names) or "keypoints_px" not in label:
        raise InputError(f"{where}: a label without the keypoints {list(names)} of the weights' target "
                         f"(it names {label.get('keypoint_names')!r})")
    nan = np.full((3, 3), np.nan)
    return {"true_px": np.asarray(label["keypoints_px"], float).reshape(len(names), 2),
            "usable": np.asarray(label["visible"], bool) & np.asarray(label["in_frame"], bool),
            "K": np.asarray(label["K"], float),
            "R": np.asarray(label.get("R_cam_from_target", nan), float),
            "t": np.asarray(label.get("t_cam_from_target_m", nan[0]), float)}


def collect_keypoints(det, frames, names: tuple[str, ...], limit: int | None = None, bar=None) -> dict:
    """Detect every frame ((key, image, label) as target_frames gives them, the first `limit`) and keep beside
    each the label's keypoints: key (N,), pred_px (N, K, 2), score, visible_prob (N, K), called (N, K) bool (the
    detector's `visible`), and label_keypoint_arrays' arrays stacked."""
    rows: dict[str, list] = {k: [] for k in ("key", "pred_px", "score", "visible_prob", "true_px", "usable", "K",
                                             "R", "t")}
    for i, (key, image, label) in enumerate(frames):
        if limit is not None and i >= limit:
            break
        truth = label_keypoint_arrays(label, names, f"sample {key}")
        found = det.detect(image)
        rows["key"].append(key)
        rows["pred_px"].append(found["keypoints_px"])
        rows["score"].append(found["score"])
        rows["visible_prob"].append(found["visible_prob"])
        for k, v in truth.items():
            rows[k].append(v)
        if bar is not None:
            bar.update(1)
    arrays = {k: np.array(v) for k, v in rows.items()}
    arrays["called"] = arrays["visible_prob"] >= det.cfg.visible_threshold
    return arrays


def detect_labelled(cfg: TargetDetectJobConfig, folders: list[str], progress: bool = False, desc: str = "evaluate"):
    """The target's keypoint detector (cfg.weights, checked against cfg.target) over the labelled frames of each
    dataset folder (each checked to be of the target; the first cfg.limit frames of each): (target, model,
    collect_keypoints' arrays over every folder with folder (N,) each frame's index into folders, the damaged
    shards left out as 'folder/shard')."""
    import os

    from tqdm import tqdm

    from envisat_pose.perception.keypoint_detect import load_keypoint_model

    target = load_target(cfg.target, "target")
    model = load_keypoint_model(cfg.weights, cfg.target, cfg.device)
    det = make_keypoint_detector(model, cfg.device)
    names = tuple(model.target.get("keypoint_names", ()))
    shards, skipped = [], []
    for folder in folders:  # every folder checked before any is detected: a refusal costs no detection
        require_dataset_of(folder, target)
        paths, left_out = checked_shards(folder, cfg.skip_damaged, "data")
        shards.append(paths)
        skipped += [os.path.join(os.path.basename(os.path.normpath(folder)), s) for s in left_out]
    totals = [sample_total(paths, cfg.limit) for paths in shards]  # None: a folder whose count is unknown
    bar = tqdm(disable=not progress, desc=desc, unit="frame", total=None if None in totals else sum(totals))
    parts = [collect_keypoints(det, target_frames(paths), names, cfg.limit, bar) for paths in shards]
    bar.close()
    for i, p in enumerate(parts):  # which folder each frame came from (an index into folders)
        p["folder"] = np.full(len(p["key"]), i)
    parts = [p for p in parts if len(p["key"])]
    if not parts:
        raise InputError(f"data {' '.join(folders)!r}: no frames")
    arrays = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    return target, model, arrays, skipped


def pnp_pose_errors(pred_px: np.ndarray, called: np.ndarray, arrays: dict,
                    keypoints_T_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per frame the pose PnP gives from the keypoints called visible: its error (N, 2) (rotation deg, translation
    % of range; NaN where no pose: too few keypoints, the solver failed, no labelled pose) and whether it is a pose
    found (N,) bool (km.pose_found: a plausible one)."""
    err, found = np.full((len(pred_px), 2), np.nan), np.zeros(len(pred_px), bool)
    for n in range(len(pred_px)):
        got = km.pnp_solve(pred_px[n], called[n], arrays["K"][n], keypoints_T_m)
        if got is not None and np.all(np.isfinite(arrays["R"][n])) and np.all(np.isfinite(arrays["t"][n])):
            err[n] = km.pose_error(got["R"], got["t"], arrays["R"][n], arrays["t"][n])
            found[n] = km.pose_found(got, arrays["t"][n])
    return err, found


def score_naming(pred_px: np.ndarray, called: np.ndarray, arrays: dict, target) -> dict:
    """score_keypoints of one naming of every frame, with its pose after PnP ('pose': pose_summary)."""
    out = km.score_keypoints(pred_px, arrays["true_px"], arrays["usable"], called, target.keypoint_names)
    out["pose"] = km.pose_summary(*pnp_pose_errors(pred_px, called, arrays, target.keypoints_T_m))
    return out


def score_target(arrays: dict, target, perms: np.ndarray, sigma_px: np.ndarray) -> dict:
    """The scores of collect_keypoints' arrays: 'as_named', 'twin_aware' (None without a kept symmetry: perms
    (P, K), keypoint_loss.relabelings, the identity first) with 'twin_share' (frames a twin's naming won), and
    'calibration' (nees_check of the weights' sigma_px (K,) on the correct detections under the twin-aware naming;
    None for weights without one)."""
    chosen = km.best_relabeling(arrays["pred_px"], arrays["true_px"], arrays["usable"], perms)
    pred = km.relabeled(arrays["pred_px"], perms, chosen)
    called = km.relabeled(arrays["called"], perms, chosen)
    out = {"relabelings": int(len(perms)), "twin_aware": None, "twin_share": None, "calibration": None,
           "as_named": score_naming(arrays["pred_px"], arrays["called"], arrays, target)}
    if len(perms) > 1:
        out["twin_aware"] = score_naming(pred, called, arrays, target)
        out["twin_share"] = float(np.mean(chosen > 0))
    if np.isfinite(sigma_px).any():
        err = km.correct_errors(pred, arrays["true_px"], arrays["usable"], called)
        out["calibration"] = nees_check(err, sigma_px, target.keypoint_names)
    return out


@locks_output("json_path", "evaluate", folder=False)
def evaluate_target_detector(cfg: TargetDetectJobConfig, data: str, json_path: str, progress: bool = False) -> dict:
    """Score the keypoint detector of cfg.weights on the labelled dataset folder `data` of cfg.target and write
    every number to json_path (its folder made then; data, json_path: a str or a pathlib.Path). Returns the JSON's
    content."""
    from envisat_pose.perception.keypoint_detect import weights_keypoint_sigma
    from envisat_pose.perception.keypoint_loss import relabelings

    cfg, data = config_arg(cfg, TargetDetectJobConfig), path_arg(data, "data")
    json_path = path_arg(json_path, "json_path")
    check_out_file(json_path, "json_path", data)
    target, model, arrays, skipped = detect_labelled(cfg, [data], progress)
    perms = relabelings(target.symmetries, target.num_keypoints)
    sigma = weights_keypoint_sigma(cfg.weights, target.num_keypoints)
    result = {"weights": weights_name(cfg.weights), "weights_sha256": sha256_file(cfg.weights),
              "target": target.record(cfg.target),
              "data": dataset_ref(data), "frames": int(len(arrays["key"])), "model": model.cfg.to_dict(),
              "match_px": km.MATCH_PX, "pnp_reprojection_px": km.PNP_REPROJ_PX,
              "twins": [list(map(int, p)) for p in perms[1:]], "skipped_damaged_shards": skipped,
              **score_target(arrays, target, perms, sigma)}
    make_out_file_dir(json_path, "json_path")
    atomic_write_text(json_path, json.dumps(json_safe(result), indent=1, allow_nan=False) + "\n")
    return result


def _cell(x, spec: str) -> str:
    """x in its column's format; an absent value as '-' padded to the column's width (the spec's leading digits)."""
    width = spec.split(".")[0]
    return "-".rjust(int(width or 1)) if x is None or not np.isfinite(x) else format(x, spec)


def pose_line(naming: str, p: dict) -> str:
    """The pose after PnP of one naming (pose_summary's p): the shares of frames with a pose found (its rule) and
    with a correct one, then the errors over the poses found."""
    rule = p["found_rule"]
    return (f"pose after PnP ({naming}): a pose found in {_cell(p['found_share'], '.1%')} of {p['frames']} frames "
            f"(PnP solved {_cell(p['solved_share'], '.1%')}; found: >= {rule['min_inliers']} inliers, RMS <= "
            f"{rule['max_rms_px']:g} px, range within x{rule['range_factor']:g} of the label's), correct (within "
            f"{km.POSE_OK_DEG:g} deg and {km.POSE_OK_PCT:g} % of the range) in {_cell(p['correct_share'], '.1%')}; "
            f"over the poses found: rotation median {_cell(p['rotation_deg_median'], '.2f')} deg, p95 "
            f"{_cell(p['rotation_deg_p95'], '.2f')}; translation median {_cell(p['translation_pct_median'], '.2f')} "
            f"% of range, p95 {_cell(p['translation_pct_p95'], '.2f')}")


def keypoint_table(result: dict) -> str:
    """The evaluation as a table: a line per keypoint and one over all, for each naming scored; then the pose
    after PnP and the calibration check."""
    head = (f"{'naming':10s} {'keypoint':14s} {'usable':>6s} {'PCK@2':>6s} {'PCK@5':>6s} {'med px':>7s} "
            f"{'p95 px':>7s} {'vis P':>6s} {'vis R':>6s} {'wrong':>6s}")
    lines = [head, "-" * len(head)]
    pose_lines = []
    for naming in ("as_named", "twin_aware"):
        s = result.get(naming)
        if s is None:
            continue
        for name, k in [("all", s["all"])] + list(s["per_keypoint"].items()):
            lines.append(f"{naming:10s} {name:14s} {k['usable']:6d} {_cell(k['pck_2px'], '6.1%')} "
                         f"{_cell(k['pck_5px'], '6.1%')} {_cell(k['median_px'], '7.2f')} {_cell(k['p95_px'], '7.2f')} "
                         f"{_cell(k['vis_precision'], '6.1%')} {_cell(k['vis_recall'], '6.1%')} "
                         f"{_cell(k['named_wrongly_rate'], '6.1%')}")
        pose_lines.append(pose_line(naming, s["pose"]))
    if result.get("twin_share") is not None:
        pose_lines.append(f"a twin's naming won in {result['twin_share']:.1%} of the frames")
    cal = result.get("calibration")
    if cal is not None:
        a = cal["all"]
        pose_lines.append(f"calibration: mean e^T C^-1 e {_cell(a['mean_nees'], '.2f')} (2 when honest), "
                          f"{_cell(a['within_gate'], '.1%')} within the {cal['gate_prob']:.0%} gate, on "
                          f"{a['count']} correct detections")
    return "\n".join(lines + pose_lines)
