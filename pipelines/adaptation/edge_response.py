"""The camera's response and blur read from its own frames: the profiles across the target's silhouette edges.

Pure functions over numpy arrays (OpenCV for the bicubic samples); no I/O, no truth.

A straight edge blurred by a symmetric PSF is, in linear light, antisymmetric about its midpoint: normalized
between its plateaus (q = 1 inside, 0 outside) and located by the area method at e, q(e - s) + q(e + s) = 1 for
every s. Stored through a response (envisat_pose/camera_response.py) after the blur it is not: the sRGB curve or
a gamma lifts the dark half of a bright body's edge on a dark sky. So for a candidate power g on GAMMA_GRID the
frames are linearized (stored^g), each usable station's profile normalized, its edge taken from a straight line
fitted to its hull edge's stations' area edges (smooth_edges), the profiles shifted onto one axis u and averaged
(the mean, not the median: noise is light's), and the asymmetry of that mean m measured as
sum_s (m(s) + m(-s) - 1)^2 (its plain sum is 0 at the area edge for any profile). The power at the smallest
asymmetry (a parabola through the grid's lowest three) is the frames' gamma; its standard error the groups'
(frames, or interleaved blocks of stations in fewer than MIN_GROUP_FRAMES frames) own minima's spread. The
response chosen (choose_response): 'linear' where the power is within NAMED_Z standard errors of 1, 'srgb' where its
asymmetry is no larger than the power's, else the power. An encoding mostly shifts an edge and only a little
bends it, so the power is held only where the blur is wide enough to show the bend: +-0.02-0.1 at 1-2.5 px
over 12 frames of 300 stations (tests/pipelines/adaptation/test_edge_response.py); below SHARP_PX no power is
reported and the named curve (linear or sRGB) of the smaller asymmetry is chosen, its ambiguity left to the caller
(adapt reads the edge cue under both and carries the difference as the scale's response term).

The blur: the linearized profiles by that response, shifted onto one axis and averaged,
fitted by the blurred step q(u) = Phi(-u / s) (least squares over s); the PSF's sigma is sqrt(s^2 - 1/12), the
pixel's own footprint (a unit box, variance 1/12 across any edge direction) taken out. Its standard error from
the groups' own fits.

Stations are those of the edge cue (pipelines/adaptation/edge_range.py: the outline of the visible corners, stations every
STEP_PX, the same guards on the stored values) with a wide profile (PROFILE_REACH_PX, so a blur up to ~2.5 px
sigma reaches its plateaus).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from envisat_pose.camera_response import GAMMA_RANGE, LINEAR, SRGB, Response
from envisat_pose.pipelines.adaptation.edge_range import FLAT_SHARE, MIN_CONTRAST, STEP_PX, area_edge_px, outline_edges

PROFILE_REACH_PX = 9.0          # the area integral's half-width here: plateaus beyond 3.5 sigmas of a 2.5 px blur
GAMMA_GRID = np.round(np.arange(0.6, 3.61, 0.1), 2)
SIGMA_GRID_PX = np.arange(0.20, 4.0, 0.01)   # blurred-step widths s tried
U_PX = np.arange(-(PROFILE_REACH_PX - 1.0), PROFILE_REACH_PX - 1.0 + 1e-9, 0.25)  # the aligned profiles' axis
MIN_RESPONSE_STATIONS = 40
GROUPS_IN_ONE_FRAME = 8         # interleaved blocks of stations when fewer than MIN_GROUP_FRAMES frames
MIN_GROUP_FRAMES = 5
LEVELS = (0.25, 0.5, 0.75)      # the profile's level crossings whose mean is compared with the area edge
SHARP_PX = 0.5                  # below this PSF sigma an encoding hardly bends an edge: no power is measured
SRGB_NOMINAL_GAMMA = 2.2        # the single power the sRGB curve is usually quoted as
NAMED_Z = 2.0                   # a named curve within this many standard errors of the fitted power is chosen


@dataclass(frozen=True)
class ResponseFit:
    """The frames' response and blur. response: the one to linearize with (LINEAR without a measurement);
    gamma, gamma_se: the fitted power (stored = light^(1/gamma)) and its standard error (None: not measured);
    psf_sigma_px, psf_sigma_se_px: the Gaussian PSF's sigma and its standard error, px (None: not measured);
    stations, groups: what the fit used; asymmetry: the stations' mean asymmetry A at power 1 and at gamma."""

    response: Response = LINEAR
    gamma: float | None = None
    gamma_se: float | None = None
    psf_sigma_px: float | None = None
    psf_sigma_se_px: float | None = None
    stations: int = 0
    groups: int = 0
    asymmetry: dict = field(default_factory=dict)

    def record(self) -> dict:
        """As plain JSON data."""
        return {"response": self.response.name(), "gamma": self.gamma, "gamma_se": self.gamma_se,
                "psf_sigma_px": self.psf_sigma_px, "psf_sigma_se_px": self.psf_sigma_se_px,
                "stations": self.stations, "groups": self.groups, "asymmetry": self.asymmetry}


