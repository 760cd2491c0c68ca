"""The image's own silhouette edges as a cue for range: where the box's outline sits in a frame against
the outline projected at a pose, fitted as a scale and a shift, and the pose's range corrected by that scale.

Pure functions over numpy arrays (OpenCV for the bicubic samples); no I/O, no truth.

Stations. The outline of the box at a pose is the convex hull of its projected visible corners (a convex body's
silhouette is the hull of its projected corners; hidden ones fall inside). Along every hull edge at least
min_edge_px long, at stations every STEP_PX from end_px in from its ends (a corner's rounding, the array's boom;
the pipeline's defaults MIN_EDGE_PX, END_PX reach the box's short edges at 512 px, bench/silhouette_bias.py keeps
60 and 20 px at 1024 px),
the image is sampled across the edge (bicubic, 0.25 px steps, +-6 px along the outward normal) and the edge located
by the area method: with the inside plateau the mean of the samples 4-6 px in and the outside one 4-6 px out,
edge = -4 + integral from -4 to 4 of the normalized profile (px, + outward; exact for a straight step blurred by
any symmetric PSF in a linear image). A station counts where
- the box is brighter than what lies behind it by over MIN_CONTRAST grey levels (a dark face on a bright Earth,
  or a face in shadow, gives none);
- the inside is uniform: its samples 1-6 px in within FLAT_SHARE of the contrast (texture, shadow-map acne on a
  face lit at grazing incidence, a sliver of another face at the rim would bias the plateau, not the edge);
- without a segmentation mask (a user's frame), the outside is uniform too: its samples 2-6 px out within
  FLAT_SHARE of the contrast (the array, an appendage, a cloud edge on the Earth behind);
- with a mask (a render's, bench/silhouette_bias.py), the mask shows one face of the body (values 1-6) from 1 to
  6 px in and the background (0) 3 px out;
- every probe lies inside the image.

The fit. Offsets d_i at stations p_i with outward normals n_i of an image scaled by (1 + delta) about a point c
and shifted by b against the projected outline: d_i = delta ((p_i - c) . n_i) + b . n_i (first order). Solved for
(delta, b_x, b_y) by iteratively reweighted least squares with Huber's weights (k = 1.345 robust sigmas; sigma
from the median absolute residual), delta's standard error from the weighted normal matrix and the residuals'
scale. Where every station's normal is (anti)parallel to one direction u (two opposite long edges of the box, its
short ones too short), the shift along the edges is not seen and b = beta u. A frame gives no delta (None) with
fewer than MIN_STATIONS stations, stations on fewer than MIN_EDGES hull edges, or a scale not separable from the
shift (the normal matrix's condition: one edge alone, or one side of the box).

The correction. A pinhole images a target of depth extent small against its range r at a scale f / r; a range r'
= r / (1 + delta) scales the image by (1 + delta) about the target's projection to first order (the depth
extent's own perspective, a few metres at 50 m, changes the shape at second order). So delta > 0 (the image's
outline outside the projected one: the target looks bigger than the pose says) moves the target towards the camera
along the line of sight, r -> r / (1 + delta): the projected centre, and the attitude, are unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_EDGE_PX = 30.0          # shorter hull edges give too few stations and sit close to the corners
STEP_PX = 2.0               # station spacing along an edge
END_PX = 10.0               # stations kept this far from an edge's ends (the profile reaches 6 px across)
PARALLEL = 1e-2             # normals this close to one direction (smallest/largest eigenvalue of sum n n^T)
REACH_PX = 4.0              # the area integral's half-width (and the plateaus' start) for a PSF sigma up to ~1 px
MIN_CONTRAST = 20.0         # grey levels, inside plateau minus outside plateau
FLAT_SHARE = 0.1            # a plateau's samples' std within this share of the contrast
CLIPPED = 250.0             # a profile reaching this is clipped at the 8-bit ceiling
MIN_STATIONS = 30
MIN_EDGES = 2
MAX_COND = 1e4              # the normalized normal matrix's condition number
HUBER_K = 1.345


@dataclass(frozen=True)
class Stations:
    """The usable stations of one frame. offset_px (S,) the image's edge against the outline (+ outward);
    point_px (S, 2) the station on the outline; normal (S, 2) its outward unit normal; edge (S,) int the hull edge
    it belongs to; clipped (S,) bool the profile reaches CLIPPED; centre_px (2,) the hull's vertices' mean."""

    offset_px: np.ndarray
    point_px: np.ndarray
    normal: np.ndarray
    edge: np.ndarray
    clipped: np.ndarray
    centre_px: np.ndarray


@dataclass(frozen=True)
class ScaleFit:
    """The outline's scale error in one frame (or a sequence). delta: image scale over projected scale minus 1
    (None: not measurable); delta_se: its standard error; shift_px (2,) b (NaN without a fit); stations: those
    used; edges: hull edges with stations."""

    delta: float | None
    delta_se: float | None
    shift_px: np.ndarray
    stations: int
    edges: int

    def record(self) -> dict:
        """As plain JSON data (shift_px None without one)."""
        shift = [float(v) for v in self.shift_px] if np.isfinite(self.shift_px).all() else None
        return {"delta": self.delta, "delta_se": self.delta_se, "stations": self.stations, "edges": self.edges,
                "shift_px": shift}


def outline_edges(corners_px: np.ndarray, use: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The box's outline: the convex hull of the corners corners_px (8, 2) px where use (8,) bool, counter-clockwise.
    Returns (edges (E, 2, 2) px: start and end point of each hull edge, outward normals (E, 2)); none below 3
    corners or for a degenerate hull."""
    from scipy.spatial import ConvexHull, QhullError

    q = np.asarray(corners_px, dtype=float)[np.asarray(use, bool)]
    empty = np.zeros((0, 2, 2)), np.zeros((0, 2))
    if len(q) < 3:
        return empty
    try:
        v = q[ConvexHull(q).vertices]
    except QhullError:  # collinear corners: an edge-on box
        return empty
    a, b = v, np.roll(v, -1, axis=0)
    d = b - a
    n = np.stack([-d[:, 1], d[:, 0]], axis=1) / np.linalg.norm(d, axis=1)[:, None]
    n *= np.sign(np.einsum("ij,ij->i", n, (a + b) / 2 - v.mean(axis=0)))[:, None]  # outward
    return np.stack([a, b], axis=1), n


