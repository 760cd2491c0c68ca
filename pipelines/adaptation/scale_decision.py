"""Step 5's scale decision of `envisat adapt` (pipelines/adaptation/adapt.py): the detector's apparent scale on
these frames that the adapted weights' error model takes (its bias_scale, which the tracker undoes in every frame:
`tracker.noise.correct_scale`), with its sd (the fit's, the outline's own offset, the camera response's), or the
original scale kept with one line saying why: the detector's own corners read that scale beyond AGREE_Z sd of the
edges' (`disagreement`), or it lies within MOVE_Z of its sd of the one the track undid (`no_evidence`).

Only labels whose range the frames' edges corrected teach a scale: uncorrected ones carry the track's own, so
measuring against them gives back the scale the tracker assumed. For the unchanged network (params 'none') the
scale is the track's own over (1 + delta), every measured station of the sequence behind it; for a fine-tuned
one its corners' scale against the corrected labels. The truth never enters here."""

from __future__ import annotations

import dataclasses

import numpy as np

from envisat_pose.perception.errormodel import ErrorModel
from envisat_pose.pipelines.runs.track import TrackConfig

# How far a rendered outline's edge may sit from the true one, px: on MuJoCo Filament frames at the true pose the
# area method reads the lit faces' edges up to 0.12 px inward, the more the brighter the face (a darker rim pixel),
# and a sequence's scale error -0.02 to -0.16 % at 512 px (0.01-0.13 px over an outline radius of ~80 px), 0.00 to
# -0.10 % at 1024 px (bench/edge_truth.py, default scenario, seeds 0-3): the scale the edges give is not known
# better than this over the outline's radius.
EDGE_OFFSET_PX = 0.08
# The edge cue's scale bias at the true pose over the grid of camera responses, each read in linear light by its
# known response and blur (bench/edge_truth.py --responses, own renders of default seed 0 at 512 px): RMS 0.045 %
# over the 12 measurable responses with a PSF sigma of 0.3 or 1 px, 0.23 % over the 6 at 2.5 px. Carried in the
# adapted scale's sd beside the outline's own offset (edge_response_sd).
EDGE_RESPONSE_SD = 4.5e-4
EDGE_RESPONSE_SD_WIDE = 2.3e-3
WIDE_PSF_PX = 1.75      # a PSF sigma above this takes EDGE_RESPONSE_SD_WIDE
AGREE_Z = 3.0           # edges and corners disagree beyond this many standard deviations of their difference
MOVE_Z = 2.0            # a scale is moved only by more than this many of its standard deviations


def edge_response_sd(psf_sigma_px: float | None) -> float:
    """The edge cue's dependence on the camera response at the true pose (EDGE_RESPONSE_SD; EDGE_RESPONSE_SD_WIDE
    above WIDE_PSF_PX)."""
    return EDGE_RESPONSE_SD_WIDE if psf_sigma_px is not None and psf_sigma_px > WIDE_PSF_PX else EDGE_RESPONSE_SD


def adapted_scale(params: str, applied: float, edges: dict, cal: dict) -> dict | None:
    """The apparent scale the adapted weights' error model holds, or None. params 'none' (the network that made
    the track, unchanged) with the sequence's edge fit: its range was off by (1 + delta) with the scale `applied`
    undone (the track's bias_scale; 1 when the tracker does not correct it), so the detector's scale on these frames
    is applied / (1 + delta), from every measured station of the sequence (edge_range.sequence_scale). Otherwise
    (a fine-tuned network, or no sequence fit) the corners' least-squares scale against the corrected labels
    (recalibrate's apparent_scale; None below SCALE_MIN_FRAMES frames). sd: how far it may be from the truth:
    the fit's standard error and the outline's own offset (EDGE_OFFSET_PX over the outline's median radius),
    in quadrature, and with the camera response's part: the cue's dependence on what the frames leave open of their
    response (the delta_sd of the edges' response record, under the report's key 'look') and its bias at the true
    pose over the grid of responses (edge_response_sd). Returns
    {value, se, sd, method}."""
    seq = edges.get("sequence") or {}
    radius = edges.get("outline_radius_px")
    resp = edges.get("look") or {}  # track_labels.response_record, under the report's key 'look'
    floor = float(np.hypot(EDGE_OFFSET_PX / radius if radius else 0.0,
                           np.hypot(resp.get("delta_sd", 0.0), edge_response_sd(resp.get("psf_sigma_px")))))
    if params == "none" and seq.get("delta") is not None:
        value, se = applied / (1.0 + seq["delta"]), applied * seq["delta_se"] / (1.0 + seq["delta"]) ** 2
        return {"value": value, "se": se, "sd": float(np.hypot(se, floor)), "method": "edges"}
    if cal.get("apparent_scale") is None:
        return None
    se = cal["apparent_scale_se"]
    return {"value": cal["apparent_scale"], "se": se, "sd": float(np.hypot(se, floor)), "method": "corners"}


