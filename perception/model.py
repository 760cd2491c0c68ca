"""The corner network: a strided stem, a compact hourglass, L-CNN's junction head (heatmap + sub-cell offset) with
a per-junction 2x2 covariance, and L-CNN's line verification (line-of-interest pooling, then a small classifier).

Model, loss and loop live apart (perception/losses.py, perception/train.py): `forward` returns raw maps only.
One frozen ModelConfig is passed explicitly; nothing global.

Shapes for a batch of B gray images of S x S input pixels, stride s = 4, H = W = S / s cells:
    image:      (B, 1, S, S) float, roughly zero-mean unit-variance (perception/data.py normalizes)
    features:   (B, C, H, W)
    jmap_logit: (B, J, H, W) junction-type logits (J = N_JTYPES; sigmoid gives the score)
    joff:       (B, 2, H, W) sub-cell offset (x, y) in [-0.5, 0.5] heatmap units
    jchol:      (B, 3, H, W) (log l11, log l22, l21) of the Cholesky factor L of the position covariance, in
                INPUT pixels: cov = L L^T, L = [[e^a, 0], [c, e^b]]
    segments:   (B, M, 2, 2) segment end points (x, y) in input pixels -> line logits (B, M)
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

from envisat_pose.config import Config, check
from envisat_pose.perception.heatmaps import N_JTYPES

# The largest network input side, px: the largest image side the jobs take (generate's resolution_px); a crop is
# resized up to it, never past the frame's own pixels. The hourglass halves it depth times down from stride 4, so
# depth is at most log2(MAX_INPUT_PX / 4) = 10 (at 2^63 - 1 levels the multiple it asks for, 4 x 2^depth, was
# computed until the memory ran out).
MAX_INPUT_PX = 4096
MAX_DEPTH = 10
# The most channels of any layer (width, stem_width, line_dim, line_hidden): a 3x3 convolution of C channels holds
# 9 C^2 weights, 9.4M at 1024 (38 MB, three times that with AdamW's moments), and the hourglass has tens of them;
# width = 100000 asked the allocator for 360 GB at the first convolution (a RuntimeError before any step).
MAX_CHANNELS = 1024


@dataclass(frozen=True)
class ModelConfig(Config):
    """Architecture. input_px: network input side; width: channels of the hourglass; depth: hourglass levels
    below stride 4; line_points: samples along a segment; line_pool: max-pool factor over them (L-CNN: 32 -> 8);
    line_dim: channels sampled per point; line_hidden: the classifier's hidden units."""

    input_px: int = 320
    width: int = 48
    depth: int = 3
    stem_width: int = 24
    n_jtypes: int = N_JTYPES
    line_points: int = 32
    line_pool: int = 4
    line_dim: int = 32
    line_hidden: int = 128

    stride = 4

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        check_backbone(self, p)
        check(self.n_jtypes == N_JTYPES, f"{p}n_jtypes", self.n_jtypes,  # the heatmaps' channels (tensor mismatch)
              f"{N_JTYPES}, the junction types the labels are encoded in (perception/heatmaps.py)")
        for name in ("line_dim", "line_hidden"):  # 0 or less: a layer of no units (a traceback at the build)
            check(1 <= getattr(self, name) <= MAX_CHANNELS, f"{p}{name}", getattr(self, name),
                  f"1 to {MAX_CHANNELS} channels")
        # a segment sampled at no point (a division by zero at the build), or more points than the input has pixels
        check(1 <= self.line_points <= self.input_px, f"{p}line_points", self.line_points,
              f"1 to input_px ({self.input_px}) samples along a segment")
        check(1 <= self.line_pool <= self.line_points, f"{p}line_pool", self.line_pool,
              f"a pooling factor of 1 to line_points ({self.line_points})")  # 0: a division by zero
        check(self.line_points % self.line_pool == 0, f"{p}line_points", self.line_points,
              f"a multiple of line_pool ({self.line_pool})")

    def to_dict(self) -> dict:
        return asdict(self)


def check_backbone(cfg, p: str) -> None:
    """ConfigError unless cfg's stem and hourglass (depth, width, stem_width, input_px, stride) can be built: at
    least one level, positive widths, an input side a multiple of stride x 2^depth. p: the field prefix ('model.')."""
    check(1 <= cfg.depth <= MAX_DEPTH, f"{p}depth", cfg.depth, f"1 to {MAX_DEPTH} hourglass levels (an input of "
          f"at most {MAX_INPUT_PX} px halved down from stride {cfg.stride})")  # before 2 ** depth is computed
    for name in ("width", "stem_width"):
        check(1 <= getattr(cfg, name) <= MAX_CHANNELS, f"{p}{name}", getattr(cfg, name), f"1 to {MAX_CHANNELS} channels")
    m = cfg.stride * 2 ** cfg.depth
    check(cfg.input_px <= MAX_INPUT_PX, f"{p}input_px", cfg.input_px,
          f"at most {MAX_INPUT_PX} px (the largest image side the jobs take)")
    check(cfg.input_px >= m and cfg.input_px % m == 0, f"{p}input_px", cfg.input_px,
          f"a multiple of {m} (stride {cfg.stride}, {cfg.depth} hourglass levels)")


