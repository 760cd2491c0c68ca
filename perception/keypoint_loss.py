"""The keypoint network's targets and loss, apart from the model: a Gaussian heatmap per keypoint (CenterNet's
focal loss, perception/losses.py's terms), the sub-cell offset's L1 at the keypoint's cell, and the visibility's
binary cross-entropy, each sample's loss the smallest over the target's symmetric relabelings.

Symmetric relabelings. A rotation R of the Target's symmetries (target_shape.Symmetry) maps keypoint k onto
keypoint perm[k] (R X_k = X_perm[k]); when neither its shape nor its materials break it, the pose R_true R^T shows
the same image as the true pose, with keypoint k where the truth has keypoint perm^-1[k]. No image can tell the
two labelings apart, so a loss that insists on one teaches the network the average of the twins. Each sample's
loss is therefore the smallest of its losses under the labelings `labels[:, perm]`, one per permutation of
`relabelings(target)` (the identity first, then each symmetry the materials keep; the kept rotations are closed
under inversion, so perm and its inverse are both among them). Minimum-over-symmetries losses are known to train
poorly on views that are themselves ambiguous (docs/field-notes.md); this is the foundation, the tracker settles
the twins.

Targets (torch, built in batch; shapes for N samples, K keypoints, H x W cells):
    kmap:  (N, K, H, W) float32, a Gaussian of sigma_cells around keypoint k's cell in channel k, 1 at the cell
    kcell: (N, K) int64, the cell's flat index row W + col (0 where not valid)
    koff:  (N, K, 2) float32, the sub-cell offset (x, y) u - round(u) in [-0.5, 0.5]
    valid: (N, K) bool, the keypoint is visible, in the frame and inside the input (the visibility target too)
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn.functional as F

from envisat_pose.config import Config
from envisat_pose.perception.losses import check_loss_weights, focal_log_likelihood


@dataclass(frozen=True)
class KeypointLossConfig(Config):
    """Weights of the terms; focal_alpha, focal_beta: CenterNet's exponents (as perception/losses.LossConfig)."""

    heatmap: float = 1.0
    offset: float = 1.0
    visibility: float = 0.5
    focal_alpha: float = 2.0
    focal_beta: float = 4.0

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        check_loss_weights(self, ("heatmap", "offset", "visibility"), p)  # losses.py's bounds

    def to_dict(self) -> dict:
        return asdict(self)


def relabelings(symmetries, num_keypoints: int) -> np.ndarray:
    """(P, K) int64: the identity, then the permutation of each symmetry (target_shape.Symmetry) that neither the
    shape nor the materials break (`broken_by` ''), in the Target's order."""
    perms = [np.arange(num_keypoints)] + [np.asarray(s.perm, np.int64) for s in symmetries if s.broken_by == ""]
    return np.stack(perms).astype(np.int64)


def encode_keypoints(points_px: torch.Tensor, valid: torch.Tensor, shape_hw: tuple[int, int], stride: int,
                     sigma_cells: float = 1.0) -> dict[str, torch.Tensor]:
    """The targets of the module doc from keypoints at input px points_px (N, K, 2) (float64; OpenCV convention)
    and valid (N, K) bool; shape_hw the heatmap's (H, W). A valid keypoint whose cell falls outside the map is
    not marked (its valid is cleared)."""
    h, w = shape_hw
    u = (points_px.to(torch.float64) + 0.5) / stride - 0.5  # heatmaps.to_cells
    mark = valid & torch.isfinite(u).all(-1)
    c = torch.round(torch.where(mark[..., None], u, torch.zeros_like(u))).to(torch.int64)  # (col, row)
    mark = mark & (c[..., 0] >= 0) & (c[..., 0] < w) & (c[..., 1] >= 0) & (c[..., 1] < h)
    xx = torch.arange(w, device=u.device)[None, None, None, :]
    yy = torch.arange(h, device=u.device)[None, None, :, None]
    d2 = (xx - c[..., 0, None, None]) ** 2 + (yy - c[..., 1, None, None]) ** 2  # (N, K, H, W)
    if sigma_cells > 0:
        g = torch.exp(-d2.to(torch.float64) / (2 * sigma_cells ** 2)).to(torch.float32)
    else:
        g = torch.zeros(d2.shape, dtype=torch.float32, device=u.device)
    g = torch.where(d2 == 0, torch.ones_like(g), g)
    kmap = torch.where(mark[..., None, None], g, torch.zeros_like(g))
    kcell = torch.where(mark, c[..., 1] * w + c[..., 0], torch.zeros_like(c[..., 0]))
    koff = torch.where(mark[..., None], u - c.to(torch.float64), torch.zeros_like(u)).to(torch.float32)
    return {"kmap": kmap, "kcell": kcell, "koff": koff, "valid": mark}


def labelled_terms(out: dict, batch: dict, perm: torch.Tensor, cfg: KeypointLossConfig
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each sample's summed terms under the labeling batch[:, perm]: (heatmap focal sum, offset L1 sum over its
    valid keypoints' cells, visibility BCE sum), each (N,)."""
    logit, koff, vis = out["kmap_logit"], out["koff"], out["kvis_logit"]
    n, k, h, w = logit.shape
    ll, _ = focal_log_likelihood(logit, batch["kmap"][:, perm], cfg.focal_alpha, cfg.focal_beta)
    heat = -ll.sum((1, 2, 3))
    valid = batch["valid"][:, perm].to(logit.dtype)
    cell = batch["kcell"][:, perm]
    at = koff.reshape(n, k, 2, h * w).gather(3, cell[:, :, None, None].expand(n, k, 2, 1))[..., 0]  # (N, K, 2)
    offset = ((at - batch["koff"][:, perm]).abs().sum(-1) * valid).sum(1)
    visibility = F.binary_cross_entropy_with_logits(vis, valid, reduction="none").sum(1)
    return heat, offset, visibility


def keypoint_losses(out: dict, batch: dict, perms: torch.Tensor, cfg: KeypointLossConfig) -> dict:
    """The terms and their weighted total ('loss'), scalar tensors: each sample's total is the smallest over the
    relabelings perms (P, K) (module doc); heatmap and offset normalized by the batch's valid keypoints (as
    perception/losses.corner_losses normalizes by the positives), visibility by N K. 'twin': the share of samples
    whose smallest loss was under another labeling than the identity (perms[0])."""
    n, k = batch["valid"].shape
    positives = batch["valid"].sum().to(out["kmap_logit"].dtype).clamp(min=1)
    terms = torch.stack([torch.stack(labelled_terms(out, batch, p, cfg)) for p in perms])  # (P, 3, N)
    scale = torch.stack([cfg.heatmap / positives, cfg.offset / positives,
                         torch.as_tensor(cfg.visibility / (n * k), dtype=positives.dtype, device=positives.device)])
    total = (terms * scale[None, :, None]).sum(1)  # (P, N)
    best = total.argmin(0)  # no host sync: the choice is gathered, never read back here
    chosen = terms.gather(0, best[None, None, :].expand(1, 3, n))[0]  # (3, N)
    return {"loss": total.gather(0, best[None])[0].sum(), "heatmap": chosen[0].sum() / positives,
            "offset": chosen[1].sum() / positives, "visibility": chosen[2].sum() / (n * k),
            "twin": (best != 0).to(total.dtype).mean()}
