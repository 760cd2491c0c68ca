"""The keypoint network of any target: K named keypoints, each with its own heatmap channel, a 2-channel sub-cell
offset and a visibility logit, on the corner network's backbone (perception/model.py: the stride-4 stem, the
hourglass and the neck, built from the same blocks; CornerNet itself is untouched).

Model, loss and loop live apart (perception/keypoint_loss.py, perception/keypoint_train.py): `forward` returns raw
maps only. Channel k is the target's keypoint k (Target.keypoint_names, the file's order); the weights record the
names, the target's name and sha256 (`metadata`, written by perception/weights.save_weights).

Shapes for a batch of B gray images of S x S input px, stride s = 4, H = W = S / s cells, K keypoints:
    image:      (B, 1, S, S) float, perception/data.py's normalization
    features:   (B, C, H, W)
    kmap_logit: (B, K, H, W) logit that keypoint k lies in the cell (sigmoid: its score)
    koff:       (B, K, 2, H, W) sub-cell offset (x, y) of keypoint k in [-0.5, 0.5] cells (heatmaps.py's units)
    kvis_logit: (B, K) logit that keypoint k is visible in the input (unoccluded, in the frame and the input)
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import nn

from envisat_pose.config import Config, check
from envisat_pose.perception.heatmaps import to_pixels
from envisat_pose.perception.model import Hourglass, Residual, check_backbone, conv_bn
from envisat_pose.perception.weights_keys import FORMAT_KEY, KIND_KEY, TARGET_KEY

KEYPOINT_FORMAT = "envisat-pose keypoint detector v1"  # the weights' metadata `format`
MODEL_KIND = "keypoints"  # the weights' metadata KIND_KEY (ENVISAT's corner weights have none: corners)
HEATMAP_PRIOR_LOGIT = -4.6  # a keypoint's cell is rare: the heatmap starts at sigmoid ~ 0.01 (focal-loss practice)


@dataclass(frozen=True)
class KeypointModelConfig(Config):
    """Architecture. input_px: network input side; width: hourglass channels; depth: hourglass levels below
    stride 4; stem_width: the stem's first channels; num_keypoints: K, the target's (None: filled in from the
    target by perception/keypoint_train.KeypointTrainConfig)."""

    input_px: int = 320
    width: int = 48
    depth: int = 3
    stem_width: int = 24
    num_keypoints: int | None = None

    stride = 4

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        check_backbone(self, p)
        check(self.num_keypoints is None or self.num_keypoints >= 1, f"{p}num_keypoints", self.num_keypoints,
              "at least 1 keypoint (or unset: the target's)")

    def to_dict(self) -> dict:
        return asdict(self)


class KeypointNet(nn.Module):
    """Backbone + per-keypoint heatmap and offset head + a pooled visibility head (module doc for shapes).
    target: what the weights record of the target, {'name', 'sha256', 'keypoint_names'} (Target.record)."""

    def __init__(self, cfg: KeypointModelConfig, target: dict | None = None):
        super().__init__()
        cfg.validate()
        check(cfg.num_keypoints is not None, "model.num_keypoints", None, "the target's keypoint count")
        self.cfg, self.target = cfg, dict(target or {})
        c, k = cfg.width, cfg.num_keypoints
        self.stem = nn.Sequential(conv_bn(1, cfg.stem_width, 3, 2), conv_bn(cfg.stem_width, c, 3, 2), Residual(c))
        self.hourglass = Hourglass(cfg.depth, c)
        self.neck = conv_bn(c, c, 3)
        self.khead = nn.Sequential(conv_bn(c, c, 3), nn.Conv2d(c, 3 * k, 1))  # K heatmaps, then K (x, y) offsets
        self.vis = nn.Linear(2 * c, k)  # from the features' mean and max over the input
        with torch.no_grad():
            self.khead[-1].bias.zero_()
            self.khead[-1].bias[:k].fill_(HEATMAP_PRIOR_LOGIT)
            self.vis.bias.zero_()

    def forward(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        """image (B, 1, S, S) -> features, kmap_logit, koff, kvis_logit (module doc)."""
        f = self.neck(self.hourglass(self.stem(image)))
        out = self.khead(f)
        b, _, h, w = out.shape
        k = self.cfg.num_keypoints
        pooled = torch.cat([f.mean((2, 3)), f.amax((2, 3))], dim=1)
        return {"features": f, "kmap_logit": out[:, :k],
                "koff": torch.sigmoid(out[:, k:].reshape(b, k, 2, h, w)) - 0.5, "kvis_logit": self.vis(pooled)}

    def metadata(self) -> dict[str, str]:
        """What a weights file records beside the tensors (perception/weights.save_weights): the format, the model
        kind and the target (name, sha256, keypoint names)."""
        return {FORMAT_KEY: KEYPOINT_FORMAT, KIND_KEY: MODEL_KIND, TARGET_KEY: json.dumps(self.target, sort_keys=True)}


def init_keypoint_net(cfg: KeypointModelConfig, seed: int, target: dict | None = None) -> KeypointNet:
    """A KeypointNet whose weights are drawn from a generator seeded by `seed` (not the global one): He-normal,
    the output layers 100 times calmer (as perception/train.init_model draws CornerNet's)."""
    model = KeypointNet(cfg, target)
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            head = name.startswith(("khead.1", "vis."))
            if p.ndim > 1:
                std = (2.0 / p[0].numel()) ** 0.5 * (0.01 if head else 1.0)
                p.copy_(torch.randn(p.shape, generator=gen) * std)
            elif name.endswith(".bias") and not head:
                p.zero_()
    return model


def decode_keypoints(kmap: np.ndarray, koff: np.ndarray, stride: int) -> dict[str, np.ndarray]:
    """Each keypoint at its channel's peak: kmap (K, H, W) scores in [0, 1], koff (K, 2, H, W) offsets (cells).
    Returns points_px (K, 2) input px (the peak cell plus its offset: heatmaps.to_pixels), score (K,) the peak's
    score, cell (K, 2) int (row, col)."""
    k, h, w = kmap.shape
    flat = np.asarray(kmap, np.float64).reshape(k, -1)
    peak = flat.argmax(axis=1)
    rows, cols = peak // w, peak % w
    idx = np.arange(k)
    u = np.stack([cols + koff[idx, 0, rows, cols], rows + koff[idx, 1, rows, cols]], axis=-1)
    return {"points_px": to_pixels(u, stride), "score": flat[idx, peak], "cell": np.stack([rows, cols], axis=-1)}
