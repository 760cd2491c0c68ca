"""Training samples streamed from the factory's shards, cropped around the target and style-augmented.

Reads shards through the core's one reader (envisat_pose/shard_reader.py; design.md, Shard): `<key>.png` 8-bit gray, `<key>.json` the label, of which
this module needs corners_px (8, 2), visible (8,), in_frame (8,) and K (3, 3); other keys (scene, mask values,
corruption) may come and go and are ignored. A training sample's draws come from the Generator its caller seeds
(perception/stream.py: seed, epoch, shard, index), so its crop and augmentation do not depend on workers or ranks.

A sample (numpy, what the DataLoader collates), for an input of S px and heatmaps of S / 4 cells:
    image:       (1, S, S) float32, (gray / 255 - 0.5) / 0.25
    jmap, joff, jmask: junction targets (perception/heatmaps.py)
    corners_px:  (8, 2) float32 A-H in input pixels; valid: (8,) bool, visible, in the frame and in the crop
    segments_px: (L, 2, 2) float32 candidate segments for line verification; line_label: (L,) float32 1 for a
                 box edge between two valid corners, 0 otherwise; line_weight: (L,) float32, 0 for padding
    crop_px:     (3,) float32 (x0, y0, side) of the crop in the full image: full = (input + 0.5) side / S - 0.5 + x0
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from envisat_pose.config import Config, InputError, check
from envisat_pose.geometry import EDGES
from envisat_pose.perception.heatmaps import CORNER_JTYPE, encode_junctions
from envisat_pose.shard_reader import (
    checked_shards,  # the one check of a dataset's shards (core)
    read_shards,
)

N_SEGMENTS = 32
MAX_IMAGE_PX = 4096  # the largest image side the jobs take (generate's resolution_px)
# shuffle_buffer: each reader (a DataLoader worker) holds that many decoded samples, each at least its float32
# input image (4 x input_px^2 bytes; its heatmap targets add ~45 %); past 16 GiB of images per reader no machine
# holds a run's readers (2^63 - 1: the whole epoch decoded before the first batch, a MemoryError hours in)
MAX_BUFFER_BYTES = 2**34
IMAGE_MEAN, IMAGE_STD = 0.5, 0.25


@dataclass(frozen=True)
class DataConfig(Config):
    """input_px: network input side; crop_margin: the crop's side over the corners' extent; crop_scale_jitter,
    crop_shift_jitter: relative jitter of side and centre (training); augment: style augmentation on;
    sigma_cells: heatmap Gaussian; shuffle_buffer: samples shuffled in memory; whole_frame_prob: share of
    training samples showing the whole frame (what the detector's coarse pass sees) instead of the target crop."""

    input_px: int = 320
    stride: int = 4
    crop_margin: float = 1.4
    crop_scale_jitter: float = 0.15
    crop_shift_jitter: float = 0.1
    augment: bool = True
    sigma_cells: float = 1.0
    shuffle_buffer: int = 64
    whole_frame_prob: float = 0.2

    def validate(self, prefix: str = "") -> None:
        """ConfigError naming a field no training can mean (validated when built)."""
        p = f"{prefix}." if prefix else ""
        cells = self.input_px / max(1, self.stride)
        # the crop's side is margin x the corners' extent: under 1 it cuts the corners it frames; at 1e300 its
        # integer box overflowed (a traceback at the first sample); a side of MAX_IMAGE_PX per px of extent is
        # larger than every frame the jobs make
        check(1.0 <= self.crop_margin <= MAX_IMAGE_PX, f"{p}crop_margin", self.crop_margin,
              f"a factor in [1, {MAX_IMAGE_PX}] on the corners' extent")
        # the side is scaled by exp(u x jitter), u in [-1, 1]: a jitter beyond ln(MAX_IMAGE_PX) = 8.3 takes it past
        # every frame or under a pixel (1e300: an inf side, a traceback); below 0 it is the same draw
        check(0.0 <= self.crop_scale_jitter <= math.log(MAX_IMAGE_PX), f"{p}crop_scale_jitter",
              self.crop_scale_jitter, f"a jitter in [0, {math.log(MAX_IMAGE_PX):.2f}] (ln {MAX_IMAGE_PX})")
        # the centre moves by u x jitter x side: beyond 1 the crop can miss the corners entirely (at 1e300 every
        # crop did: a loss of 0.002, nothing learnt)
        check(0.0 <= self.crop_shift_jitter <= 1.0, f"{p}crop_shift_jitter", self.crop_shift_jitter,
              "a share of the crop's side in [0, 1]")
        # 0: a single 1 at the corner's cell (by design); a Gaussian wider than the map marks every cell a corner
        # (1e300: an overflow at the first sample); below 0 it is the same as 0
        check(0.0 <= self.sigma_cells <= cells, f"{p}sigma_cells", self.sigma_cells,
              f"a heatmap sigma in [0, {cells:g}] cells (the map's side; 0: one cell)")
        most = max(1, MAX_BUFFER_BYTES // (4 * max(1, self.input_px) ** 2))
        check(0 <= self.shuffle_buffer <= most, f"{p}shuffle_buffer", self.shuffle_buffer,
              f"0 (no shuffle) to {most} samples (each reader holds them decoded: at most 16 GiB of float32 "
              f"{self.input_px} px images)")
        check(0.0 <= self.whole_frame_prob <= 1.0, f"{p}whole_frame_prob", self.whole_frame_prob,
              "a probability in [0, 1]")

    def to_dict(self) -> dict:
        return asdict(self)


def warn_shuffle_buffer(cfg: DataConfig, samples: int | None) -> None:
    """A warning where a shuffle_buffer given (not the default, which a small dataset leaves unfilled unasked) is
    more than the `samples` the training data holds (None: unknown, no warning): each reader then holds all of its
    samples and shuffles them whole, the same order a buffer of the data's size gives (the buffer never fills);
    the config keeps the value given (a resumed run compares it)."""
    if samples is not None and cfg.shuffle_buffer > samples and cfg.shuffle_buffer != DataConfig.shuffle_buffer:
        warnings.warn(f"data.shuffle_buffer = {cfg.shuffle_buffer}: more than the {samples} samples of the training "
                      f"data; each reader shuffles all of its samples, as a buffer of {samples} would", stacklevel=3)


def shard_paths(data_dir: str, field: str = "--data") -> list[str]:
    """The dataset's shard files to read, each checked against its manifest (the core's checked_shards: size, then
    sha256; a folder without a manifest: every *.tar). InputError naming the field when there are none or one is
    damaged; readers that may go on without damaged shards call checked_shards(data_dir, skip_damaged)."""
    return checked_shards(data_dir, False, field)[0]


def decode_image(data: bytes, where: str) -> np.ndarray:
    """An 8-bit single-channel image from PNG bytes; InputError (naming the member) for anything else."""
    if not isinstance(data, (bytes, bytearray)) or len(data) == 0:
        raise InputError(f"{where}: empty image member")
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"{where}: not an image (cannot be decoded as PNG)")
    if image.ndim != 2:
        raise InputError(f"{where}: a {image.shape[2]}-channel image; expected 8-bit grayscale")
    if image.dtype != np.uint8:
        raise InputError(f"{where}: a {image.dtype.itemsize * 8}-bit image; expected 8-bit grayscale")
    return image


def decode_label(data: bytes, where: str) -> dict:
    """The fields of a label this module uses, as arrays, checked (the pose R_cam_from_target, t_cam_from_target_m
    where the label has it); other keys are ignored."""
    try:
        label = json.loads(data)
        out = {"corners_px": np.asarray(label["corners_px"], dtype=np.float64),
               "visible": np.asarray(label["visible"], dtype=bool),
               "in_frame": np.asarray(label["in_frame"], dtype=bool),
               "K": np.asarray(label["K"], dtype=np.float64),
               # 'clean': the stored image is the clean render; the factory's corruption is not applied here
               "image_stored": str(label.get("image_stored", "corrupted")),
               "corruption": label.get("corruption") if isinstance(label.get("corruption"), dict) else {}}
        if "R_cam_from_target" in label and "t_cam_from_target_m" in label:  # the pose (the face cue's fit)
            out["R_cam_from_target"] = np.asarray(label["R_cam_from_target"], dtype=np.float64)
            out["t_cam_from_target_m"] = np.asarray(label["t_cam_from_target_m"], dtype=np.float64)
    except (ValueError, KeyError, TypeError) as err:
        raise InputError(f"{where}: not a corner label ({type(err).__name__}: {err})") from None
    shapes = {"corners_px": (8, 2), "visible": (8,), "in_frame": (8,), "K": (3, 3), "R_cam_from_target": (3, 3),
              "t_cam_from_target_m": (3,)}
    for name, shape in shapes.items():
        if name in out and out[name].shape != shape:
            raise InputError(f"{where}: label '{name}' has shape {out[name].shape}, expected {shape}")
    return out


def read_samples(paths: list[str]):
    """(key, image (H, W) uint8, label) for every sample of the shards, in order (envisat_pose/shard_reader.py)."""

    for where, key, sample in read_shards(paths):
        if "png" not in sample:
            members = sorted(sample)
            raise InputError(f"{where}: sample has no '.png' image member (members: {', '.join(members)})")
        if "json" not in sample:
            raise InputError(f"{where}: sample has no '.json' label member")
        yield key, decode_image(sample["png"], f"{where}.png"), decode_label(sample["json"], f"{where}.json")


def crop_box(corners_px: np.ndarray, usable: np.ndarray, image_hw: tuple[int, int], cfg: DataConfig,
             rng: np.random.Generator | None) -> np.ndarray:
    """(x0, y0, side) integer square crop around the usable corners (all in-frame corners; the image centre if
    none), side = margin x their extent (at least 32 px), jittered when rng is given."""
    h, w = image_hw
    pts = corners_px[usable & np.all(np.isfinite(corners_px), axis=1)]
    if len(pts) == 0:
        centre, extent = np.array([w / 2, h / 2]), float(min(h, w))
    else:
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        centre, extent = (lo + hi) / 2, float(max(np.max(hi - lo), 16.0))
    side = extent * cfg.crop_margin
    if rng is not None:
        side *= float(np.exp(rng.uniform(-1, 1) * cfg.crop_scale_jitter))
        centre = centre + rng.uniform(-1, 1, size=2) * cfg.crop_shift_jitter * side
    side = int(np.ceil(max(side, 32.0)))
    x0, y0 = (np.round(centre - side / 2)).astype(int)
    return np.array([x0, y0, side], dtype=np.int64)


def crop_resize(image: np.ndarray, box: np.ndarray, out_px: int) -> np.ndarray:
    """The square crop box (x0, y0, side) of the image (zeros outside it), resized to out_px (area averaging)."""
    x0, y0, side = (int(v) for v in box)
    h, w = image.shape
    xa, ya, xb, yb = max(x0, 0), max(y0, 0), min(x0 + side, w), min(y0 + side, h)
    if (xa, ya, xb, yb) == (x0, y0, x0 + side, y0 + side):
        canvas = image[y0:y0 + side, x0:x0 + side]  # inside the image: no copy
    else:
        canvas = np.zeros((side, side), dtype=image.dtype)
        if xb > xa and yb > ya:
            canvas[ya - y0:yb - y0, xa - x0:xb - x0] = image[ya:yb, xa:xb]
    interp = cv2.INTER_AREA if side >= out_px else cv2.INTER_LINEAR
    return cv2.resize(canvas, (out_px, out_px), interpolation=interp)


def to_input_px(points_px: np.ndarray, box: np.ndarray, out_px: int) -> np.ndarray:
    """Full-image pixels -> input pixels of the crop (pixel centres at integers in both). (..., 2)."""
    s = out_px / float(box[2])
    return (points_px - box[:2] + 0.5) * s - 0.5


def to_full_px(points_px: np.ndarray, box: np.ndarray, out_px: int) -> np.ndarray:
    """Input pixels of the crop -> full-image pixels, the inverse of to_input_px. (..., 2)."""
    s = float(box[2]) / out_px
    return (points_px + 0.5) * s - 0.5 + box[:2]


def augment_style(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Photometric augmentation of a uint8 image -> float32 in [0, 1]: brightness, contrast, gamma, blur, noise,
    glare, random erasing, each drawn from rng (a detector must not learn one renderer's shading)."""
    x = image.astype(np.float32) / 255.0
    h, w = x.shape
    if rng.random() < 0.8:
        x = x * rng.uniform(0.5, 1.6) + rng.uniform(-0.08, 0.08)  # gain and offset
    if rng.random() < 0.5:
        m = float(x.mean())
        x = (x - m) * rng.uniform(0.6, 1.4) + m  # contrast
    x = np.clip(x, 0.0, 1.0)
    if rng.random() < 0.5:
        x = x ** rng.uniform(0.6, 1.6)  # gamma
    if rng.random() < 0.4:
        x = cv2.GaussianBlur(x, (0, 0), rng.uniform(0.3, 1.8))
    if rng.random() < 0.3:  # glare: a bright blob, maybe a streak
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        sx, sy = rng.uniform(0.03, 0.3) * w, rng.uniform(0.03, 0.3) * h
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        x = x + rng.uniform(0.2, 0.9) * np.exp(-((xx - cx) ** 2 / (2 * sx ** 2) + (yy - cy) ** 2 / (2 * sy ** 2)))
    if rng.random() < 0.3:  # random erasing
        eh, ew = int(rng.uniform(0.05, 0.3) * h), int(rng.uniform(0.05, 0.3) * w)
        ey, ex = int(rng.integers(0, h - eh + 1)), int(rng.integers(0, w - ew + 1))
        x[ey:ey + eh, ex:ex + ew] = rng.uniform(0, 1)
    if rng.random() < 0.7:  # sensor noise: signal-dependent plus read noise
        sigma = rng.uniform(0.0, 0.06)
        x = x + rng.normal(size=x.shape).astype(np.float32) * np.sqrt(sigma ** 2 * np.clip(x, 0, 1) + (sigma / 3) ** 2)
    return np.clip(x, 0.0, 1.0).astype(np.float32)


def line_targets(corners_in: np.ndarray, valid: np.ndarray, rng: np.random.Generator, out_px: int,
                 n: int = N_SEGMENTS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Segments (n, 2, 2), labels (n,), weights (n,): every box edge between valid corners (1), non-edge pairs of
    valid corners (0), and segments from a valid corner to a random point (0), padded with weight 0."""
    edges = {tuple(sorted(e)) for e in EDGES}
    idx = np.flatnonzero(valid)
    pos, neg = [], []
    for i in range(len(idx)):
        for j in range(i + 1, len(idx)):
            a, b = int(idx[i]), int(idx[j])
            (pos if (a, b) in edges else neg).append((corners_in[a], corners_in[b]))
    rng.shuffle(neg)
    segs = pos + neg[: max(0, n // 2 - len(pos))]
    while len(idx) and len(segs) < (3 * n) // 4:
        a = corners_in[int(rng.choice(idx))]
        segs.append((a, rng.uniform(0, out_px - 1, size=2)))
    labels = [1.0] * len(pos) + [0.0] * (len(segs) - len(pos))
    segs, labels = segs[:n], labels[:n]
    out = np.zeros((n, 2, 2), np.float32)
    lab = np.zeros(n, np.float32)
    wt = np.zeros(n, np.float32)
    if segs:
        out[: len(segs)] = np.array(segs, dtype=np.float32)
        lab[: len(segs)] = labels
        wt[: len(segs)] = 1.0
    return out, lab, wt


def make_sample(image: np.ndarray, label: dict, cfg: DataConfig, rng: np.random.Generator | None) -> dict:
    """One training (rng given: jittered crop and augmentation) or evaluation (rng None) sample: see the module
    doc. The crop comes from the label (training and evaluation against labels only)."""
    usable = label["in_frame"]
    if rng is not None and rng.random() < cfg.whole_frame_prob:
        box = np.array([0, 0, max(image.shape)], dtype=np.int64)
    else:
        box = crop_box(label["corners_px"], usable, image.shape, cfg, rng)
    crop = crop_resize(image, box, cfg.input_px)
    x = augment_style(crop, rng) if (rng is not None and cfg.augment) else crop.astype(np.float32) / 255.0
    corners_in = to_input_px(label["corners_px"], box, cfg.input_px)
    inside = np.all((corners_in > -0.5) & (corners_in < cfg.input_px - 0.5), axis=1)
    valid = label["visible"] & label["in_frame"] & inside & np.all(np.isfinite(corners_in), axis=1)
    cells = cfg.input_px // cfg.stride
    t = encode_junctions(corners_in, valid, CORNER_JTYPE, (cells, cells), cfg.stride, cfg.sigma_cells)
    segs, lab, wt = line_targets(corners_in, valid, rng if rng is not None else np.random.default_rng(0),
                                 cfg.input_px)
    return {"image": ((x - IMAGE_MEAN) / IMAGE_STD)[None].astype(np.float32), "jmap": t["jmap"],
            "joff": t["joff"], "jmask": t["jmask"], "corners_px": np.nan_to_num(corners_in).astype(np.float32),
            "valid": valid, "segments_px": segs, "line_label": lab, "line_weight": wt,
            "crop_px": box.astype(np.float32)}
