"""Steps 2-3 of `envisat adapt` (pipelines/adaptation/adapt.py): the labels of a track run. Its trusted frames
(pseudo_labels.trusted_frames over the smoothed segments, the smoother built from the tracker's own model:
smoother_model) before the held-out part whose label is tight, their range corrected by the frames' own
silhouette edges (edge_corrected; pipelines/adaptation/edge_range.py) read in linear light under the frames'
camera response (response curve and blur; frames_response: the camera file's, else estimated,
pipelines/adaptation/edge_response.py), and the response term of the edges' scale (response_record: the sequence's
delta under the responses the estimate leaves open)."""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from envisat_pose.camera_response import GAMMA_RANGE, LINEAR, SRGB, Response
from envisat_pose.filtering.dynamics import load_inertia_T_kg_m2
from envisat_pose.io import open_npz
from envisat_pose.pipelines.adaptation.edge_range import correct_range, frame_scale, sequence_scale
from envisat_pose.pipelines.adaptation.edge_response import estimate_response
from envisat_pose.pipelines.adaptation.pseudo_labels import corner_labels, label_sigma_px, smooth_track
from envisat_pose.pipelines.runs.track import TrackConfig
from envisat_pose.pipelines.tracking.build import tracker_filter
from envisat_pose.pipelines.tracking.onboard import chaser_function

RESPONSE_FRAMES = 30    # labelled frames the response and blur are estimated from (evenly spread)
# How far an estimated power is from the rendered frames' own: RMS 0.62 over 17 camera responses of the project's
# renders (the grid at 512 px with a power measured, and three adapt runs: sRGB read 1.25, gamma 2.4 read 1.49,
# linear 1.15); the edges are read again at the estimate +- this (or its own standard error, if larger).
GAMMA_EST_SD = 0.6
EDGE_RANGE_MODES = ("sequence", "frame", "off")  # how the labels' range is corrected (edge_corrected)


def smoother_model(tcfg: TrackConfig) -> tuple[tuple, dict]:
    """The filter's model as the tracker builds it (pipelines/tracking/tracker.Tracker), for the smoother: q_sigma, each
    component the larger of the filter's and the detector's (tracker.noise.detector_q_sigma), and the dynamics
    (J_T, mu_m3_s2, gravity_gradient, max_step_s). Nothing of the detector is needed."""

    fcfg = tracker_filter(dataclasses.asdict(tcfg.filter))
    q = tuple(max(a, b) for a, b in zip(fcfg.q_sigma, tcfg.tracker.noise.detector_q_sigma))
    return q, {"J_T": load_inertia_T_kg_m2(), "mu_m3_s2": float(tcfg.orbit.mu_m3_s2),
               "gravity_gradient": tcfg.gravity_gradient, "max_step_s": fcfg.max_rk4_step_s}


def track_run_labels(run_dir: str, camera, orbit, q_sigma, dyn: dict, cut: int, cfg) -> dict:
    """The labels of a track run: the smoothed segments (pseudo_labels.smooth_track) of the frames before `cut`
    alone (a segment running on into the held-out part is smoothed up to the cut: no held-out frame's detection
    moves a label), the trusted frames whose largest corner sigma is below cfg.max_label_sigma_px, at most
    cfg.max_labels of them evenly spread (cfg: the AdaptConfig). Returns {frames (N,) int, x (N, 12) their
    smoothed states, sigma_px (N,) the largest corner sigma, trusted: all trusted frames before cut};
    label_record(x[i], camera) labels frame i."""

    with open_npz(os.path.join(run_dir, "est.npz")) as est, open_npz(os.path.join(run_dir, "det.npz")) as det:
        t_s, x_hat, P, status = est["t_s"][:cut], est["x_hat"][0, :cut], est["P"][0, :cut], est["status"][0, :cut]
        n_hyp = det["n_hypotheses"][:cut]
    chaser_at = chaser_function(orbit)
    chaser = np.array([chaser_at(t) for t in t_s])
    sm = smooth_track(t_s, x_hat, P, status, chaser, q_sigma, n_hyp, **dyn)
    trusted = np.flatnonzero(sm.trusted)
    sigma = label_sigma_px(sm.x[trusted], sm.P[trusted], camera).max(axis=1) if len(trusted) else np.zeros(0)
    keep = trusted[sigma < cfg.max_label_sigma_px]
    sigma = sigma[sigma < cfg.max_label_sigma_px]
    if len(keep) > cfg.max_labels:
        pick = np.unique(np.linspace(0, len(keep) - 1, cfg.max_labels).round().astype(int))
        keep, sigma = keep[pick], sigma[pick]
    return {"frames": keep, "x": sm.x[keep], "sigma_px": sigma, "trusted": int(len(trusted))}


