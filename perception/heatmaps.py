"""Junction targets (L-CNN's jmap/joff) from corner pixels, and decoding back to sub-pixel positions.

Coordinates: input pixels in the OpenCV convention (pixel centres at integer coordinates). A heatmap of stride s
has cell (i, j) centred on input pixel ((j + 0.5) s - 0.5, (i + 0.5) s - 0.5); in heatmap units
u = (x + 0.5) / s - 0.5, so cell centres sit at integer u. A junction lives in the cell round(u) with the
sub-cell offset u - round(u) in [-0.5, 0.5]: decoding x = (j + off + 0.5) s - 0.5 is exact.

Junction types (L-CNN's J = 4): which end and which side, 2 end + side: end 0 for the +x end face (A-D), 1 for
the array's -x end (E-H); side 0 for z > 0 (A, B, E, F), 1 for z < 0 (C, D, G, H). The box looks the same after a
half-turn about any of its axes: the end breaks the turns that swap the ends (the array is there to see); the
side breaks the half-turn about the long axis only where the image shows what tells +z from -z (the ASAR
antenna and instruments under -z); elsewhere a network can only split its score between the two sides, and the
naming (perception/naming.py) reports both namings.

Targets (numpy, float32), for a heatmap of H x W cells:
    jmap:  (J, H, W) junction heatmap, 1 at the junction's cell, a Gaussian of `sigma_cells` around it (CenterNet
           style: the focal loss treats only the 1s as positives and down-weights negatives near them)
    joff:  (2, H, W) sub-cell offset (x, y) in [-0.5, 0.5] at junction cells, 0 elsewhere
    jmask: (H, W) 1 at junction cells (where the offset and the uncertainty are trained)
"""

from __future__ import annotations

import numpy as np

N_JTYPES = 4
# the junction type of corners A-H: 2 end + side (module doc)
CORNER_JTYPE = np.array([0, 0, 1, 1, 2, 2, 3, 3])
# the end alone (0: +x, A-D; 1: -x, E-H), for cues that know only the end
CORNER_END = CORNER_JTYPE // 2


def to_cells(points_px: np.ndarray, stride: int) -> np.ndarray:
    """Input pixels -> heatmap units (cell centres at integers). (..., 2) -> (..., 2)."""
    return (np.asarray(points_px, dtype=np.float64) + 0.5) / stride - 0.5


def to_pixels(points_cells: np.ndarray, stride: int) -> np.ndarray:
    """Heatmap units -> input pixels, the inverse of to_cells. (..., 2) -> (..., 2)."""
    return (np.asarray(points_cells, dtype=np.float64) + 0.5) * stride - 0.5


def encode_junctions(points_px: np.ndarray, valid: np.ndarray, jtypes: np.ndarray, shape_hw: tuple[int, int],
                     stride: int, sigma_cells: float = 1.0) -> dict[str, np.ndarray]:
    """Targets for junctions at input pixels points_px (N, 2); valid (N,) bool picks the ones to mark
    (visible and inside the input); jtypes (N,) int in [0, N_JTYPES). shape_hw: the heatmap's (H, W).

    Returns jmap (J, H, W), joff (2, H, W), jmask (H, W) (float32, see the module doc) and cell (N, 2) int
    (row, col) of each junction, -1 where not marked.
    """
    h, w = shape_hw
    jmap = np.zeros((N_JTYPES, h, w), np.float32)
    joff = np.zeros((2, h, w), np.float32)
    jmask = np.zeros((h, w), np.float32)
    cells = np.full((len(points_px), 2), -1, np.int64)
    u = to_cells(points_px, stride)
    yy, xx = np.mgrid[0:h, 0:w]
    for n in range(len(points_px)):
        if not valid[n] or not np.all(np.isfinite(u[n])):
            continue
        c = np.round(u[n]).astype(np.int64)  # (col, row)
        if not (0 <= c[0] < w and 0 <= c[1] < h):
            continue
        t = int(jtypes[n])
        if sigma_cells > 0:
            g = np.exp(-((xx - c[0]) ** 2 + (yy - c[1]) ** 2) / (2 * sigma_cells ** 2)).astype(np.float32)
            jmap[t] = np.maximum(jmap[t], g)
        jmap[t, c[1], c[0]] = 1.0
        joff[:, c[1], c[0]] = (u[n] - c).astype(np.float32)
        jmask[c[1], c[0]] = 1.0
        cells[n] = (c[1], c[0])
    return {"jmap": jmap, "joff": joff, "jmask": jmask, "cell": cells}


def decode_junctions(jmap: np.ndarray, joff: np.ndarray, stride: int, top_k: int = 16, threshold: float = 0.1,
                     nms_radius: int = 1) -> dict[str, np.ndarray]:
    """Junctions from a heatmap (J, H, W) of scores in [0, 1] and offsets (2, H, W): local maxima over a
    (2 r + 1)^2 window (any type), the top_k of those scoring at least `threshold`.

    Returns points_px (K, 2) input pixels, score (K,), jtype (K,) int, cell (K, 2) int (row, col), best first.
    """
    jmap = np.asarray(jmap, dtype=np.float32)
    best = jmap.max(axis=0)
    jtype = jmap.argmax(axis=0)
    h, w = best.shape
    r = nms_radius
    padded = np.pad(best, r, mode="constant", constant_values=-np.inf)
    # the (2 r + 1)^2 window's maximum, separably: over the rows' shifts, then the columns'
    rows_max = padded[:, 0:w].copy()
    for dx in range(1, 2 * r + 1):
        np.maximum(rows_max, padded[:, dx:dx + w], out=rows_max)
    window = rows_max[0:h].copy()
    for dy in range(1, 2 * r + 1):
        np.maximum(window, rows_max[dy:dy + h], out=window)
    peak = (best >= window) & (best >= threshold)
    rows, cols = np.nonzero(peak)
    order = np.argsort(-best[rows, cols], kind="stable")[:top_k]
    rows, cols = rows[order], cols[order]
    u = np.stack([cols + joff[0, rows, cols], rows + joff[1, rows, cols]], axis=-1)
    return {"points_px": to_pixels(u, stride), "score": best[rows, cols].astype(np.float64),
            "jtype": jtype[rows, cols].astype(np.int64), "cell": np.stack([rows, cols], axis=-1)}