def profile_reach_px(blur_px: float | None) -> float:
    """Half-width of the area method's integral, px: REACH_PX up to a PSF sigma of ~1 px, else 3.5 sigmas of the
    blur with the pixel's own footprint (sqrt(blur^2 + 1/12)), rounded up: the plateaus must lie beyond the
    blurred edge. blur_px None: REACH_PX."""
    if blur_px is None:
        return REACH_PX
    return float(max(REACH_PX, np.ceil(3.5 * np.sqrt(blur_px**2 + 1.0 / 12.0))))


def edge_stations(image: np.ndarray, corners_px: np.ndarray, use: np.ndarray, mask: np.ndarray | None = None,
                  min_edge_px: float = MIN_EDGE_PX, end_px: float = END_PX, light=None,
                  blur_px: float | None = None) -> Stations:
    """The usable stations (module doc) of the outline of corners_px (8, 2) px, use (8,) bool, in image (H, W)
    (8-bit grey levels, any dtype); mask (H, W) the render's segmentation values, None for a user's frame;
    min_edge_px, end_px: the shortest hull edge measured and the stations' distance from its ends, px.
    light: the frames' response (envisat_pose.camera_response.Response; None or linear: the image is light): the
    edge is located on the profile in linear light (the guards read the stored values, whose noise they know);
    blur_px: the PSF's sigma, px, which sets the profile's reach (profile_reach_px; None: REACH_PX)."""
    from envisat_pose.perception.refine import sample_bicubic

    edges, normals = outline_edges(corners_px, use)
    h, w = image.shape
    centre = np.asarray(corners_px, float)[np.asarray(use, bool)].mean(axis=0) if len(edges) else np.zeros(2)
    rows = {k: [] for k in ("offset_px", "point_px", "normal", "edge", "clipped")}
    reach = profile_reach_px(blur_px)
    t_px = np.arange(-(reach + 2.0), reach + 2.0 + 1e-9, 0.25)
    win = (t_px >= -reach) & (t_px <= reach)
    end_px = max(end_px, reach + 6.0)
    lin = None if light is None or light.is_linear else light.linearize(image)
    for e, ((pa, pb), n) in enumerate(zip(edges, normals)):
        length = float(np.linalg.norm(pb - pa))
        if length < min_edge_px:
            continue
        d = (pb - pa) / length
        base = pa[None] + np.arange(end_px, length - end_px, STEP_PX)[:, None] * d
        if not len(base):  # shorter than its two ends' margins (the reach grows them with the blur)
            continue
        pts = base[:, None] + t_px[None, :, None] * n
        prof = sample_bicubic(image, pts).astype(np.float64)
        inside, outside = prof[:, t_px <= -reach].mean(axis=1), prof[:, t_px >= reach].mean(axis=1)
        contrast = inside - outside
        ok = (contrast > MIN_CONTRAST) & (prof[:, (t_px >= -(reach + 2.0)) & (t_px <= -reach / 4.0)].std(axis=1)
                                          < FLAT_SHARE * np.abs(contrast))
        probe = {o: np.round(base + o * n).astype(int) for o in (-(reach + 2.0), -5.0, -3.0, -1.0, 3.0, reach + 2.0)}
        for p in probe.values():
            ok &= (p[:, 0] >= 0) & (p[:, 0] < w) & (p[:, 1] >= 0) & (p[:, 1] < h)
        if mask is None:
            ok &= prof[:, (t_px >= reach / 2.0) & (t_px <= reach + 2.0)].std(axis=1) < FLAT_SHARE * np.abs(contrast)
        else:
            cls = {o: np.where(ok, mask[np.clip(p[:, 1], 0, h - 1), np.clip(p[:, 0], 0, w - 1)], -1)
                   for o, p in probe.items()}
            ok &= (cls[3.0] == 0) & (cls[-1.0] >= 1) & (cls[-1.0] <= 6)
            for o in (-3.0, -5.0, -(reach + 2.0)):
                ok &= cls[o] == cls[-1.0]
        i = np.flatnonzero(ok)
        lin_prof = prof[i] if lin is None or not len(i) else sample_bicubic(lin, pts[i]).astype(np.float64)
        rows["offset_px"].append(area_edge_px(lin_prof, t_px, reach))
        rows["point_px"].append(base[i])
        rows["normal"].append(np.broadcast_to(n, (len(i), 2)))
        rows["edge"].append(np.full(len(i), e))
        rows["clipped"].append(prof[i][:, win].max(axis=1) >= CLIPPED)
    shapes = {"offset_px": (0,), "point_px": (0, 2), "normal": (0, 2), "edge": (0,), "clipped": (0,)}
    cat = {k: np.concatenate(v) if v else np.zeros(shapes[k]) for k, v in rows.items()}
    return Stations(cat["offset_px"], cat["point_px"], cat["normal"], cat["edge"].astype(int),
                    cat["clipped"].astype(bool), centre)