def edge_corrected(x: np.ndarray, images: list[np.ndarray], camera, mode: str, min_frames: int, light=None,
                   blur_px: float | None = None) -> tuple[np.ndarray, dict]:
    """The labels' states x (N, 12) with their range corrected by the frames' silhouette edges (images: the N
    frames as the tracker saw them; pipelines/adaptation/edge_range.py): mode 'sequence' divides every range by (1 + delta)
    of the sequence (edge_range.sequence_scale over the frames' fits; none below min_frames measured frames),
    'frame' each by its own frame's (a frame without one keeps its range), 'off' leaves x (the edges are
    measured and recorded all the same). Returns (x corrected,
    record: mode, per-frame delta / delta_se / stations (None where not measured) and range_m (before the
    correction), the sequence's fit, the frames measured, the outline's median radius (px, the RMS distance of
    the used corners from their centroid) and the factor applied per frame (1: none)). light, blur_px: the
    frames' response and PSF sigma (px) the edges are located with (edge_range.edge_stations; None: as stored,
    the default reach)."""

    lab = corner_labels(x, camera)
    use = lab["visible"] & lab["in_frame"]
    fits = [frame_scale(im, lab["corners_px"][i], use[i], light=light, blur_px=blur_px) for i, im in enumerate(images)]
    radius = [float(np.sqrt(np.mean(np.sum((c[u] - c[u].mean(axis=0)) ** 2, axis=1))))
              for c, u in zip(lab["corners_px"], use) if u.sum() >= 3]
    seq = sequence_scale(fits, min_frames)
    if mode == "sequence":
        delta = np.full(len(x), np.nan if seq.delta is None else seq.delta)
    elif mode == "frame":
        delta = np.array([np.nan if f.delta is None else f.delta for f in fits])
    else:  # 'off': measured and recorded, not applied
        delta = np.full(len(x), np.nan)
    record = {"mode": mode, "sequence": seq.record(), "frames_measured": int(sum(f.delta is not None for f in fits)),
              "outline_radius_px": float(np.median(radius)) if radius else None,
              "range_m": [float(v) for v in np.linalg.norm(x[:, :3] - camera.pos_C_m, axis=1)],
              "delta": [f.delta for f in fits], "delta_se": [f.delta_se for f in fits],
              "stations": [f.stations for f in fits],
              "range_factor": [float(v) for v in np.where(np.isfinite(delta), 1.0 / (1.0 + np.nan_to_num(delta)),
                                                          1.0)]}
    return correct_range(x, camera.pos_C_m, delta), record


def frames_response(x: np.ndarray, images: list[np.ndarray], camera, given: tuple) -> dict:
    """The frames' camera response, its response curve and blur: given (the camera file's (response,
    psf_sigma_px), each None where not given) or estimated from RESPONSE_FRAMES of the labelled frames, evenly
    spread (pipelines/adaptation/edge_response.py, along the outline of each label's visible corners). Returns
    {response (Response), psf_sigma_px, estimate (the estimate's record), given: which came from the file,
    alternatives: the responses the edges are read under too, what the estimate leaves open (its power
    GAMMA_EST_SD either side, or for a response without a measured power the other named curve; none when the
    response was given)}."""

    response, psf = given
    pick = calibration_frames(len(images), RESPONSE_FRAMES)
    lab = corner_labels(x[pick], camera)
    fit = estimate_response([images[i] for i in pick], lab["corners_px"], lab["visible"] & lab["in_frame"])
    alternatives = []
    if response is None:
        response = fit.response
        if fit.gamma is None:
            alternatives = [LINEAR if response == SRGB else SRGB]
        else:
            s = max(fit.gamma_se or 0.0, GAMMA_EST_SD)
            alternatives = [Response("gamma", float(np.clip(g, *GAMMA_RANGE))) for g in (fit.gamma - s, fit.gamma + s)]
    return {"response": response, "psf_sigma_px": fit.psf_sigma_px if psf is None else psf,
            "estimate": fit.record(), "given": {"response": given[0] is not None, "psf_sigma_px": given[1] is not None},
            "alternatives": alternatives}


def response_record(resp: dict, x: np.ndarray, images: list[np.ndarray], camera, edges: dict, min_frames: int
                    ) -> dict:
    """The camera response the edges were read with (frames_response) as JSON data, and the sequence's delta under
    each of its alternative responses: delta_sd, the largest difference from the delta applied (0 without
    alternatives or a fit), is how much the cue depends on what the frames leave open of their response
    (adapted_scale's response term)."""
    delta, alt = edges["sequence"]["delta"], []
    if delta is not None:
        for r in resp["alternatives"]:
            _, rec = edge_corrected(x, images, camera, "off", min_frames, r, resp["psf_sigma_px"])
            alt.append(rec["sequence"]["delta"])
    spread = [abs(a - delta) for a in alt if a is not None]
    if len(spread) < len(alt):  # an alternative reading measures nothing: the cue is not held
        spread.append(float("inf"))
    return {"response": resp["response"].name(), "psf_sigma_px": resp["psf_sigma_px"], "given": resp["given"],
            "estimate": resp["estimate"], "alternatives": [r.name() for r in resp["alternatives"]],
            "alternative_deltas": alt, "delta_sd": max(spread, default=0.0)}


def calibration_frames(n: int, most: int) -> np.ndarray:
    """Indices of at most `most` of n labelled frames, evenly spread."""
    return np.unique(np.linspace(0, n - 1, min(n, most)).round().astype(int))


def read_frames(source, remap, keep: np.ndarray) -> dict[int, np.ndarray]:
    """The frames `keep` of the source as the tracker saw them (remapped to its pinhole): {k: (H, W) uint8}."""
    import cv2

    want, out = set(int(k) for k in keep), {}
    for k, image in source.frames():
        if k in want:
            out[k] = image if remap is None else cv2.remap(image, remap[0], remap[1], cv2.INTER_LINEAR)
    return out