def conv_bn(cin: int, cout: int, k: int = 3, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, k, stride, k // 2, bias=False), nn.BatchNorm2d(cout),
                         nn.ReLU(inplace=True))


class Residual(nn.Module):
    """Basic residual block (two 3x3 convolutions), channels kept."""

    def __init__(self, ch: int):
        super().__init__()
        self.body = nn.Sequential(nn.Conv2d(ch, ch, 3, 1, 1, bias=False), nn.BatchNorm2d(ch), nn.ReLU(inplace=True),
                                  nn.Conv2d(ch, ch, 3, 1, 1, bias=False), nn.BatchNorm2d(ch))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(x + self.body(x))


class Hourglass(nn.Module):
    """One hourglass of `depth` levels (Newell et al.): a skip branch at each scale, max-pool down, nearest up."""

    def __init__(self, depth: int, ch: int):
        super().__init__()
        self.skip = Residual(ch)
        self.down = Residual(ch)
        self.inner = Hourglass(depth - 1, ch) if depth > 1 else Residual(ch)
        self.up = Residual(ch)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        low = self.up(self.inner(self.down(F.max_pool2d(x, 2))))
        return self.skip(x) + F.interpolate(low, size=x.shape[-2:], mode="nearest")


class CornerNet(nn.Module):
    """Backbone + junction head + line verification head (see the module doc for shapes)."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        c = cfg.width
        self.stem = nn.Sequential(conv_bn(1, cfg.stem_width, 3, 2), conv_bn(cfg.stem_width, c, 3, 2), Residual(c))
        self.hourglass = Hourglass(cfg.depth, c)
        self.neck = conv_bn(c, c, 3)
        self.jhead = nn.Sequential(conv_bn(c, c, 3), nn.Conv2d(c, cfg.n_jtypes + 2 + 3, 1))
        # line of interest: reduce, sample along the segment, max-pool, classify (L-CNN's fc1 / pooling / fc2)
        self.line_reduce = nn.Conv2d(c, cfg.line_dim, 1)
        n = cfg.line_dim * cfg.line_points // cfg.line_pool
        self.line_mlp = nn.Sequential(nn.Linear(n, cfg.line_hidden), nn.ReLU(inplace=True),
                                      nn.Linear(cfg.line_hidden, cfg.line_hidden), nn.ReLU(inplace=True),
                                      nn.Linear(cfg.line_hidden, 1))
        # a junction's prior is rare: start the heatmap logits at sigmoid ~ 0.01 (focal-loss practice)
        with torch.no_grad():
            self.jhead[-1].bias.zero_()
            self.jhead[-1].bias[: cfg.n_jtypes].fill_(-4.6)

    def forward(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        """image (B, 1, S, S) -> features, jmap_logit, joff, jchol (module doc)."""
        f = self.neck(self.hourglass(self.stem(image)))
        out = self.jhead(f)
        j = self.cfg.n_jtypes
        return {"features": f, "jmap_logit": out[:, :j], "joff": torch.sigmoid(out[:, j:j + 2]) - 0.5,
                "jchol": out[:, j + 2:]}

    def line_logits(self, features: torch.Tensor, segments_px: torch.Tensor) -> torch.Tensor:
        """Line-of-interest pooling: features (B, C, H, W), segments (B, M, 2, 2) in input px -> logits (B, M)."""
        cfg = self.cfg
        b, m = segments_px.shape[:2]
        if m == 0:
            return features.new_zeros((b, 0))
        h, w = features.shape[-2:]
        u = (segments_px + 0.5) / cfg.stride - 0.5  # heatmap units: cell centres at integers
        lam = torch.linspace(0.0, 1.0, cfg.line_points, device=features.device, dtype=features.dtype)
        pts = u[:, :, :1, :] + lam[None, None, :, None] * (u[:, :, 1:, :] - u[:, :, :1, :])  # (B, M, P, 2)
        scale = torch.tensor([2.0 / max(w - 1, 1), 2.0 / max(h - 1, 1)], device=features.device,
                             dtype=features.dtype)
        grid = pts * scale - 1.0  # align_corners=True: -1 and 1 are the centres of the corner cells
        sampled = F.grid_sample(self.line_reduce(features), grid, mode="bilinear", padding_mode="zeros",
                                align_corners=True)  # (B, D, M, P)
        x = sampled.permute(0, 2, 1, 3).reshape(b * m, cfg.line_dim, cfg.line_points)
        x = F.max_pool1d(x, cfg.line_pool).flatten(1)
        return self.line_mlp(x).view(b, m)