def area_edge_px(prof: np.ndarray, t_px: np.ndarray, reach: float) -> np.ndarray:
    """The area method on profiles prof (S, len(t_px)) sampled at t_px (+ outward, the body inside): with the
    plateaus the means beyond +-reach, edge = -reach + integral over [-reach, reach] of the normalized profile,
    px (exact for a straight step blurred by a symmetric PSF in linear light). (S,)."""
    inside, outside = prof[:, t_px <= -reach].mean(axis=1), prof[:, t_px >= reach].mean(axis=1)
    win = (t_px >= -reach) & (t_px <= reach)
    norm = (prof[:, win] - outside[:, None]) / (inside - outside)[:, None]
    return -reach + np.trapezoid(norm, t_px[win], axis=1)


def fit_scale(st: Stations, min_stations: int = MIN_STATIONS, min_edges: int = MIN_EDGES) -> ScaleFit:
    """Fit d_i = delta ((p_i - c) . n_i) + b . n_i to the stations (module doc: Huber IRLS). ScaleFit with delta
    None where the frame cannot tell the scale (too few stations or edges, scale and shift not separable)."""
    S, n_edges = len(st.offset_px), len(np.unique(st.edge))
    none = ScaleFit(None, None, np.full(2, np.nan), int(S), int(n_edges))
    if S < min_stations or n_edges < min_edges:
        return none
    s = np.einsum("ij,ij->i", st.point_px - st.centre_px, st.normal)
    lam, vec = np.linalg.eigh(st.normal.T @ st.normal)
    basis = vec[:, 1:] if lam[0] < PARALLEL * lam[1] else np.eye(2)  # b = basis @ beta: along u alone if parallel
    A = np.column_stack([s, st.normal @ basis])            # (S, 1 + m): delta, beta
    scale = np.r_[np.sqrt(np.mean(s * s)), np.ones(basis.shape[1])]  # columns of like size for the condition test
    An = A / scale
    if np.linalg.cond(An.T @ An) > MAX_COND:
        return none
    y = st.offset_px
    wts = np.ones(S)
    for _ in range(20):
        theta = np.linalg.lstsq(An * np.sqrt(wts)[:, None], y * np.sqrt(wts), rcond=None)[0]
        r = y - An @ theta
        sigma = max(1.4826 * np.median(np.abs(r - np.median(r))), 1e-6)
        new = np.minimum(1.0, HUBER_K * sigma / np.maximum(np.abs(r), 1e-12))  # Huber's weights
        if np.allclose(new, wts, atol=1e-6):
            break
        wts = new
    # covariance: (A^T W A)^-1 sigma_w^2, sigma_w^2 the weighted residuals' variance on S - (1 + m) degrees of freedom
    s2 = float(np.sum(wts * r * r) / max(S - A.shape[1], 1))
    cov = np.linalg.inv((An * wts[:, None]).T @ An) * s2
    theta = theta / scale
    return ScaleFit(float(theta[0]), float(np.sqrt(cov[0, 0]) / scale[0]), basis @ theta[1:], int(S),
                    int(n_edges))