def profile_samples(image: np.ndarray, corners_px: np.ndarray, use: np.ndarray, min_edge_px: float = 30.0
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The sample points (S, P, 2) px of the usable stations' profiles across the outline of corners_px (8, 2),
    use (8,) bool, in image (H, W) (stored 8-bit values): +-(PROFILE_REACH_PX + 2) px along the outward normal
    at 0.25 px, stations every STEP_PX from 2 PROFILE_REACH_PX + 6 px in from each hull edge's ends; kept where the
    body is brighter than the background by MIN_CONTRAST and both plateaus are flat (edge_range's guards). Also each
    station's position along its hull edge, px, offset by 1e4 x the edge's index (S,): stations of one edge share
    a line (smooth_edges)."""
    from envisat_pose.perception.refine import sample_bicubic

    reach, t = PROFILE_REACH_PX, profile_t_px()
    edges, normals = outline_edges(corners_px, use)
    h, w = image.shape
    out, along = [], []
    for j, ((pa, pb), n) in enumerate(zip(edges, normals)):
        length = float(np.linalg.norm(pb - pa))
        end = 2.0 * reach + 6.0  # clear of the corners: a neighbouring edge's blur would bend the plateau
        if length < max(min_edge_px, 2 * end + STEP_PX):
            continue
        a = np.arange(end, length - end, STEP_PX)
        base = pa[None] + a[:, None] * ((pb - pa) / length)
        pts = base[:, None] + t[None, :, None] * n
        ok = (pts[:, [0, -1], 0].min(axis=1) >= 0) & (pts[:, [0, -1], 0].max(axis=1) <= w - 1) \
            & (pts[:, [0, -1], 1].min(axis=1) >= 0) & (pts[:, [0, -1], 1].max(axis=1) <= h - 1)
        prof = sample_bicubic(image, pts).astype(np.float64)
        inside, outside = prof[:, t <= -reach].mean(axis=1), prof[:, t >= reach].mean(axis=1)
        contrast = inside - outside
        ok &= contrast > MIN_CONTRAST
        ok &= prof[:, t <= -reach].std(axis=1) < FLAT_SHARE * np.abs(contrast)
        ok &= prof[:, t >= reach].std(axis=1) < FLAT_SHARE * np.abs(contrast)
        out.append(pts[ok])
        along.append(a[ok] + 1e4 * j)
    if not out:
        return np.zeros((0, len(t), 2)), np.zeros(0)
    return np.concatenate(out), np.concatenate(along)


def smooth_edges(e: np.ndarray, along: np.ndarray) -> np.ndarray:
    """The stations' edges e (S,) replaced by a straight line along each hull edge (a least-squares fit of e
    against the position `along`, profile_samples'): the line's noise is far below a station's, and it does not
    follow the station's own noise (an edge located from the same samples it aligns would bias their mean)."""
    out = np.array(e, dtype=float)
    for j in np.unique(np.floor(along / 1e4)):
        m = np.floor(along / 1e4) == j
        if m.sum() >= 3:
            A = np.column_stack([np.ones(m.sum()), along[m] - along[m].mean()])
            out[m] = A @ np.linalg.lstsq(A, e[m], rcond=None)[0]
    return out


def profile_t_px() -> np.ndarray:
    """The profile's sample positions across the edge, px (+ outward)."""
    return np.arange(-(PROFILE_REACH_PX + 2.0), PROFILE_REACH_PX + 2.0 + 1e-9, 0.25)


def normalized(prof: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Profiles (S, P) normalized between their plateaus (1 inside, 0 outside) and their edges by the area method
    (S,) px."""
    inside, outside = prof[:, t <= -PROFILE_REACH_PX].mean(axis=1), prof[:, t >= PROFILE_REACH_PX].mean(axis=1)
    return (prof - outside[:, None]) / (inside - outside)[:, None], area_edge_px(prof, t, PROFILE_REACH_PX)


def aligned_mean(q: np.ndarray, e: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The mean of normalized profiles q (S, P) shifted by their edges e (S,) onto U_PX (u = t - e). The mean,
    not the median: a pixel's noise is light's, so only the mean of the linearized values keeps the blur's
    symmetry where the response bends the noise (and clips it at 0)."""
    return np.mean(np.stack([np.interp(e[i] + U_PX, t, q[i]) for i in range(len(q))]), axis=0)


def asymmetry(m: np.ndarray) -> float:
    """How far a profile m on U_PX is from antisymmetric about u = 0: the sum over s of (m(s) + m(-s) - 1)^2 (0
    for a symmetric PSF in linear light; the mean of m(s) + m(-s) - 1 is 0 for any profile at its area edge, so
    the squares, not the mean, tell an encoding)."""
    return float(np.sum((m + m[::-1] - 1.0) ** 2))


def linear_profiles(frames: list[tuple[np.ndarray, np.ndarray]], response: Response) -> np.ndarray:
    """The stations' profiles (S, P) in linear light by `response`: frames [(image, samples (S_f, P, 2))]."""
    from envisat_pose.perception.refine import sample_bicubic

    rows = [sample_bicubic(response.linearize(im), pts).astype(np.float64) for im, pts in frames if len(pts)]
    return np.concatenate(rows) if rows else np.zeros((0, len(profile_t_px())))


def station_groups(frames: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """The group of each station for standard errors: its frame, or with fewer than MIN_GROUP_FRAMES frames with
    stations an interleaved block (station index mod GROUPS_IN_ONE_FRAME). (S,) int."""
    sizes = [len(pts) for _, pts in frames if len(pts)]
    if len(sizes) >= MIN_GROUP_FRAMES:
        return np.repeat(np.arange(len(sizes)), sizes)
    return np.arange(sum(sizes)) % GROUPS_IN_ONE_FRAME


def grid_minimum(cost: np.ndarray) -> float:
    """The power at the minimum of cost over GAMMA_GRID, refined by a parabola through the lowest point and its
    neighbours (the grid's end where it lies there)."""
    i = int(np.argmin(cost))
    if i == 0 or i == len(cost) - 1:
        return float(GAMMA_GRID[i])
    c0, c1, c2 = cost[i - 1], cost[i], cost[i + 1]
    den = c0 - 2.0 * c1 + c2
    step = 0.5 * (c0 - c2) / den if den > 0 else 0.0
    return float(GAMMA_GRID[i] + np.clip(step, -1.0, 1.0) * (GAMMA_GRID[i + 1] - GAMMA_GRID[i]))


def fit_gamma(frames: list[tuple[np.ndarray, np.ndarray]], groups: np.ndarray, along: np.ndarray
              ) -> tuple[float, float, dict]:
    """The power whose linearization makes the stations' mean profile most antisymmetric (module doc), its
    standard error (the groups' own minima's spread over sqrt(groups)), and the asymmetry (pooled, and the
    groups' mean excess over the fitted power's with its standard error) at power 1 and under the sRGB curve."""
    t, ids = profile_t_px(), np.unique(groups)

    def costs(response: Response) -> tuple[float, np.ndarray]:
        q, e = normalized(linear_profiles(frames, response), t)
        e = smooth_edges(e, along)
        return asymmetry(aligned_mean(q, e, t)), np.array([asymmetry(aligned_mean(q[groups == k], e[groups == k],
                                                                                  t)) for k in ids])

    pooled, per = np.zeros(len(GAMMA_GRID)), np.zeros((len(ids), len(GAMMA_GRID)))
    for j, g in enumerate(GAMMA_GRID):
        pooled[j], per[:, j] = costs(LINEAR if g == 1.0 else Response("gamma", float(g)))
    gamma = grid_minimum(pooled)
    mins = np.array([grid_minimum(c) for c in per])
    se = float(np.std(mins, ddof=1) / np.sqrt(len(mins))) if len(mins) > 1 else float("inf")
    near = int(np.argmin(np.abs(GAMMA_GRID - gamma)))
    named = {"linear": (pooled[int(np.flatnonzero(GAMMA_GRID == 1.0)[0])],
                        per[:, int(np.flatnonzero(GAMMA_GRID == 1.0)[0])]), "srgb": costs(SRGB)}
    record = {"at_gamma": costs(Response("gamma", float(np.clip(gamma, *GAMMA_RANGE))))[0]}
    for name, (c, c_per) in named.items():
        d = c_per - per[:, near]
        record[name] = {"pooled": float(c), "excess": float(np.mean(d)),
                        "excess_se": float(np.std(d, ddof=1) / np.sqrt(len(d))) if len(d) > 1 else float("inf")}
    return gamma, se, record


def choose_response(gamma: float, gamma_se: float, record: dict) -> Response:
    """The response to linearize with: 'linear' where the fitted power is within NAMED_Z of its standard errors of
    1 (the data cannot tell them apart; the groups' own asymmetries are too noisy on real frames to compare
    curves by); else 'srgb' where the power is within NAMED_Z standard errors of its nominal 2.2 (on the
    project's renders a power fitted to sRGB frames lands anywhere in 1.8-2.8, and linearizing them by it
    instead of the curve moved the cue by up to 0.6 %: bench/edge_truth.py --responses), or where its pooled
    asymmetry is no larger than the fitted power's (a curve that bends in the darks as no power does; the sRGB frames' best
    power drifts with their levels); else the fitted power. A power at the grid's end is no measurement: then the
    named curve of the smaller asymmetry."""
    if abs(gamma - 1.0) <= NAMED_Z * gamma_se:
        return LINEAR
    if not GAMMA_GRID[0] < gamma < GAMMA_GRID[-1]:  # no minimum inside the grid: the power is not measured
        return SRGB if record["srgb"]["pooled"] < record["linear"]["pooled"] else LINEAR
    if abs(gamma - SRGB_NOMINAL_GAMMA) <= NAMED_Z * gamma_se or record["srgb"]["pooled"] <= record["at_gamma"]:
        return SRGB
    return Response("gamma", round(float(np.clip(gamma, *GAMMA_RANGE)), 4))


def fit_blur(q: np.ndarray, e: np.ndarray, t: np.ndarray) -> float | None:
    """The PSF's sigma (px) from normalized linear profiles q (S, P) with edges e (S,): their aligned mean
    fitted by Phi(-u / s) over SIGMA_GRID_PX, the pixel's footprint (1/12) taken out; None without profiles."""
    from scipy.special import ndtr

    if not len(q):
        return None
    med = aligned_mean(q, e, t)
    cost = [np.sum((ndtr(-U_PX / s) - med) ** 2) for s in SIGMA_GRID_PX]
    s = float(SIGMA_GRID_PX[int(np.argmin(cost))])
    return float(np.sqrt(max(s * s - 1.0 / 12.0, 0.0)))


def estimate_response(images: list[np.ndarray], corners_px: np.ndarray, use: np.ndarray) -> ResponseFit:
    """The response and blur of frames `images` (N of (H, W) stored 8-bit) from the outlines of corners_px
    (N, 8, 2) px, use (N, 8) bool (module doc). A ResponseFit with nothing measured (LINEAR) below
    MIN_RESPONSE_STATIONS stations."""
    samples = [profile_samples(im, c, u) for im, c, u in zip(images, corners_px, use)]
    frames = [(im, pts) for im, (pts, _) in zip(images, samples)]
    along = np.concatenate([a + 1e6 * f for f, (_, a) in enumerate(samples)]) if samples else np.zeros(0)
    groups = station_groups(frames)
    n, n_groups = len(groups), int(len(np.unique(groups)))
    if n < MIN_RESPONSE_STATIONS:
        return ResponseFit(stations=n, groups=n_groups)
    gamma, gamma_se, asym = fit_gamma(frames, groups, along)
    response = choose_response(gamma, gamma_se, asym)
    t = profile_t_px()
    q, e = normalized(linear_profiles(frames, response), t)
    e = smooth_edges(e, along)
    sigma = fit_blur(q, e, t)
    if sigma is not None and sigma < SHARP_PX:  # the power is not measured: the named curve of less asymmetry
        response = SRGB if asym["srgb"]["pooled"] < asym["linear"]["pooled"] else LINEAR
        gamma, gamma_se = None, None
    per = np.array([fit_blur(q[groups == g], e[groups == g], t) for g in np.unique(groups)])
    sigma_se = float(np.std(per, ddof=1) / np.sqrt(len(per))) if len(per) > 1 else None
    return ResponseFit(response, gamma, gamma_se, sigma, sigma_se, n, n_groups, asym)
