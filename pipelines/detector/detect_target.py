"""The pipeline of `envisat detect --target FILE.xml`: another target's keypoints in every frame of a dataset of that
target (`envisat generate --target FILE.xml`), by its keypoint detector (perception/keypoint_detect.py), written as
the core's KeypointDetections contract (det.npz). The weights are checked against the target before any work
(one line naming the weights, their target and the given one); so is the dataset's recorded target. Frames are
read as `envisat detect` reads them (a shard stored clean gets its recorded corruption on read); no label is
used but the frame time where it has one. Each keypoint's pixel covariance (cov_px) is the calibrated
sigma_k^2 I the weights carry (`envisat calibrate --target`), NaN for a keypoint they carry none of.

TargetDetectJobConfig is the job config of `envisat evaluate --target` and `envisat calibrate --target` too
(pipelines/detector/evaluate_target.py, calibrate_target.py).
"""

from __future__ import annotations

import json
from dataclasses import dataclass

from envisat_pose.config import Config, InputError, check, config_arg, path_arg
from envisat_pose.contracts import KeypointDetections
from envisat_pose.io import sha256_file
from envisat_pose.out_dirs import check_out_file, make_out_file_dir
from envisat_pose.out_lock import locks_output
from envisat_pose.provenance import manifest_sha256
from envisat_pose.shard_reader import checked_shards, load_dataset_manifest, read_shards, sample_total
from envisat_pose.target import load_target


@dataclass(frozen=True)
class TargetDetectJobConfig(Config):
    """One `envisat detect --target` job (and evaluate's, calibrate's: the same inputs). target: the target's MJCF
    file; weights: its keypoint detector (trained with `envisat train --target`; "": FILE_detector.safetensors
    beside the target file, when it was trained for it, e.g. the shipped upper stage's); device: torch device ("cpu",
    "cuda"); limit: only the first N frames (None: all; per folder where a job reads several); skip_damaged: go on
    without the shards that do not match the dataset's manifest (named in config_json and the records)."""

    target: str = ""
    weights: str = ""
    device: str = "cpu"
    limit: int | None = None
    skip_damaged: bool = False

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        check(self.target != "", f"{p}target", self.target, "the target's MJCF file")
        check(self.device in ("cpu", "cuda"), f"{p}device", self.device, "'cpu' or 'cuda'")
        check(self.limit is None or self.limit >= 1, f"{p}limit", self.limit, "at least 1 frame (or unset: all)")

    def __post_init__(self) -> None:
        super().__post_init__()
        from envisat_pose.pipelines.common.job_defaults import target_weights, weights_file  # scipy (filters)

        # "": the target's own detector beside its file (job_defaults.default_target_weights), as the verbs take it
        object.__setattr__(self, "weights", weights_file(target_weights(self.weights, self.target)))


def require_dataset_of(folder: str, target, field: str = "data") -> None:
    """InputError in one line unless the dataset in `folder` records the Target `target` (its manifest's target
    sha256); a folder without a manifest passes (checked_shards reports it)."""
    manifest = load_dataset_manifest(folder, field, required=False)
    record = (manifest or {}).get("target")
    if manifest is None or (record or {}).get("sha256") == target.sha256:
        return
    what = f"target {record.get('name')!r}" if record else "ENVISAT (no target recorded)"
    raise InputError(f"{field} {folder!r}: a dataset of {what}, not of target {target.name!r} (sha256 "
                     f"{target.sha256[:12]}): give a dataset generated with this target file")


def target_frames(paths: list[str]):
    """(key, image (H, W) uint8, label dict) of every sample of the shards, as the camera saw it: a sample stored
    clean gets its label's recorded corruption (datagen's space camera) applied on read."""
    from envisat_pose.datagen.corrupt import apply_corruption
    from envisat_pose.perception.data import decode_image

    for where, key, sample in read_shards(paths):
        if "png" not in sample or "json" not in sample:
            raise InputError(f"{where}: a sample without its image or label member")
        image, label = decode_image(sample["png"], f"{where}.png"), json.loads(sample["json"])
        if label.get("image_stored") == "clean":
            image = apply_corruption(image, label["corruption"])
        yield key, image, label


def detect_target_dataset(cfg: TargetDetectJobConfig, data: str, progress: bool = False) -> dict:
    """The keypoints of every frame of the dataset folder `data`: the arrays of det.npz (KeypointDetections'),
    checked against the contract. The weights and the dataset are checked against the target first."""
    import numpy as np
    from tqdm import tqdm

    from envisat_pose.perception.keypoint_cov import isotropic_cov
    from envisat_pose.perception.keypoint_detect import KeypointDetector, load_keypoint_model, weights_keypoint_sigma
    from envisat_pose.pipelines.common.job_defaults import weights_name

    target = load_target(cfg.target, "target")
    model = load_keypoint_model(cfg.weights, cfg.target, cfg.device)
    require_dataset_of(data, target)
    paths, skipped = checked_shards(data, cfg.skip_damaged, "data")
    det = KeypointDetector(model, device=cfg.device)
    rows = {k: [] for k in ("key", "t_s", "keypoints_px", "score", "visible_prob", "crop_px")}
    bar = tqdm(disable=not progress, desc="detect", unit="frame", total=sample_total(paths, cfg.limit))
    for i, (key, image, label) in enumerate(target_frames(paths)):
        if cfg.limit is not None and i >= cfg.limit:
            break
        found = det.detect(image)
        rows["key"].append(key)
        rows["t_s"].append(float(label.get("t_s", i)))
        for name in ("keypoints_px", "score", "visible_prob", "crop_px"):
            rows[name].append(found[name])
        bar.update(1)
    bar.close()
    if not rows["key"]:
        raise InputError(f"data {data!r}: no frames")
    arrays = {k: np.array(v) for k, v in rows.items()}
    arrays["key"] = arrays["key"].astype(str)
    arrays["visible"] = arrays["visible_prob"] >= det.cfg.visible_threshold
    arrays["keypoint_names"] = np.array(det.keypoint_names, dtype=str)
    sigma = weights_keypoint_sigma(cfg.weights, len(det.keypoint_names))
    arrays["cov_px"] = isotropic_cov(sigma, len(arrays["key"]))  # NaN where not calibrated
    arrays["config_json"] = json.dumps({"weights": weights_name(cfg.weights),
                                        "weights_sha256": sha256_file(cfg.weights),
                                        "target": target.record(cfg.target),  # as the manifest names it
                                        "data": data, "data_manifest_sha256": manifest_sha256(data),
                                        "model": model.cfg.to_dict(),
                                        "calibrated": [n for n, s in zip(det.keypoint_names, sigma) if s > 0],
                                        "skipped_damaged_shards": skipped}, sort_keys=True)
    KeypointDetections.validated(arrays, "det.npz")  # the contract's checks before anything is written
    return arrays


@locks_output("out", "detect", folder=False)
def run_detect_target(cfg: TargetDetectJobConfig, data: str, out: str, progress: bool = False) -> dict:
    """The whole job: detect_target_dataset, then det.npz written atomically at out (its folder made then): a run
    refused or stopped before leaves nothing. data, out: a str or a pathlib.Path. Returns det.npz's arrays."""
    cfg, data, out = config_arg(cfg, TargetDetectJobConfig), path_arg(data, "data"), path_arg(out, "out")
    check_out_file(out, "out", data)
    arrays = detect_target_dataset(cfg, data, progress)
    det = KeypointDetections.validated(arrays, out)
    make_out_file_dir(out, "out")
    det.save(out)
    return arrays