def frame_scale(image: np.ndarray, corners_px: np.ndarray, use: np.ndarray, mask: np.ndarray | None = None,
                light=None, blur_px: float | None = None) -> ScaleFit:
    """One frame's outline scale error against corners_px (8, 2) px, use (8,) bool: edge_stations (in linear
    light by `light`, the reach set by blur_px) then fit_scale."""
    return fit_scale(edge_stations(image, corners_px, use, mask, light=light, blur_px=blur_px))


def sequence_scale(fits: list[ScaleFit], min_frames: int = 5) -> ScaleFit:
    """One scale error for a sequence (a bias its frames share) from the frames' fits: a Huber location estimate
    (IRLS, k = HUBER_K) over the measured frames' deltas weighted by 1 / delta_se^2, the standardized residuals'
    scale from their median absolute deviation (at least 1: the frames scatter at least as their errors say); its
    standard error that weighted mean's, times that scale. delta None with fewer than min_frames measured frames.
    stations, edges: sums over the frames used."""
    ok = [f for f in fits if f.delta is not None and f.delta_se and np.isfinite(f.delta_se)]
    stations, edges = sum(f.stations for f in ok), sum(f.edges for f in ok)
    if len(ok) < min_frames:
        return ScaleFit(None, None, np.full(2, np.nan), int(stations), int(edges))
    d, se = np.array([f.delta for f in ok]), np.array([f.delta_se for f in ok])
    mean, hub = float(np.median(d)), np.ones(len(d))
    for _ in range(50):
        z = (d - mean) / se
        scale = max(1.0, 1.4826 * float(np.median(np.abs(z - np.median(z)))))
        hub = np.minimum(1.0, HUBER_K * scale / np.maximum(np.abs(z), 1e-12))
        w = hub / se**2
        new = float(np.sum(w * d) / np.sum(w))
        if abs(new - mean) < 1e-9:
            break
        mean = new
    return ScaleFit(mean, float(scale / np.sqrt(np.sum(1.0 / se**2))), np.full(2, np.nan), int(stations), int(edges))


def correct_range(x: np.ndarray, pos_C_m: np.ndarray, delta: np.ndarray | float) -> np.ndarray:
    """The state x (..., 12) with the target's position moved along the line of sight from the camera centre
    pos_C_m (3,) (C, m) so that its range r becomes r / (1 + delta) (module doc); velocity, attitude and rate
    unchanged (a label needs the pose only). delta (...,) or scalar; NaN leaves that state as it was."""
    x = np.array(x, dtype=float, copy=True)
    delta = np.asarray(delta, dtype=float)
    factor = np.where(np.isfinite(delta), 1.0 / (1.0 + np.nan_to_num(delta)), 1.0)
    x[..., :3] = pos_C_m + (x[..., :3] - pos_C_m) * np.asarray(factor)[..., None]
    return x
