"""Losses of the corner network, apart from the model: heatmap focal loss, offset L1, covariance NLL, line BCE.

Inputs are the model's outputs (perception/model.py) and a collated batch of perception/data.py samples.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F

from envisat_pose.config import Config, check

# A term's weight counts in its ratio to the others' (AdamW normalises the gradient's scale); float32 keeps about 7
# digits, so a term weighted over 1e6 times another drowns it in their sum, and at 1e300 the float32 loss was inf
# and every weight NaN by the second step (TrainingDiverged blaming the learning rate).
MAX_LOSS_WEIGHT = 1e6
# focal_alpha: the negatives' factor p^alpha at the heatmap's starting prior (p = sigmoid(-4.6) = 0.01, model.py)
# falls below float32's least number (1.4e-45) beyond alpha = 22.4: the negatives weigh nothing; at 1e300 every
# weight was NaN by the second step. focal_beta has no such bound: at any size it only leaves out the negatives
# near a corner's peak (the loss stayed finite at 1e300).
MAX_FOCAL_ALPHA = 22.0


def check_loss_weights(cfg, names: tuple[str, ...], p: str) -> None:
    """ConfigError naming the first of cfg's loss weights `names` outside [0, MAX_LOSS_WEIGHT], or focal_alpha
    beyond MAX_FOCAL_ALPHA (LossConfig's and keypoint_loss.KeypointLossConfig's)."""
    for name in names:
        check(0 <= getattr(cfg, name) <= MAX_LOSS_WEIGHT, f"{p}{name}", getattr(cfg, name),
              f"a weight in [0, {MAX_LOSS_WEIGHT:g}] (0: the term off; the ratios count, float32 keeps 7 digits)")
    check(0 <= cfg.focal_alpha <= MAX_FOCAL_ALPHA, f"{p}focal_alpha", cfg.focal_alpha, f"an exponent in [0, "
          f"{MAX_FOCAL_ALPHA:g}] (beyond, p^alpha at the heatmap's starting p = 0.01 underflows float32)")
    check(cfg.focal_beta >= 0, f"{p}focal_beta", cfg.focal_beta, "an exponent >= 0")


@dataclass(frozen=True)
class LossConfig(Config):
    """Weights of the terms; focal_alpha, focal_beta: CenterNet's exponents (positives at the 1s of jmap,
    negatives down-weighted by (1 - jmap)^beta near them). Each at least 0 (a negative weight trains the term
    the wrong way)."""

    heatmap: float = 1.0
    offset: float = 1.0
    nll: float = 0.1
    line: float = 0.5
    focal_alpha: float = 2.0
    focal_beta: float = 4.0

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        check_loss_weights(self, ("heatmap", "offset", "nll", "line"), p)

    def to_dict(self) -> dict:
        return asdict(self)


def focal_log_likelihood(logit: torch.Tensor, target: torch.Tensor, alpha: float, beta: float
                         ) -> tuple[torch.Tensor, torch.Tensor]:
    """CenterNet's penalty-reduced focal terms, element by element: (the negated loss of each element, the positives
    (target 1) as 0/1 weights), both shaped like logit. Positives and negatives are weights, not boolean indices:
    no data-dependent shapes, so no host sync (a `nonzero`) on a GPU."""
    p = torch.sigmoid(logit).clamp(1e-6, 1 - 1e-6)
    pos = (target >= 1.0).to(logit.dtype)
    log_p, log_1mp = F.logsigmoid(logit), F.logsigmoid(-logit)
    pos_loss = (1 - p) ** alpha * log_p
    neg_loss = ((1 - target) ** beta) * p ** alpha * log_1mp
    return pos * pos_loss + (1 - pos) * neg_loss, pos


def focal_loss(logit: torch.Tensor, target: torch.Tensor, alpha: float, beta: float) -> torch.Tensor:
    """CenterNet's penalty-reduced focal loss over (B, J, H, W), normalized by the number of positives
    (focal_log_likelihood's terms summed; the sums are those of the indexed form, tests/perception/test_losses.py)."""
    ll, pos = focal_log_likelihood(logit, target, alpha, beta)
    return -ll.sum() / pos.sum().clamp(min=1)


def chol_nll(err_px: torch.Tensor, jchol: torch.Tensor, dim: int = -1) -> torch.Tensor:
    """Gaussian negative log-likelihood (without the constant) of errors under L L^T: err_px holds (x, y) px and
    jchol (log l11, log l22, l21) along `dim` (-1: (N, 2) and (N, 3); 1: maps (B, 2, H, W) and (B, 3, H, W)):
    0.5 |L^-1 e|^2 + log l11 + log l22, with `dim` reduced."""
    a, b, c = jchol.unbind(dim)
    ex, ey = err_px.unbind(dim)
    z1 = ex / torch.exp(a)
    z2 = (ey - c * z1) / torch.exp(b)
    return 0.5 * (z1 ** 2 + z2 ** 2) + a + b


def corner_losses(out: dict, batch: dict, line_logits: torch.Tensor, cfg: LossConfig, stride: int) -> dict:
    """The terms and their weighted total ('loss'), each a scalar tensor. The junction cells (jmask) weight the
    offset and covariance terms over the whole map (no boolean indexing: see focal_loss)."""
    focal = focal_loss(out["jmap_logit"], batch["jmap"], cfg.focal_alpha, cfg.focal_beta)
    on = batch["jmask"] > 0  # (B, H, W)
    mask = on.to(out["joff"].dtype)
    n = mask.sum().clamp(min=1)
    off_err = out["joff"] - batch["joff"]  # (B, 2, H, W)
    offset = (off_err.abs().sum(1) * mask).sum() / n
    # the covariance learns the offset's actual error (detached: the NLL must not move the position); cells off
    # the junctions get a neutral factor, so an extreme logit there cannot make inf * 0 = nan in the gradient
    err_px = off_err.detach() * stride
    jchol = torch.where(on[:, None], out["jchol"], torch.zeros_like(out["jchol"]))
    nll = (chol_nll(err_px, jchol, dim=1) * mask).sum() / n
    w = batch["line_weight"]
    line = (F.binary_cross_entropy_with_logits(line_logits, batch["line_label"], reduction="none") * w).sum() \
        / w.sum().clamp(min=1)
    total = cfg.heatmap * focal + cfg.offset * offset + cfg.nll * nll + cfg.line * line
    return {"loss": total, "heatmap": focal, "offset": offset, "nll": nll, "line": line}