def disagreement(scale: dict, cal: dict) -> str | None:
    """One line saying why an edges' scale is not adopted, or None: the detector's own corners, measured against
    the same edge-corrected labels (recalibrate's apparent_scale), are a second reading of the same scale; where
    the two differ by more than AGREE_Z standard deviations of their difference (the edges' sd, camera response
    included, and the corners' standard error), one of them is wrong and neither is evidence. No check without a
    corners' reading (fewer than SCALE_MIN_FRAMES frames with one) or for the corners' own scale."""
    corners, se = cal.get("apparent_scale"), cal.get("apparent_scale_se")
    if scale["method"] != "edges" or corners is None or se is None:
        return None
    sd = float(np.hypot(scale["sd"], se))
    if abs(scale["value"] - corners) <= AGREE_Z * sd:
        return None
    return (f"the original scale kept: the edges read the detector's scale as {scale['value']:.5f} +- "
            f"{scale['sd']:.5f}, its own corners as {corners:.5f} +- {se:.5f} ({abs(scale['value'] - corners) / sd:.1f}"
            f" sd apart, over {AGREE_Z:g})")


def no_evidence(scale: dict, applied: float) -> str | None:
    """One line saying why a scale is not adopted, or None: a scale within MOVE_Z of its own sd of the one the
    track undid (`applied`) is no evidence that it should move (an estimated response can leave the edges' scale
    uncertain by most of a per cent: its response term)."""
    if abs(scale["value"] - applied) > MOVE_Z * scale["sd"]:
        return None
    return (f"the original scale kept: the {scale['method']}' scale {scale['value']:.5f} +- {scale['sd']:.5f} is "
            f"within {MOVE_Z:g} sd of the one the track undid ({applied:.5f})")


def decide_scale(params: str, tcfg: TrackConfig, weights: str, edges: dict, cal: dict,
                 source: str = "") -> dict | None:
    """The apparent scale the candidate's error model takes (adapted_scale, params: AdaptConfig.params) with that
    error model as JSON under 'error_model' (candidate_error_model); with 'kept' (one line: disagreement,
    no_evidence) instead where the evidence does not hold (a fine-tuned network's error model is still written
    then, holding the scale kept); or None when no label's range was corrected by the edges (edges:
    track_labels.edge_corrected's record) or no scale was measured. weights: the network that made the labels'
    track (the base weights in the first round, the last round's after it); cal: recalibrate's figures; source:
    what the labels are, for a new error model's record."""
    from envisat_pose.perception.detect import weights_error_model

    if not any(f != 1.0 for f in edges["range_factor"]):
        return None
    tracked = weights_error_model(weights)
    applied = tracked.bias_scale if tcfg.tracker.noise.correct_scale else 1.0
    scale = adapted_scale(params, applied, edges, cal)
    if scale is None:
        return None
    reason = disagreement(scale, cal) or no_evidence(scale, applied)
    if reason is not None:
        if params == "none":  # the weights' own error model stays as it is
            return {**scale, "kept": reason}
        kept = {"value": tracked.bias_scale, "sd": max(tracked.bias_scale_sd, scale["sd"])}
        return {**scale, "kept": reason, "error_model": candidate_error_model(params, tracked, kept, cal, source)}
    return {**scale, "error_model": candidate_error_model(params, tracked, scale, cal, source)}


def candidate_error_model(params: str, tracked: ErrorModel, scale: dict, cal: dict, source: str) -> str:
    """The candidate's error model (JSON) with the apparent scale `scale` ({value, sd}). The unchanged
    network (params 'none'): the one its track used (tracked: measured on sequences for these very tensors), its
    bias_scale and bias_scale_sd replaced (the sd at least the sequences' spread). A fine-tuned network: a new one
    holding only what adapt measured on it, the covariance scale (recalibrate's, so that the tracker's R takes
    the weights' own: noise.sequence_cov_factor 1) and the apparent scale with its sd on the frames it was
    measured on; the rest at the defaults (white errors, no radial bias): the base's were measured on the network
    before the fine-tune (the adapted weights' metadata drops them, run_records.removed_calibration)."""
    if params == "none":
        return dataclasses.replace(tracked, bias_scale=scale["value"],
                                   bias_scale_sd=max(tracked.bias_scale_sd, scale["sd"])).to_json()
    return ErrorModel(cov_scale=cal.get("scale") or 1.0, bias_scale=scale["value"], bias_scale_sd=scale["sd"],
                      n_frames=int(cal.get("apparent_scale_frames") or 1), source=source).to_json()
