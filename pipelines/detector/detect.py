"""The pipeline of `envisat detect`: named corners of every frame of a dataset (full frames, no label used but the
intrinsics K), written as the core's Detections contract plus the shard keys and the half-turn alternative.

The glue from the image factory's shards into perception lives here too: `camera_samples` (every sample as the
camera saw it: a shard stored clean gets its recorded sensor corruption applied on read) and `read_roi` (the
regions of interest that skip the coarse pass). `envisat calibrate` and `envisat evaluate` read frames the same way.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

from envisat_pose.config import Config, InputError, check, config_arg, path_arg
from envisat_pose.contracts import Detections
from envisat_pose.io import NotAnNpz, open_npz, save_npz, sha256_file
from envisat_pose.out_dirs import check_out_file, make_out_file_dir
from envisat_pose.out_lock import locks_output
from envisat_pose.pipelines.common.job_defaults import job_weights, weights_name
from envisat_pose.provenance import manifest_sha256
from envisat_pose.shard_reader import checked_shards, sample_total
from envisat_pose.target import require_envisat_dataset


@dataclass(frozen=True)
class DetectJobConfig(Config):
    """One `envisat detect` job. weights: the detector's weights file ("": the shipped ones); device: torch device ("cpu", "cuda");
    limit: only the first N frames (None: all); roi: an ROI file (key (M,), roi_px (M, 3)) whose frames skip the
    coarse pass (None: every frame gets it); refine: refine the named corners on the full-resolution pixels
    (perception.detect.DetectConfig.refine); skip_damaged: go on without the shards that do not match the dataset's
    manifest (named in det.npz's config_json), instead of refusing the dataset."""

    weights: str = ""
    device: str = "cpu"
    limit: int | None = None
    roi: str | None = None
    refine: bool = False
    skip_damaged: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "weights", job_weights(self.weights))  # "": the shipped ones; checked, before work

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        check(self.device in ("cpu", "cuda"), f"{p}device", self.device, "'cpu' or 'cuda'")
        check(self.limit is None or self.limit >= 1, f"{p}limit", self.limit, "at least 1 frame (or unset: all)")


def camera_samples(paths: list[str]):
    """(key, image, label) of every sample as the camera saw it: a shard stored clean (`image_stored` 'clean')
    gets its label's recorded sensor corruption applied on read (datagen's space camera, deterministic)."""
    from envisat_pose.datagen.corrupt import apply_corruption
    from envisat_pose.perception.data import read_samples

    for key, image, label in read_samples(paths):
        if label.get("image_stored") == "clean":
            image = apply_corruption(image, label["corruption"])
        yield key, image, label


def read_roi(path: str) -> dict[str, "object"]:
    """{key: roi_px (3,) int} from an ROI file (npz of key (M,) str and roi_px (M, 3) finite, side > 0);
    InputError naming the file and the problem otherwise. Loaded without pickle."""
    import os
    import zipfile

    import numpy as np

    if not os.path.isfile(path):
        raise InputError(f"roi {path!r}: no such file")
    try:
        with open_npz(path) as z:
            keys, roi = z["key"].astype(str), np.asarray(z["roi_px"], dtype=np.float64)
    except NotAnNpz:
        raise InputError(f"roi {path!r}: not an .npz file (a zip archive of the arrays key and roi_px)") from None
    except (KeyError, ValueError, OSError, EOFError, zipfile.BadZipFile) as err:  # damaged or truncated too
        raise InputError(f"roi {path!r}: expected an npz with key (M,) and roi_px (M, 3) ({err})") from None
    if roi.shape != (len(keys), 3):
        raise InputError(f"roi {path!r}: roi_px has shape {roi.shape}, expected ({len(keys)}, 3): one row "
                         "(x, y, side) per key")
    bad = np.flatnonzero(~np.all(np.isfinite(roi), axis=1) | ~(roi[:, 2] > 0))
    if bad.size:
        i = int(bad[0])
        raise InputError(f"roi {path!r}: roi_px row {i} (key {str(keys[i])!r}) is {roi[i].tolist()}, expected finite "
                         f"(x, y, side) with side > 0 ({bad.size} such rows)")
    return {k: np.round(r).astype(np.int64) for k, r in zip(keys.tolist(), roi)}


def detect_dataset(cfg: DetectJobConfig, data: str, progress: bool = False) -> dict:
    """Named corners of every frame of the dataset folder `data` (its shards): the arrays of det.npz (the
    Detections contract's, key, alt_corners_px, alt_probability, ambiguous; config_json a str), checked against
    the contract; config_json names the damaged shards left out (skipped_damaged_shards). InputError when the
    folder holds no frames or a damaged shard (unless cfg.skip_damaged)."""
    import numpy as np
    from tqdm import tqdm

    from envisat_pose.perception.detect import load_detector

    require_envisat_dataset(data, "data", "detect")
    paths, skipped = checked_shards(data, cfg.skip_damaged, "data")
    rois = read_roi(cfg.roi) if cfg.roi else {}
    det = load_detector(cfg.weights, device=cfg.device)
    if cfg.refine:
        import dataclasses

        det.cfg = dataclasses.replace(det.cfg, refine=True)
    rows = {k: [] for k in ("key", "t_s", "corners_px", "cov_px", "confidence", "visible", "alt_corners_px",
                            "alt_probability", "ambiguous")}
    bar = tqdm(disable=not progress, desc="detect", unit="frame", total=sample_total(paths, cfg.limit))
    for i, (key, image, label) in enumerate(camera_samples(paths)):
        if cfg.limit is not None and i >= cfg.limit:
            break
        # the label's intrinsics only: positions come from the image
        f = det.detect(image, label["K"], roi_px=rois.get(key))
        rows["key"].append(key)
        rows["t_s"].append(float(label.get("t_s", i)))
        for name in ("corners_px", "cov_px", "confidence", "visible", "alt_corners_px", "alt_probability",
                     "ambiguous"):
            rows[name].append(getattr(f, name))
        bar.update(1)
    bar.close()
    if not rows["key"]:
        raise InputError(f"data {data!r}: no frames")
    config = {"weights": weights_name(cfg.weights), "weights_sha256": sha256_file(cfg.weights), "data": data,
              "data_manifest_sha256": manifest_sha256(data), "model": det.model.cfg.to_dict(),
              "cov_scale": det.cfg.cov_scale, "roi": cfg.roi, "refine": bool(cfg.refine),
              "skipped_damaged_shards": skipped}
    arrays = {k: np.array(v) for k, v in rows.items()}
    arrays["key"] = arrays["key"].astype(str)
    arrays["config_json"] = json.dumps(config, sort_keys=True)
    Detections.validated(arrays, "det.npz")  # the contract's checks before anything is written
    return arrays


@locks_output("out", "detect", folder=False)
def run_detect(cfg: DetectJobConfig, data: str, out: str, progress: bool = False) -> dict:
    """The whole job: detect_dataset, then det.npz written atomically at out, its folder made then (parents too):
    a run stopped before leaves nothing. Returns det.npz's arrays. data and out: a str or a pathlib.Path."""
    import numpy as np

    cfg, data, out = config_arg(cfg, DetectJobConfig), path_arg(data, "data"), path_arg(out, "out")
    check_out_file(out, "out", data)
    arrays = detect_dataset(cfg, data, progress)
    Detections.validated(arrays, out)
    make_out_file_dir(out, "out")
    save_npz(out, {**arrays, "config_json": np.array(arrays["config_json"])})
    return arrays
