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
(SIGMA_KEY, a JSON list, null where a keypoint was not calibrated; perception/keypoint_cov.py);
`weights_keypoint_sigma` reads it (NaN where absent).
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np
import torch

from envisat_pose.config import from_dict
from envisat_pose.perception.data import IMAGE_MEAN, IMAGE_STD, DataConfig, crop_box, crop_resize, to_full_px
from envisat_pose.perception.keypoint_net import KEYPOINT_FORMAT, KeypointModelConfig, KeypointNet, decode_keypoints
from envisat_pose.perception.weights import (
    WeightsError,
    check_weights_target,
    load_state,
    read_header,
    read_weights,
    trained_for,
)

MIN_CROP_KEYPOINTS = 2  # keypoints the coarse pass must find to crop around them
SIGMA_KEY = "keypoint_sigma_px"  # the weights' metadata: the calibrated isotropic sigma per keypoint, px
SIGMA_RECORD_KEY = "keypoint_cov_calibration"  # ... and the record of its fit (JSON)


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
    if meta.get("format") != KEYPOINT_FORMAT or "model_config" not in meta:
        raise WeightsError(f"{path}: not keypoint-detector weights (metadata format {meta.get('format')!r})")
    try:
        cfg = from_dict(KeypointModelConfig, json.loads(meta["model_config"]))
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
