"""Losses of the corner network, apart from the model: heatmap focal loss, offset L1, covariance NLL, line BCE.

Inputs are the model's outputs (perception/model.py) and a collated batch of perception/data.py samples.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F


@dataclass(frozen=True)
class LossConfig:
    """Weights of the terms; focal_alpha, focal_beta: CenterNet's exponents (positives at the 1s of jmap,
    negatives down-weighted by (1 - jmap)^beta near them)."""

    heatmap: float = 1.0
    offset: float = 1.0
    nll: float = 0.1
    line: float = 0.5
    focal_alpha: float = 2.0
    focal_beta: float = 4.0

    def to_dict(self) -> dict:
        return asdict(self)


def focal_loss(logit: torch.Tensor, target: torch.Tensor, alpha: float, beta: float) -> torch.Tensor:
    """CenterNet's penalty-reduced focal loss over (B, J, H, W), normalized by the number of positives."""
    p = torch.sigmoid(logit).clamp(1e-6, 1 - 1e-6)
    pos = target >= 1.0
    log_p, log_1mp = F.logsigmoid(logit), F.logsigmoid(-logit)
    pos_loss = -((1 - p) ** alpha * log_p)[pos].sum()
    neg_loss = -(((1 - target) ** beta) * p ** alpha * log_1mp)[~pos].sum()
    return (pos_loss + neg_loss) / pos.sum().clamp(min=1)


def chol_nll(err_px: torch.Tensor, jchol: torch.Tensor) -> torch.Tensor:
    """Gaussian negative log-likelihood (without the constant) of errors (N, 2) px under L L^T, jchol (N, 3) =
    (log l11, log l22, l21): 0.5 |L^-1 e|^2 + log l11 + log l22."""
    a, b, c = jchol.unbind(-1)
    z1 = err_px[:, 0] / torch.exp(a)
    z2 = (err_px[:, 1] - c * z1) / torch.exp(b)
    return 0.5 * (z1 ** 2 + z2 ** 2) + a + b


def corner_losses(out: dict, batch: dict, line_logits: torch.Tensor, cfg: LossConfig, stride: int) -> dict:
    """The terms and their weighted total ('loss'), each a scalar tensor."""
    focal = focal_loss(out["jmap_logit"], batch["jmap"], cfg.focal_alpha, cfg.focal_beta)
    mask = batch["jmask"] > 0  # (B, H, W)
    n = mask.sum().clamp(min=1)
    off_pred = out["joff"].permute(0, 2, 3, 1)[mask]  # (N, 2)
    off_true = batch["joff"].permute(0, 2, 3, 1)[mask]
    offset = (off_pred - off_true).abs().sum() / n
    # the covariance learns the offset's actual error (detached: the NLL must not move the position)
    err_px = (off_pred.detach() - off_true) * stride
    nll = chol_nll(err_px, out["jchol"].permute(0, 2, 3, 1)[mask]).sum() / n
    w = batch["line_weight"]
    line = (F.binary_cross_entropy_with_logits(line_logits, batch["line_label"], reduction="none") * w).sum() \
        / w.sum().clamp(min=1)
    total = cfg.heatmap * focal + cfg.offset * offset + cfg.nll * nll + cfg.line * line
    return {"loss": total, "heatmap": focal, "offset": offset, "nll": nll, "line": line}
