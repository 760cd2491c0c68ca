"""Training batches made on the device from whole frames: crops, resizing, style augmentation and targets, in batch.

The online trainer (pipelines/detector/online.py) hands raw rendered frames and their labels as tensors; this module makes
of them the batch that perception/data.py's make_sample + perception/stream.py's collate_batch make from shards
(the same keys, shapes, dtypes and meaning; the same distributions), as torch ops over the whole batch with
per-sample parameters:

- the crop box by data.crop_box's rule (the usable corners' extent x margin, its own scale and shift jitter, an
  integer square box) or, a share whole_frame_prob, the whole frame (0, 0, max(H, W));
- crop and resize as two separable resampling matrices per sample, out = Y @ frame @ X^T: cv2.INTER_AREA's area
  weights where the crop shrinks (side >= S), INTER_LINEAR's bilinear weights (the crop's edge pixels repeated)
  where it grows, zeros outside the frame, rounded to whole gray levels as cv2 does on uint8 (data.crop_resize);
  output pixel j covers input [j side / S, (j + 1) side / S) of the crop, so its centre is data.to_input_px's
  map, which moves the labels (float64, the same operations);
- data.augment_style's photometric augmentation, each sample its own draws from the same distributions (gain and
  offset, contrast, gamma, Gaussian blur with cv2's kernel, glare, random erasing, signal-dependent noise);
- the junction targets of heatmaps.encode_junctions (batched: equal to it) and line targets by data.line_targets'
  rule (its own random choice of the negatives and the random segments, the same distribution).

Random numbers: every parameter from a CPU torch.Generator the caller seeds (the same draws on every device), the
per-pixel noise from a device generator seeded from it (the same bits for a given seed and device type).

Frames: (B, H, W) gray levels 0-255, uint8 or float, on the device. Labels: corners_px (B, 8, 2) OpenCV pixels
(centres at integer coordinates), visible (B, 8) bool, in_frame (B, 8) bool. A batch of N samples takes sample
n from frame frame_of_sample[n] (several crops of a frame: its index several times).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from envisat_pose.geometry import EDGES
from envisat_pose.perception.data import IMAGE_MEAN, IMAGE_STD, N_SEGMENTS, DataConfig
from envisat_pose.perception.heatmaps import CORNER_JTYPE, N_JTYPES

# samples resampled at once: bounds the (n, S, H) resampling matrices and the (n, H, W) float frames
RESAMPLE_CHUNK = 32
# the pairs of corners (i < j) in data.line_targets' order, and which are box edges
PAIRS = [(i, j) for i in range(8) for j in range(i + 1, 8)]
EDGE_SET = {tuple(sorted(e)) for e in EDGES}
BLUR_SIGMA_MAX = 1.8  # data.augment_style's largest blur
BLUR_KSIZE_MAX = round(BLUR_SIGMA_MAX * 8 + 1) | 1  # cv2's kernel size for it (float images)


# ---------------------------------------------------------------------------------------------------------
# Crop boxes


def draw_crop_params(n: int, cfg: DataConfig, generator: torch.Generator) -> dict[str, torch.Tensor]:
    """Per-sample crop draws (CPU): whole (n,) bool (the whole frame, probability cfg.whole_frame_prob),
    u_scale (n,) and u_shift (n, 2) float64 uniform in [-1, 1] (data.crop_box's jitter draws)."""
    whole = torch.rand(n, generator=generator, dtype=torch.float64) < cfg.whole_frame_prob
    u_scale = torch.rand(n, generator=generator, dtype=torch.float64) * 2 - 1
    u_shift = torch.rand((n, 2), generator=generator, dtype=torch.float64) * 2 - 1
    return {"whole": whole, "u_scale": u_scale, "u_shift": u_shift}


def crop_boxes(corners_px: torch.Tensor, usable: torch.Tensor, image_hw: tuple[int, int] | torch.Tensor,
               cfg: DataConfig, params: dict[str, torch.Tensor] | None = None) -> torch.Tensor:
    """data.crop_box for a batch: (N, 3) int64 (x0, y0, side) square boxes around the usable corners (the image
    centre and min(H, W) when none), side = margin x their extent (at least 16 px, the box at least 32 px);
    jittered by params (draw_crop_params, on the corners' device), whole frames where params['whole'].
    corners_px (N, 8, 2) float64 full-image px; usable (N, 8) bool; image_hw (H, W) of every sample, or each
    sample's own (N, 2) int64 (frames of several sizes). params None: no jitter, no whole frames."""
    c = corners_px.to(torch.float64)
    if torch.is_tensor(image_hw):
        h, w = image_hw[:, 0].to(c.device, torch.float64), image_hw[:, 1].to(c.device, torch.float64)
    else:
        h, w = (torch.full((len(c),), float(v), dtype=torch.float64, device=c.device) for v in image_hw)
    ok = usable & torch.isfinite(c).all(-1)
    inf = torch.tensor(math.inf, dtype=torch.float64, device=c.device)
    lo = torch.where(ok[..., None], c, inf).amin(1)
    hi = torch.where(ok[..., None], c, -inf).amax(1)
    some = ok.any(1)
    mid = torch.stack([w / 2, h / 2], dim=1)
    centre = torch.where(some[:, None], (lo + hi) / 2, mid)
    extent = torch.where(some, (hi - lo).amax(-1).clamp(min=16.0), torch.minimum(h, w))
    side = extent * cfg.crop_margin
    if params is not None:
        side = side * torch.exp(params["u_scale"] * cfg.crop_scale_jitter)
        centre = centre + params["u_shift"] * cfg.crop_shift_jitter * side[:, None]
    side = torch.ceil(side.clamp(min=32.0))
    origin = torch.round(centre - side[:, None] / 2)
    box = torch.cat([origin, side[:, None]], dim=1).to(torch.int64)
    if params is not None:
        zero = torch.zeros_like(h)
        whole = torch.stack([zero, zero, torch.maximum(h, w)], dim=1).to(torch.int64)
        box = torch.where(params["whole"][:, None], whole, box)
    return box


def max_crop_side(image_hw: tuple[int, int], cfg: DataConfig) -> int:
    """A bound on crop_boxes' sides for an image of image_hw: the whole frame, or the margin and the largest scale
    jitter over the usable corners' extent (within the frame, at least 16 px; the box at least 32 px)."""
    extent = max(*image_hw, 16)  # in-frame corners span at most the frame
    return max(extent, 32, math.ceil(extent * cfg.crop_margin * math.exp(cfg.crop_scale_jitter)) + 1)


def to_input_px_batch(points_px: torch.Tensor, box: torch.Tensor, out_px: int) -> torch.Tensor:
    """data.to_input_px for a batch, in float64 with the same operations: full-image px (N, P, 2) -> input px
    of each sample's crop box (N, 3)."""
    b = box.to(torch.float64)
    s = out_px / b[:, 2]
    return (points_px.to(torch.float64) - b[:, None, :2] + 0.5) * s[:, None, None] - 0.5


# ---------------------------------------------------------------------------------------------------------
# Crop and resize


def area_taps(origin: torch.Tensor, side: torch.Tensor, out_px: int, taps: int) -> tuple[torch.Tensor, torch.Tensor]:
    """cv2.INTER_AREA along one axis, for crops that shrink (side >= out_px): output j averages the crop's
    [j r, (j + 1) r) (r = side / out_px), each pixel weighted by its overlap over r. Returns the frame pixel
    (N, out_px, T) int64 and weight (N, out_px, T) float32 of each of its `taps` >= ceil(r) + 1 taps. origin (N,),
    side (N,) int64: the crop's first pixel and size on this axis."""
    r = (side.to(torch.float64) / out_px)[:, None, None]
    j = torch.arange(out_px, device=origin.device, dtype=torch.float64)[None, :, None]
    c = torch.floor(j * r) + torch.arange(taps, device=origin.device, dtype=torch.float64)[None, None, :]
    overlap = torch.minimum(c + 1, (j + 1) * r) - torch.maximum(c, j * r)
    return (c + origin[:, None, None]).to(torch.int64), (overlap.clamp(min=0) / r).to(torch.float32)


def linear_taps(origin: torch.Tensor, side: torch.Tensor, out_px: int) -> tuple[torch.Tensor, torch.Tensor]:
    """cv2.INTER_LINEAR along one axis, for crops that grow (side < out_px): source x = (j + 0.5) side / out_px - 0.5
    in the crop, its two neighbours weighted 1 - t and t, the crop's edge pixels repeated beyond it (cv2's
    border). Returns frame pixels and weights (N, out_px, 2) as area_taps."""
    d = side.to(torch.float64)[:, None]
    fx = (torch.arange(out_px, device=origin.device, dtype=torch.float64)[None, :] + 0.5) * d / out_px - 0.5
    sx = torch.floor(fx)
    t = fx - sx
    low, high = sx < 0, sx >= d - 1
    t = torch.where(low | high, torch.zeros_like(t), t)
    sx = torch.where(low, torch.zeros_like(sx), torch.where(high, d - 1, sx))
    i0 = sx + origin.to(torch.float64)[:, None]
    i1 = i0 + torch.where(high, 0.0, 1.0)  # the weight there is 0 where clamped
    return torch.stack([i0, i1], -1).to(torch.int64), torch.stack([1 - t, t], -1).to(torch.float32)


def axis_weights(origin: torch.Tensor, side: torch.Tensor, length: int, out_px: int, max_side: int) -> torch.Tensor:
    """The resampling matrix of one axis (N, out_px, length) float32: area weights where the crop shrinks,
    bilinear where it grows (data.crop_resize's choice); frame pixels outside the frame contribute zero (the
    crop's zero padding). Built from each output's taps (the additions are exact: distinct pixels, or a 0);
    max_side bounds the sides (the tap count, fixed so that nothing waits for the device)."""
    shrink = side >= out_px
    taps = max(2, -(-int(max_side) // out_px) + 1)
    ia, wa = area_taps(origin, torch.where(shrink, side, torch.full_like(side, out_px)), out_px, taps)
    il, wl = linear_taps(origin, side, out_px)
    il = torch.cat([il, il[..., :1].expand(-1, -1, taps - 2)], -1)
    wl = torch.cat([wl, torch.zeros_like(wl[..., :1]).expand(-1, -1, taps - 2)], -1)
    idx = torch.where(shrink[:, None, None], ia, il)
    wt = torch.where(shrink[:, None, None], wa, wl)
    inside = (idx >= 0) & (idx < length)
    wt = torch.where(inside, wt, torch.zeros_like(wt))
    m = torch.zeros((len(side), out_px, length), dtype=torch.float32, device=origin.device)
    return m.scatter_add_(2, idx.clamp(0, length - 1), wt)


def crop_resize_batch(frames: torch.Tensor, frame_of_sample: torch.Tensor, box: torch.Tensor, out_px: int,
                quantize: bool = True, max_side: int | None = None) -> torch.Tensor:
    """data.crop_resize for a batch: (N, out_px, out_px) float32 gray levels, sample n the square box (x0, y0, side)
    of frame frame_of_sample[n] (zeros outside the frame) resized to out_px; rounded to whole levels (what cv2
    gives on uint8) unless quantize is False. frames (B, H, W) uint8 or float levels. max_side: a bound on the
    boxes' sides (max_crop_side; None: read from box, which waits for the device)."""
    _, h, w = frames.shape
    max_side = int(box[:, 2].max()) if max_side is None else max_side
    out = []
    for a in range(0, len(box), RESAMPLE_CHUNK):
        b = box[a:a + RESAMPLE_CHUNK]
        wy = axis_weights(b[:, 1], b[:, 2], h, out_px, max_side)
        wx = axis_weights(b[:, 0], b[:, 2], w, out_px, max_side)
        f = frames[frame_of_sample[a:a + RESAMPLE_CHUNK]].to(torch.float32)
        out.append(torch.bmm(torch.bmm(wy, f), wx.transpose(1, 2)))
    x = torch.cat(out)
    if not quantize:
        return x
    # cv2 rounds ties half to even, but up in its 2x2 averaging path (a shrink by exactly 2)
    half_up = (box[:, 2] == 2 * out_px).to(x.device)[:, None, None]
    return torch.where(half_up, torch.floor(x + 0.5), x.round()).clamp(0, 255)


# ---------------------------------------------------------------------------------------------------------
# Style augmentation


def draw_style_params(n: int, out_px: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
    """Per-sample draws of data.augment_style (CPU, float64 unless said): for each step a flag `on_<step>` (n,)
    bool with its probability and its values; erasing's box in whole pixels (int64) of an out_px image;
    noise_seed a seed for the device's per-pixel noise."""
    def u(lo, hi, shape=(n,)):
        return lo + (hi - lo) * torch.rand(shape, generator=generator, dtype=torch.float64)

    def flag(p):
        return torch.rand(n, generator=generator, dtype=torch.float64) < p

    p = {"on_gain": flag(0.8), "gain": u(0.5, 1.6), "offset": u(-0.08, 0.08),
         "on_contrast": flag(0.5), "contrast": u(0.6, 1.4),
         "on_gamma": flag(0.5), "gamma": u(0.6, 1.6),
         "on_blur": flag(0.4), "blur_sigma": u(0.3, BLUR_SIGMA_MAX),
         "on_glare": flag(0.3), "glare_centre": u(0, out_px, (n, 2)), "glare_size": u(0.03, 0.3, (n, 2)) * out_px,
         "glare_amp": u(0.2, 0.9),
         "on_erase": flag(0.3)}
    size = torch.floor(u(0.05, 0.3, (n, 2)) * out_px).to(torch.int64)  # (height, width), int() of data.py
    start = torch.floor(u(0, 1, (n, 2)) * (out_px - size + 1)).to(torch.int64)  # rng.integers(0, S - e + 1)
    p.update({"erase_size": size, "erase_start": start, "erase_value": u(0, 1),
              "on_noise": flag(0.7), "noise_sigma": u(0.0, 0.06),
              "noise_seed": torch.randint(0, 2 ** 62, (1,), generator=generator)})
    return p


def gaussian_kernels(sigma: torch.Tensor, on: torch.Tensor) -> torch.Tensor:
    """cv2.GaussianBlur's 1-D kernels for float images (size round(8 sigma + 1) | 1, normalized), centred in
    a common odd size (N, BLUR_KSIZE_MAX) float32; a unit impulse where `on` is False (no blur)."""
    ksize = torch.bitwise_or(torch.round(sigma * 8 + 1).to(torch.int64), 1)
    r = (BLUR_KSIZE_MAX - 1) // 2  # a fixed size: nothing waits for the device
    x = torch.arange(-r, r + 1, dtype=torch.float64, device=sigma.device)[None, :]
    k = torch.exp(-x ** 2 / (2 * sigma[:, None] ** 2)) * (x.abs() <= ((ksize - 1) // 2)[:, None])
    k = k / k.sum(1, keepdim=True)
    impulse = (x == 0).to(torch.float64).expand_as(k)
    return torch.where(on[:, None], k, impulse).to(torch.float32)


def blur(x: torch.Tensor, kernels: torch.Tensor) -> torch.Tensor:
    """Separable blur of each image (N, S, S) with its kernel (N, K), borders reflected (cv2's REFLECT_101)."""
    n, s, _ = x.shape
    r = (kernels.shape[1] - 1) // 2
    if r == 0:
        return x * kernels[:, :1, None]
    y = F.pad(x[None], (r, r, r, r), mode="reflect")  # (1, N, S + 2r, S + 2r): one channel per sample
    y = F.conv2d(y, kernels[:, None, None, :], groups=n)
    return F.conv2d(y, kernels[:, None, :, None], groups=n)[0]


def augment_style_batch(x: torch.Tensor, p: dict[str, torch.Tensor]) -> torch.Tensor:
    """data.augment_style for a batch: images (N, S, S) float32 in [0, 1] -> (N, S, S) float32 in [0, 1], each
    sample with its draws p (draw_style_params, moved to x's device): gain and offset, contrast about the mean,
    clip, gamma, Gaussian blur, a glare blob, random erasing, signal-dependent noise, clip."""
    n, s, _ = x.shape
    dev = x.device

    def col(name):
        return p[name].to(dev, torch.float32)[:, None, None]

    def on(name):
        return p[name].to(dev)[:, None, None]

    x = torch.where(on("on_gain"), x * col("gain") + col("offset"), x)
    m = x.mean((1, 2), keepdim=True)
    x = torch.where(on("on_contrast"), (x - m) * col("contrast") + m, x)
    x = x.clamp(0.0, 1.0)
    x = torch.where(on("on_gamma"), x ** col("gamma"), x)
    x = blur(x, gaussian_kernels(p["blur_sigma"].to(dev), p["on_blur"].to(dev)))
    grid = torch.arange(s, device=dev, dtype=torch.float32)
    centre, size = p["glare_centre"].to(dev, torch.float32), p["glare_size"].to(dev, torch.float32)
    gx = (grid[None, :] - centre[:, :1]) ** 2 / (2 * size[:, :1] ** 2)  # (N, S) along x
    gy = (grid[None, :] - centre[:, 1:]) ** 2 / (2 * size[:, 1:] ** 2)
    glare = col("glare_amp") * torch.exp(-(gx[:, None, :] + gy[:, :, None]))
    x = torch.where(on("on_glare"), x + glare, x)
    size, start = p["erase_size"].to(dev), p["erase_start"].to(dev)
    idx = torch.arange(s, device=dev)
    rows = (idx[None, :] >= start[:, :1]) & (idx[None, :] < start[:, :1] + size[:, :1])
    cols = (idx[None, :] >= start[:, 1:]) & (idx[None, :] < start[:, 1:] + size[:, 1:])
    erase = on("on_erase") & rows[:, :, None] & cols[:, None, :]
    x = torch.where(erase, col("erase_value").expand_as(x), x)
    gen = torch.Generator(device=dev).manual_seed(int(p["noise_seed"][0]))
    noise = torch.randn(x.shape, generator=gen, device=dev, dtype=torch.float32)
    sigma = col("noise_sigma")
    x = torch.where(on("on_noise"), x + noise * torch.sqrt(sigma ** 2 * x.clamp(0, 1) + (sigma / 3) ** 2), x)
    return x.clamp(0.0, 1.0)


# ---------------------------------------------------------------------------------------------------------
# Targets


def encode_junctions_batch(points_px: torch.Tensor, valid: torch.Tensor, jtypes: torch.Tensor, shape_hw: tuple[int, int],
                     stride: int, sigma_cells: float = 1.0) -> dict[str, torch.Tensor]:
    """heatmaps.encode_junctions for a batch, equal to it: points_px (N, P, 2) input px (float64), valid (N, P)
    bool, jtypes (P,) int64 in [0, N_JTYPES). Returns jmap (N, J, H, W), joff (N, 2, H, W), jmask (N, H, W)
    float32: the Gaussian of sigma_cells (computed in float64 like numpy's) at the cell round(u) of each marked
    junction, 1 there, its sub-cell offset u - round(u) (the later junction's where two share a cell)."""
    h, w = shape_hw
    n, npt, _ = points_px.shape
    dev = points_px.device
    u = (points_px.to(torch.float64) + 0.5) / stride - 0.5
    mark = valid & torch.isfinite(u).all(-1)
    c = torch.round(torch.where(mark[..., None], u, torch.zeros_like(u))).to(torch.int64)  # (col, row)
    mark = mark & (c[..., 0] >= 0) & (c[..., 0] < w) & (c[..., 1] >= 0) & (c[..., 1] < h)
    jt = jtypes.to(dev, torch.int64)
    jmap = torch.zeros((n, N_JTYPES, h, w), dtype=torch.float32, device=dev)
    if sigma_cells > 0:
        xx = torch.arange(w, device=dev, dtype=torch.int64)[None, None, None, :]
        yy = torch.arange(h, device=dev, dtype=torch.int64)[None, None, :, None]
        d2 = (xx - c[..., 0, None, None]) ** 2 + (yy - c[..., 1, None, None]) ** 2  # (N, P, H, W)
        g = torch.exp(-d2.to(torch.float64) / (2 * sigma_cells ** 2)).to(torch.float32)
        g = torch.where(mark[..., None, None], g, torch.zeros_like(g))
        index = jt[None, :, None, None].expand(n, npt, h, w)
        jmap = jmap.scatter_reduce(1, index, g, reduce="amax", include_self=True)
    # a later junction in the same cell wins (numpy's loop order): keep a junction only if none after it shares it
    same = (c[:, :, None, :] == c[:, None, :, :]).all(-1) & mark[:, None, :]
    later = torch.triu(torch.ones(npt, npt, dtype=torch.bool, device=dev), diagonal=1)
    keep = mark & ~(same & later).any(-1)
    # written through flat indices with one spare cell for the junctions not kept (no nonzero: nothing waits for
    # the device; the kept ones are distinct cells, so every write is determined)
    cell = torch.where(keep, c[..., 1] * w + c[..., 0], torch.full_like(c[..., 0], h * w))  # (N, P)
    flat = jmap.reshape(n, N_JTYPES * h * w)
    spare = torch.zeros((n, 1), dtype=torch.float32, device=dev)
    peak = torch.cat([flat, spare], 1)
    target = torch.where(keep, jt[None, :] * h * w + cell, N_JTYPES * h * w)
    peak.scatter_(1, target, torch.ones_like(cell, dtype=torch.float32))
    jmap = peak[:, :-1].reshape(n, N_JTYPES, h, w)
    off = (u - c.to(torch.float64)).to(torch.float32)  # (N, P, 2) x, y
    joff = torch.zeros((n, 2, h * w + 1), dtype=torch.float32, device=dev)
    joff.scatter_(2, cell[:, None, :].expand(n, 2, npt), off.transpose(1, 2))
    joff = joff[..., :-1].reshape(n, 2, h, w)
    jmask = torch.zeros((n, h * w + 1), dtype=torch.float32, device=dev)
    jmask.scatter_(1, cell, torch.ones_like(cell, dtype=torch.float32))
    jmask = jmask[:, :-1].reshape(n, h, w)
    return {"jmap": jmap, "joff": joff, "jmask": jmask}


def line_targets_batch(corners_in: torch.Tensor, valid: torch.Tensor, generator: torch.Generator, out_px: int,
                 n_segments: int = N_SEGMENTS) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """data.line_targets for a batch: segments (N, L, 2, 2) float32, labels (N, L), weights (N, L). Per sample:
    every box edge between valid corners (label 1), then non-edge pairs of valid corners in a random order up to
    L // 2 segments, then segments from a uniformly drawn valid corner to a point uniform in [0, out_px - 1]^2 up
    to 3 L // 4 (label 0), padded with weight 0. corners_in (N, 8, 2) input px; valid (N, 8) bool."""
    n = len(corners_in)
    dev = corners_in.device
    ii = torch.tensor([a for a, _ in PAIRS], device=dev)
    jj = torch.tensor([b for _, b in PAIRS], device=dev)
    is_edge = torch.tensor([p in EDGE_SET for p in PAIRS], device=dev)
    pair_ok = valid[:, ii] & valid[:, jj]  # (N, 28)
    pos, neg = pair_ok & is_edge, pair_ok & ~is_edge
    npos = pos.sum(1)
    # negatives in a random order: rank by a uniform key, invalid pairs last
    key = torch.rand((n, len(PAIRS)), generator=generator, dtype=torch.float64).to(dev)
    key = torch.where(neg, key, torch.full_like(key, 2.0))
    rank = torch.argsort(torch.argsort(key, dim=1, stable=True), dim=1)
    take_neg = neg & (rank < (n_segments // 2 - npos).clamp(min=0)[:, None])
    n_rand = torch.where(valid.any(1), ((3 * n_segments) // 4 - npos - take_neg.sum(1)).clamp(min=0), 0)
    n_rand_max = (3 * n_segments) // 4
    # random segments: the r-th valid corner (r uniform) to a uniform point
    nvalid = valid.sum(1)
    r = torch.floor(torch.rand((n, n_rand_max), generator=generator, dtype=torch.float64).to(dev)
                    * nvalid[:, None]).to(torch.int64)
    order = torch.cumsum(valid.to(torch.int64), 1) - 1  # rank of each valid corner among the valid ones
    hit = valid[:, None, :] & (order[:, None, :] == r[:, :, None])  # (N, R, 8)
    start_idx = torch.argmax(hit.to(torch.int64), dim=2)
    end = torch.rand((n, n_rand_max, 2), generator=generator, dtype=torch.float64).to(dev) * (out_px - 1)
    c64 = corners_in.to(torch.float64)
    start = torch.gather(c64, 1, start_idx[..., None].expand(n, n_rand_max, 2))
    segs = torch.cat([torch.stack([c64[:, ii], c64[:, jj]], dim=2), torch.stack([start, end], dim=2)], dim=1)
    label = torch.cat([pos, torch.zeros((n, n_rand_max), dtype=torch.bool, device=dev)], dim=1)
    # the order data.line_targets gives: edges, chosen negatives, random segments, then padding
    slot = torch.arange(len(PAIRS) + n_rand_max, device=dev)[None, :].expand(n, -1)
    rand_on = slot[:, len(PAIRS):] - len(PAIRS) < n_rand[:, None]
    order_key = torch.cat([torch.where(pos, slot[:, :len(PAIRS)],
                                       torch.where(take_neg, 1000 + rank, torch.full_like(rank, 3000))),
                           torch.where(rand_on, 2000 + slot[:, len(PAIRS):], torch.full_like(rand_on, 3000,
                                                                                             dtype=torch.int64))],
                          dim=1)
    pick = torch.argsort(order_key, dim=1, stable=True)[:, :n_segments]
    used = torch.gather(order_key, 1, pick) < 3000
    out = torch.gather(segs, 1, pick[..., None, None].expand(n, n_segments, 2, 2))
    out = torch.where(used[..., None, None], out, torch.zeros_like(out)).to(torch.float32)
    lab = (torch.gather(label, 1, pick) & used).to(torch.float32)
    return out, lab, used.to(torch.float32)


# ---------------------------------------------------------------------------------------------------------
# The batch


def batch_from_boxes(frames: torch.Tensor, corners_px: torch.Tensor, visible: torch.Tensor, in_frame: torch.Tensor,
                     frame_of_sample: torch.Tensor, box: torch.Tensor, cfg: DataConfig,
                     style: dict[str, torch.Tensor] | None, line_generator: torch.Generator) -> dict[str, torch.Tensor]:
    """The batch of the crop boxes `box` (N, 3) int64 of frames frame_of_sample (N,): the keys of make_sample
    stacked (data.py's module doc): image (N, 1, S, S), jmap (N, 4, S/s, S/s), joff (N, 2, ., .), jmask (N, ., .),
    corners_px (N, 8, 2) input px, valid (N, 8) bool, segments_px (N, L, 2, 2), line_label (N, L),
    line_weight (N, L), crop_px (N, 3) float32. style: augment_style_batch's draws, None for none. The sides must not
    exceed max_crop_side (crop_boxes' never do): the resampling's tap count is fixed by it."""
    s = cfg.input_px
    fs = frame_of_sample.to(frames.device)
    box = box.to(frames.device)
    x = crop_resize_batch(frames, fs, box, s, True, max_crop_side(tuple(frames.shape[1:]), cfg)) / 255.0
    if style is not None:
        x = augment_style_batch(x, style)
    corners = corners_px[fs].to(torch.float64)
    corners_in = to_input_px_batch(corners, box, s)
    inside = ((corners_in > -0.5) & (corners_in < s - 0.5)).all(-1)
    valid = visible[fs].bool() & in_frame[fs].bool() & inside & torch.isfinite(corners_in).all(-1)
    cells = s // cfg.stride
    jtypes = torch.as_tensor(CORNER_JTYPE, dtype=torch.int64)
    t = encode_junctions_batch(corners_in, valid, jtypes, (cells, cells), cfg.stride, cfg.sigma_cells)
    segs, lab, wt = line_targets_batch(corners_in, valid, line_generator, s)
    return {"image": ((x - IMAGE_MEAN) / IMAGE_STD)[:, None].to(torch.float32), "jmap": t["jmap"],
            "joff": t["joff"], "jmask": t["jmask"], "corners_px": torch.nan_to_num(corners_in).to(torch.float32),
            "valid": valid, "segments_px": segs, "line_label": lab, "line_weight": wt,
            "crop_px": box.to(torch.float32)}


def training_batch(frames: torch.Tensor, corners_px: torch.Tensor, visible: torch.Tensor, in_frame: torch.Tensor,
                   cfg: DataConfig, generator: torch.Generator | None,
                   frame_of_sample: torch.Tensor | None = None,
                   frame_hw: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """make_sample + collate_batch on the device: sample n a crop of frame frame_of_sample[n] (default: each frame
    once) with its own draws from `generator` (a CPU torch.Generator the caller seeds: crop jitter and the whole
    frame share, style augmentation when cfg.augment, line segments); generator None: evaluation samples (no
    jitter, no whole frames, no augmentation, line segments from a generator seeded 0), as make_sample's rng None.
    frame_hw: frames of several sizes, (B, 2) int64 each frame's own (H, W), held in the top-left of its frames
    entry with zeros beyond (what the crops' zero padding reads there); None: every frame the whole entry.
    Returns batch_from_boxes's dict, on the frames' device."""
    dev = frames.device
    fs = torch.arange(len(frames), device=dev) if frame_of_sample is None else frame_of_sample.to(dev)
    n = len(fs)
    params = None
    if generator is not None:
        params = {k: v.to(dev) for k, v in draw_crop_params(n, cfg, generator).items()}
    image_hw = tuple(frames.shape[1:]) if frame_hw is None else frame_hw.to(dev)[fs]
    box = crop_boxes(corners_px[fs], in_frame[fs].bool(), image_hw, cfg, params)
    style = None
    if generator is not None and cfg.augment:
        style = draw_style_params(n, cfg.input_px, generator)
    line_gen = generator if generator is not None else torch.Generator().manual_seed(0)
    return batch_from_boxes(frames, corners_px, visible, in_frame, fs, box, cfg, style, line_gen)
