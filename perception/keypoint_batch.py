"""Training batches of the keypoint network made on the device from whole frames, as perception/batch_augment.py
makes the corner network's (its crop boxes around the keypoints, resampling and style augmentation, per-sample
draws from the caller's generator), with perception/keypoint_loss.py's targets instead of junctions and lines.

Frames: (B, H, W) gray levels 0-255 on the device. Labels: keypoints_px (B, K, 2) OpenCV pixels, visible (B, K)
bool, in_frame (B, K) bool. The batch (N samples, S input px, H = W = S / stride cells):
    image:        (N, 1, S, S) float32, perception/data.py's normalization
    kmap, kcell, koff, valid: keypoint_loss.encode_keypoints's targets
    keypoints_px: (N, K, 2) float32 input px (0 where not finite); crop_px (N, 3) float32 (x0, y0, side) of the
                  crop in the frame: full = (input + 0.5) side / S - 0.5 + x0
"""

from __future__ import annotations

import torch

from envisat_pose.perception.batch_augment import (
    augment_style_batch,
    crop_boxes,
    crop_resize_batch,
    draw_crop_params,
    draw_style_params,
    max_crop_side,
    to_input_px_batch,
)
from envisat_pose.perception.data import IMAGE_MEAN, IMAGE_STD, DataConfig
from envisat_pose.perception.keypoint_loss import encode_keypoints


def keypoint_batch(frames: torch.Tensor, keypoints_px: torch.Tensor, visible: torch.Tensor, in_frame: torch.Tensor,
                   cfg: DataConfig, generator: torch.Generator | None, frame_of_sample: torch.Tensor | None = None,
                   frame_hw: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """The batch of the module doc (batch_augment.training_batch's arguments and draws: sample n a crop of frame
    frame_of_sample[n] around its in-frame keypoints, or a share cfg.whole_frame_prob of whole frames, jittered
    and style-augmented from `generator`; generator None: evaluation crops, no jitter or augmentation)."""
    dev = frames.device
    fs = torch.arange(len(frames), device=dev) if frame_of_sample is None else frame_of_sample.to(dev)
    n, s = len(fs), cfg.input_px
    params = None
    if generator is not None:
        params = {k: v.to(dev) for k, v in draw_crop_params(n, cfg, generator).items()}
    image_hw = tuple(frames.shape[1:]) if frame_hw is None else frame_hw.to(dev)[fs]
    box = crop_boxes(keypoints_px[fs], in_frame[fs].bool(), image_hw, cfg, params)
    x = crop_resize_batch(frames, fs, box, s, True, max_crop_side(tuple(frames.shape[1:]), cfg)) / 255.0
    if generator is not None and cfg.augment:
        x = augment_style_batch(x, draw_style_params(n, s, generator))
    points = to_input_px_batch(keypoints_px[fs].to(torch.float64), box, s)
    inside = ((points > -0.5) & (points < s - 0.5)).all(-1)
    valid = visible[fs].bool() & in_frame[fs].bool() & inside & torch.isfinite(points).all(-1)
    cells = s // cfg.stride
    t = encode_keypoints(points, valid, (cells, cells), cfg.stride, cfg.sigma_cells)
    return {"image": ((x - IMAGE_MEAN) / IMAGE_STD)[:, None].to(torch.float32), **t,
            "keypoints_px": torch.nan_to_num(points).to(torch.float32), "crop_px": box.to(torch.float32)}
