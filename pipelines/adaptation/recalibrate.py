"""Step 5 of `envisat adapt` (pipelines/adaptation/adapt.py): a network recalibrated on the pseudo-labels, as
`envisat calibrate --roi labels` fits it on a labelled set: its covariance scale on their residuals, and its
apparent scale against them (the quantity the error model's bias_scale holds; scale_decision.py decides whether
the adapted weights take it)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np

from envisat_pose.perception.calibrate import fit_cov_scale, nees_px
from envisat_pose.perception.errormodel import SCALE_MIN_FRAMES, mean_se
from envisat_pose.pipelines.detector.calibrate import collect_frames, flat_errors


def recalibrate(weights: str, images: list[np.ndarray], labels: list[dict], bar=None) -> dict:
    """The covariance scale of `weights` refitted on the pseudo-labels' residuals (perception/calibrate.fit_cov_scale
    over the correctly named corners, the network's own covariances, the labels' region of interest: what
    `envisat calibrate --roi labels` fits), and the detector's apparent scale against the labels (each frame's
    least-squares scale of its right corners about their centroid, perception/errormodel.apparent_scale: the
    quantity the error model's bias_scale holds). {scale, corners, mean_nees_before (at the file's scale),
    apparent_scale, apparent_scale_se, apparent_scale_frames}; scale None when fewer than 20 corners matched,
    apparent_scale None below SCALE_MIN_FRAMES frames with one."""
    from envisat_pose.perception.data import decode_label
    from envisat_pose.perception.detect import DetectConfig, load_detector, weights_cov_scale

    det = load_detector(weights, config=dataclasses.replace(DetectConfig(), cov_scale=1.0, refine=False,
                                                            refine_cov_floor_px2=0.0))
    samples = ((str(i), im, decode_label(json.dumps(lab).encode(), f"pseudo-label {i}"))
               for i, (im, lab) in enumerate(zip(images, labels)))
    frames = collect_frames(det, samples, bar=bar, roi="labels")
    err, cov, _ = flat_errors(frames)
    s_mean, s_se, s_n = mean_se(frames["scale"])
    scale = {"apparent_scale": s_mean if s_n >= SCALE_MIN_FRAMES else None,
             "apparent_scale_se": s_se if s_n >= SCALE_MIN_FRAMES else None, "apparent_scale_frames": s_n}
    if len(err) < 20:
        return {"scale": None, "corners": int(len(err)), "mean_nees_before": None, **scale}
    old = weights_cov_scale(weights)
    return {"scale": fit_cov_scale(err, cov), "corners": int(len(err)),
            "mean_nees_before": float(np.mean(nees_px(err, cov * old))), **scale}
