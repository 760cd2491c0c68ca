"""Inference of another target's keypoint network (perception/keypoint_net.py): weights loaded for the one target
they were trained for, then per frame a coarse pass on the whole frame and a pass on the crop around what it
found, each keypoint at its channel's peak plus its offset. Plain numpy at the boundary.

A frame's result (K keypoints, in the channel order of the weights' keypoint_names):
    keypoints_px: (K, 2) full-image px (OpenCV convention), always a position (the channel's peak)
    score:        (K,) the heatmap's peak score in [0, 1]
    visible_prob: (K,) the visibility head's probability in [0, 1]
    crop_px:      (3,) int (x0, y0, side) of the crop of the second pass (the whole frame when the coarse pass
                  found fewer than MIN_CROP_KEYPOINTS)
The names are the network's up to the target's symmetries that its materials keep: twins are not told apart here.

The pixel covariance: `envisat calibrate --target` writes one sigma per keypoint into the weights' metadata
(perception/weights_keys.SIGMA_KEY, a JSON list, null where a keypoint was not calibrated; perception/keypoint_cov.py);
`weights_keypoint_sigma` reads it (NaN where absent). Beside it the share of a correct track's keypoints its gate
rejects, as a function of the gate's whitened radius (REJECT_KEY; `weights_reject_curve`, None where absent),
and, calibrated on sequences, the errors' frame-to-frame model (perception/detect.weights_error_model).
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import torch

from envisat_pose.config import InputError, from_dict
from envisat_pose.perception.data import IMAGE_MEAN, IMAGE_STD, DataConfig, crop_box, crop_resize, to_full_px
from envisat_pose.perception.detect import FrameDetection, weights_error_model
from envisat_pose.perception.errormodel import ErrorModel
from envisat_pose.perception.keypoint_metrics import PNP_MIN_POINTS
from envisat_pose.perception.keypoint_net import KEYPOINT_FORMAT, KeypointModelConfig, KeypointNet, decode_keypoints
from envisat_pose.perception.weights import (
    WeightsError,
    check_weights_target,
    load_state,
    read_header,
    read_weights,
    trained_for,
)
from envisat_pose.perception.weights_keys import FORMAT_KEY, MODEL_CONFIG_KEY, REJECT_KEY, SIGMA_KEY
from envisat_pose.target import load_target

MIN_CROP_KEYPOINTS = 2  # keypoints the coarse pass must find to crop around them


@dataclass(frozen=True)
class KeypointDetectConfig:
    """coarse_threshold: a keypoint's peak score for the coarse pass to count it; crop_margin: the crop's side
    over the found keypoints' extent (perception/data.crop_box's rule); visible_threshold: visible_prob at which a
    keypoint is reported visible (the contract's `visible`)."""

    coarse_threshold: float = 0.2
    crop_margin: float = 1.4
    visible_threshold: float = 0.5


def load_keypoint_model(path: str, target: str, device: str = "cpu", field: str = "weights") -> KeypointNet:
    """The KeypointNet stored at path, in eval mode, for the target value `target` (its file): InputError in one
    line for another target's weights or ENVISAT's (check_weights_target), WeightsError for a truncated or foreign
    file or tensors that do not fit."""
    check_weights_target(path, target, field)
    tensors, meta = read_weights(path)
    if meta.get(FORMAT_KEY) != KEYPOINT_FORMAT or MODEL_CONFIG_KEY not in meta:
        raise WeightsError(f"{path}: not keypoint-detector weights (metadata {FORMAT_KEY} {meta.get(FORMAT_KEY)!r})")
    try:
        cfg = from_dict(KeypointModelConfig, json.loads(meta[MODEL_CONFIG_KEY]))
    except (ValueError, TypeError) as err:
        raise WeightsError(f"{path}: bad model config in the metadata ({err})") from None
    model = KeypointNet(cfg, trained_for(path, meta))
    load_state(model, tensors, path)
    return model.to(device).eval()


def weights_keypoint_sigma(path: str, num_keypoints: int) -> np.ndarray:
    """(K,) px: the isotropic sigma per keypoint the weights' metadata carries (SIGMA_KEY), NaN where a keypoint
    was not calibrated and everywhere for weights never calibrated. WeightsError when the entry is there but not
    a list of K positive numbers or nulls."""
    raw = read_header(path).get(SIGMA_KEY)
    if raw is None:
        return np.full(num_keypoints, np.nan)
    try:
        values = json.loads(raw)
        sigma = np.array([np.nan if v is None else float(v) for v in values], float)
    except (ValueError, TypeError):
        sigma = np.zeros(0)
    if sigma.shape != (num_keypoints,) or np.any(~np.isnan(sigma) & ~((sigma > 0) & np.isfinite(sigma))):
        raise WeightsError(f"{path}: metadata {SIGMA_KEY} {raw[:80]!r} is not {num_keypoints} positive numbers "
                           "(or nulls)")
    return sigma


def weights_reject_curve(path: str) -> dict | None:
    """The weights' reject curve (REJECT_KEY: perception/keypoint_cov.reject_curve's r_sigma and share), None for
    weights calibrated before it was recorded. WeightsError when the entry is there but not two equally long lists
    of increasing radii and shares in [0, 1]."""
    raw = read_header(path).get(REJECT_KEY)
    if raw is None:
        return None
    try:
        d = json.loads(raw)
        r, share = np.asarray(d["r_sigma"], float), np.asarray(d["share"], float)
    except (ValueError, TypeError, KeyError):
        r = share = np.zeros(0)
    if len(r) < 2 or r.shape != share.shape or np.any(np.diff(r) <= 0) \
            or not np.all((share >= 0) & (share <= 1)):
        raise WeightsError(f"{path}: metadata {REJECT_KEY} {raw[:80]!r} is not increasing radii r_sigma and shares "
                           "in [0, 1] of the same length")
    return {"r_sigma": r.tolist(), "share": share.tolist(), "given": int(d.get("given", 0))}


class KeypointDetector:
    """A trained KeypointNet (eval mode) and the two passes around it (module doc)."""

    def __init__(self, model: KeypointNet, config: KeypointDetectConfig = KeypointDetectConfig(),
                 device: str = "cpu"):
        self.model, self.cfg, self.device = model.to(device).eval(), config, torch.device(device)
        self.input_px, self.stride = model.cfg.input_px, model.cfg.stride
        self.keypoint_names = tuple(model.target.get("keypoint_names", ()))

    def network(self, image: np.ndarray, box: np.ndarray) -> dict[str, np.ndarray]:
        """One pass on the crop box (x0, y0, side) of a uint8 image: keypoints_px (K, 2) full-image px, score
        (K,), visible_prob (K,)."""
        crop = crop_resize(image, box, self.input_px)
        x = (crop.astype(np.float32) / 255.0 - IMAGE_MEAN) / IMAGE_STD
        with torch.inference_mode():
            out = self.model(torch.from_numpy(x)[None, None].to(self.device))
        d = decode_keypoints(torch.sigmoid(out["kmap_logit"][0]).cpu().numpy(), out["koff"][0].cpu().numpy(),
                             self.stride)
        return {"keypoints_px": to_full_px(d["points_px"], box, self.input_px), "score": d["score"],
                "visible_prob": torch.sigmoid(out["kvis_logit"][0]).double().cpu().numpy()}

    def detect(self, image: np.ndarray) -> dict[str, np.ndarray]:
        """The keypoints of one frame (H, W) uint8: the coarse pass on the whole frame, then the crop around the
        keypoints it found (score >= coarse_threshold; at least MIN_CROP_KEYPOINTS, else the coarse pass is the
        answer). Returns the module doc's arrays."""
        h, w = image.shape
        whole = np.array([0, 0, max(h, w)], dtype=np.int64)
        coarse = self.network(image, whole)
        found = coarse["score"] >= self.cfg.coarse_threshold
        if found.sum() < MIN_CROP_KEYPOINTS:
            return {**coarse, "crop_px": whole}
        box = crop_box(coarse["keypoints_px"], found, (h, w), DataConfig(crop_margin=self.cfg.crop_margin), None)
        return {**self.network(image, box), "crop_px": box}


class KeypointFrameDetector:
    """A keypoint detector as the Tracker takes one (pipelines/tracking/tracker.py): detect(image, K, roi_px=None,
    ...) -> perception.detect.FrameDetection with K rows, keypoint k in row k (the weights' channel order, the
    Target's). A keypoint is reported (visible, with its position) where its visibility probability and its peak
    score pass the detector's thresholds and its sigma is calibrated; its covariance is sigma_k^2 I
    (`envisat calibrate --target`). In a region of interest the network looks at that window alone (one pass);
    without one, at the whole frame then the crop around what it found. The pose priors the corner network takes
    for its naming are accepted and not used: a keypoint's name is its channel. alt_probability is 0.5 (no
    half-turn cue: the tracker's namings weigh a keypoint network's names by the target's symmetries).
    reject_curve: what a correct track's gate rejects (weights_reject_curve; None: the tracker's fixed share).
    error_model: the errors' frame-to-frame correlation and bias (perception/errormodel.ErrorModel, `calibrate
    --target` on sequences; the white default without one)."""

    def __init__(self, detector: KeypointDetector, sigma_px: np.ndarray, reject_curve: dict | None = None,
                 error_model: ErrorModel | None = None):
        self.detector = detector
        self.sigma_px = np.asarray(sigma_px, float)
        self.reject_curve = reject_curve
        self.error_model = ErrorModel() if error_model is None else error_model
        self.trained_for = dict(detector.model.target)
        self.keypoint_names = detector.keypoint_names

    @property
    def num_keypoints(self) -> int:
        return int(self.sigma_px.shape[0])

    def detect(self, image: np.ndarray, K: np.ndarray | None = None, roi_px: np.ndarray | None = None,
               prior_R_cam_from_target=None, prior_t_cam_from_target_m=None, prior_weighs_namings: bool = True):
        if roi_px is None:
            found = self.detector.detect(image)
        else:
            box = np.asarray(roi_px, dtype=np.int64)
            found = {**self.detector.network(image, box), "crop_px": box}
        cfg = self.detector.cfg
        visible = (found["visible_prob"] >= cfg.visible_threshold) & (found["score"] >= cfg.coarse_threshold) \
            & np.isfinite(self.sigma_px) & np.isfinite(found["keypoints_px"]).all(-1)
        z = np.where(visible[:, None], found["keypoints_px"], np.nan)
        var = np.where(visible, np.square(np.nan_to_num(self.sigma_px, nan=1.0)), np.nan)
        cov = var[:, None, None] * np.eye(2)
        return FrameDetection(z, cov, np.asarray(found["score"], float), visible, np.full_like(z, np.nan), 0.5,
                              False, np.asarray(found["crop_px"], np.float64), np.zeros((0, 2)))


def load_frame_detector(path: str, target: str, device: str = "cpu", field: str = "weights") -> KeypointFrameDetector:
    """The KeypointFrameDetector of the weights at path for the target file `target` (load_keypoint_model's
    checks). InputError when the weights carry no calibrated covariance: the tracker weighs each keypoint by it."""
    model = load_keypoint_model(path, target, device, field)
    sigma = require_calibrated(path, target, field)
    return KeypointFrameDetector(KeypointDetector(model, device=device), sigma, weights_reject_curve(path),
                                 weights_error_model(path))


def require_calibrated(path: str, target: str, field: str = "weights") -> np.ndarray:
    """The weights' calibrated sigma per keypoint (weights_keypoint_sigma, K of the target file `target`);
    InputError in one line when they carry none: the tracker weighs each keypoint by it."""
    sigma = weights_keypoint_sigma(path, load_target(target).num_keypoints)
    if not np.isfinite(sigma).any():
        raise InputError(f"{field} {path!r}: no calibrated pixel covariance (the tracker weighs each keypoint by "
                         f"it): calibrate the weights on held-out frames first, `envisat calibrate --target {target} "
                         f"--weights {path} --data HELD_OUT_DIR --out CALIBRATED.safetensors`")
    n = int(np.isfinite(sigma).sum())
    if n < PNP_MIN_POINTS:
        raise InputError(f"{field} {path!r}: only {n} of {len(sigma)} keypoints calibrated; the tracker's cold start "
                         f"needs {PNP_MIN_POINTS} for PnP (calibrate on more held-out frames, or train longer)")
    return sigma
