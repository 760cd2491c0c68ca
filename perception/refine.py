"""Sub-pixel refinement of named corners from the full-resolution pixels. Plain numpy + OpenCV.

A named corner of the box is where its visible edges meet. For each edge of the wireframe (geometry.EDGES) from
the corner to a visible neighbour, the fitted pose's projection gives its direction; along it, at stations s
px from the corner, the image is sampled across the edge (bicubic, at half-pixel steps), the derivative of the
profile taken, and the edge located as the centroid of the derivative's magnitude over a window re-centred on it
until it settles (for a straight step edge blurred by a symmetric PSF that centroid is the edge, whatever its
contrast sign or level). The offsets across, as a function of s, are fitted by weighted least squares with a
line; its intercept at s = 0 and its slope give the edge's line through the corner with the intercept's
variance (residual scatter x the fit's design). The corner is the weighted least-squares intersection of its
edges' lines: x minimizing sum_i (n_i . x - c_i)^2 / var_i, with covariance (sum_i n_i n_i^T / var_i)^-1
(px^2). Edges nearly parallel in the image (< min_angle_deg apart) give no corner; a refined corner farther than
max_shift_px from the network's keeps the network's.

Coordinates: full-image pixels, OpenCV convention (pixel centres at integers).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class RefineConfig:
    """half_width_px: half width of the profile across an edge; clearance_px: the stations start where every
    other edge of the corner is farther than half_width_px + clearance_px from this one (the blur's reach);
    start_px: first station from the corner at the least; length_px: farthest station (and at most edge_frac of
    the edge); step_px: station spacing; min_stations: fewer fitted stations drop the edge; min_angle_deg: two
    edges closer in direction than this do not make a corner; max_shift_px: refined corners farther than this
    from the network's are not used; iterations: re-centring of the profile window (each of the two steps);
    min_contrast: a station whose contrast across the edge is below this many times the pixel noise (the
    plateaus' spread) has no edge; fuse: the detector combines the refined corner with the network's by their
    covariances (information-weighted) instead of replacing it."""

    half_width_px: float = 3.0
    clearance_px: float = 2.0
    start_px: float = 4.0
    length_px: float = 24.0
    edge_frac: float = 0.45
    step_px: float = 1.0
    min_stations: int = 5
    min_angle_deg: float = 20.0
    max_shift_px: float = 2.5
    iterations: int = 3
    min_contrast: float = 6.0
    fuse: bool = True


REMAP_COLS = 4096


def sample_bicubic(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Image values at points xy (..., 2) px, bicubic (OpenCV remap; border replicated): (...,) float32. Only the
    patch around the points (plus the kernel's reach) is converted, not the whole frame."""
    shape = xy.shape[:-1]
    flat = xy.reshape(-1, 2).astype(np.float64)
    h, w = image.shape
    x0 = int(np.clip(np.floor(flat[:, 0].min()) - 3, 0, w - 1))
    y0 = int(np.clip(np.floor(flat[:, 1].min()) - 3, 0, h - 1))
    x1 = int(np.clip(np.ceil(flat[:, 0].max()) + 4, x0 + 1, w))
    y1 = int(np.clip(np.ceil(flat[:, 1].max()) + 4, y0 + 1, h))
    patch = np.ascontiguousarray(image[y0:y1, x0:x1], dtype=np.float32)
    n = len(flat)
    cols = min(max(n, 1), REMAP_COLS)  # remap's maps: rows of REMAP_COLS (it takes fewer than 32767 a side)
    pad = -n % cols
    mx = np.pad(flat[:, 0] - x0, (0, pad)).astype(np.float32).reshape(-1, cols)
    my = np.pad(flat[:, 1] - y0, (0, pad)).astype(np.float32).reshape(-1, cols)
    out = cv2.remap(patch, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    return out.ravel()[:n].reshape(shape)


def edge_offsets(image: np.ndarray, corner: np.ndarray, direction: np.ndarray, stations: np.ndarray,
                 cfg: RefineConfig) -> tuple[np.ndarray, np.ndarray]:
    """Offsets across the edge (along the left normal of `direction`), px, of the edge at each station s (S,)
    px from `corner` along the unit `direction`, and each station's weight (its contrast, grey levels; 0 where
    no edge stands out of the noise): (S,), (S,).

    The edge is first found as the centroid of the profile derivative's magnitude, then located by the area
    method: with plateaus A and B the means of the profile from h to 2h either side of the current centre c,
    the edge of a monotone profile is t_e = (c + h) - integral_{c-h}^{c+h} (I - A) / (B - A) dt, exact for a
    step blurred by a symmetric PSF and linear in I, so zero-mean noise, whatever its level either side (shot
    noise is larger on the bright side), adds no bias (the derivative's magnitude would be pulled toward the
    noisier side)."""
    normal = np.array([-direction[1], direction[0]])
    h = cfg.half_width_px
    dt = 0.5
    t = np.arange(-3.0 * h, 3.0 * h + 1e-9, dt)  # the window (+- h) and its plateaus (h to 2h) move within it
    pts = corner[None, None] + stations[:, None, None] * direction + t[None, :, None] * normal  # (S, T, 2)
    prof = sample_bicubic(image, pts).astype(np.float64)  # (S, T)
    deriv = np.abs(np.gradient(prof, dt, axis=1))
    centre = np.zeros(len(stations))
    for _ in range(cfg.iterations):  # locate: centroid of the derivative's magnitude above the window's floor
        win = np.abs(t[None] - centre[:, None]) <= h
        d = np.where(win, deriv, 0.0)
        d = np.maximum(d - np.where(win, deriv, np.inf).min(axis=1, keepdims=True), 0.0)
        mass = d.sum(axis=1)
        centre = np.where(mass > 0, (d * t[None]).sum(axis=1) / np.maximum(mass, 1e-12), 0.0)
        centre = np.clip(centre, -h, h)
    idx = np.arange(len(stations))
    contrast = np.zeros(len(stations))
    for _ in range(cfg.iterations):  # refine: the area method
        rel = t[None] - centre[:, None]
        lo = (rel >= -2.0 * h) & (rel <= -h)
        hi = (rel >= h) & (rel <= 2.0 * h)
        a = np.sum(np.where(lo, prof, 0.0), axis=1) / np.maximum(lo.sum(axis=1), 1)
        b = np.sum(np.where(hi, prof, 0.0), axis=1) / np.maximum(hi.sum(axis=1), 1)
        contrast = b - a
        norm = (prof - a[:, None]) / np.where(np.abs(contrast) > 1e-9, contrast, 1e-9)[:, None]
        # the window's samples t1..t2 (|t - c| <= h), integrated by the trapezoid rule
        win = np.abs(rel) <= h
        first = np.argmax(win, axis=1)
        last = win.shape[1] - 1 - np.argmax(win[:, ::-1], axis=1)
        wts = win.astype(np.float64)
        wts[idx, first] = 0.5
        wts[idx, last] = 0.5
        area = np.sum(wts * norm, axis=1) * dt
        centre = np.clip(t[last] - area, -h, h)
    # the noise: the spread of the plateaus' samples about their means, pooled over the stations
    rel = t[None] - centre[:, None]
    lo = (rel >= -2.0 * h) & (rel <= -h)
    hi = (rel >= h) & (rel <= 2.0 * h)
    resid = [(prof - np.sum(np.where(m, prof, 0.0), 1, keepdims=True) / np.maximum(m.sum(1, keepdims=True), 1))[m]
             for m in (lo, hi)]
    resid = np.concatenate(resid)
    noise = float(np.median(np.abs(resid))) / 0.6745 + 1e-9 if len(resid) else 1e-9  # MAD -> sigma
    strength = np.abs(contrast)
    return centre, np.where(strength >= cfg.min_contrast * noise, strength, 0.0)


def fit_edge(stations: np.ndarray, offsets: np.ndarray, weights: np.ndarray) -> tuple[float, float, float] | None:
    """Weighted least-squares line offset = a + b s: (a, b, var(a)) px, px/px, px^2; None when too few stations
    carry weight or the fit is degenerate."""
    ok = weights > 0
    if ok.sum() < 3:
        return None
    s, y, w = stations[ok], offsets[ok], weights[ok] / weights[ok].max()
    X = np.stack([np.ones_like(s), s], axis=1)
    XtW = X.T * w
    A = XtW @ X
    if np.linalg.cond(A) > 1e12:
        return None
    cov_unit = np.linalg.inv(A)
    a, b = cov_unit @ (XtW @ y)
    r = y - (a + b * s)
    dof = max(len(s) - 2, 1)
    sigma2 = float(np.sum(w * r * r) / dof)
    return float(a), float(b), float(sigma2 * cov_unit[0, 0])


def intersect(points: np.ndarray, normals: np.ndarray, var: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares intersection of lines n_i . x = n_i . p_i (points (L, 2), unit normals (L, 2),
    offset variances (L,) px^2): x (2,) and its covariance (2, 2) px^2."""
    w = 1.0 / np.maximum(var, 1e-8)
    info = np.einsum("l,li,lj->ij", w, normals, normals)
    rhs = np.einsum("l,li,l->i", w, normals, np.sum(normals * points, axis=1))
    cov = np.linalg.inv(info)
    return cov @ rhs, cov


def refine_corner(image: np.ndarray, corner: np.ndarray, directions: np.ndarray, lengths: np.ndarray,
                  cfg: RefineConfig = RefineConfig()) -> tuple[np.ndarray, np.ndarray] | None:
    """One corner (2,) px refined from its edges' unit directions (E, 2) and lengths (E,) px: (corner (2,),
    covariance (2, 2) px^2), or None when fewer than two usable edges at least min_angle_deg apart meet."""
    lines = []
    directions = np.asarray(directions, float)
    for k, (d, length) in enumerate(zip(directions, lengths)):
        # the stations start where the other edges are clear of this one's profile window
        others = np.delete(directions, k, axis=0)
        sin_min = float(np.min(np.abs(others[:, 0] * d[1] - others[:, 1] * d[0]))) if len(others) else 1.0
        start = max(cfg.start_px, (2.0 * cfg.half_width_px + cfg.clearance_px) / max(sin_min, 1e-3))
        far = min(cfg.length_px, cfg.edge_frac * float(length))
        s = np.arange(start, far + 1e-9, cfg.step_px)
        if len(s) < cfg.min_stations:
            continue
        off, wgt = edge_offsets(image, corner, d, s, cfg)
        fit = fit_edge(s, off, wgt)
        if fit is None or not np.isfinite(fit[2]):
            continue
        a, b, var_a = fit
        normal = np.array([-d[1], d[0]])
        # the fitted line: corner + s d + (a + b s) n; its unit normal n' = (n - b d) / sqrt(1 + b^2)
        n_fit = (normal - b * d) / np.hypot(1.0, b)
        d_fit = np.array([n_fit[1], -n_fit[0]])
        lines.append((corner + a * normal, n_fit, d_fit, var_a / (1.0 + b * b)))
    if len(lines) < 2:
        return None
    dirs = np.array([ln[2] for ln in lines])
    cosang = np.abs(dirs @ dirs.T)
    np.fill_diagonal(cosang, 0.0)
    if cosang.min() > np.cos(np.radians(cfg.min_angle_deg)) and len(lines) == 2:
        return None
    keep = [i for i in range(len(lines)) if (cosang[i] < np.cos(np.radians(cfg.min_angle_deg))).any()]
    if len(keep) < 2:
        return None
    pts = np.array([lines[i][0] for i in keep])
    nrm = np.array([lines[i][1] for i in keep])
    var = np.array([lines[i][3] for i in keep])
    x, cov = intersect(pts, nrm, var)
    if not np.all(np.isfinite(x)) or np.linalg.norm(x - corner) > cfg.max_shift_px:
        return None
    return x, cov


def refine_named(image: np.ndarray, corners_px: np.ndarray, projected_px: np.ndarray, visible: np.ndarray,
                 edges, cfg: RefineConfig = RefineConfig()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Refine the named corners (8, 2) px (NaN: not found) of a box fit: each found corner's edges are the
    wireframe's `edges` (pairs of corner indices) to corners the fit shows (visible (8,) bool), in the
    directions of the fit's projection projected_px (8, 2). Returns (corners (8, 2), covariances (8, 2, 2) px^2
    NaN where not refined, refined (8,) bool); corners not refined keep their position."""
    out = np.array(corners_px, dtype=np.float64)
    cov = np.full((8, 2, 2), np.nan)
    done = np.zeros(8, bool)
    img = np.asarray(image)
    for k in range(8):
        if not (np.all(np.isfinite(out[k])) and visible[k]):
            continue
        nbr = [b if a == k else a for a, b in edges if k in (a, b)]
        nbr = [j for j in nbr if visible[j] and np.all(np.isfinite(projected_px[j]))]
        if len(nbr) < 2:
            continue
        vec = projected_px[nbr] - projected_px[k]
        lengths = np.linalg.norm(vec, axis=1)
        if np.any(lengths < 1e-6):
            continue
        r = refine_corner(img, out[k], vec / lengths[:, None], lengths, cfg)
        if r is not None:
            out[k], cov[k], done[k] = r[0], r[1], True
    return out, cov, done
