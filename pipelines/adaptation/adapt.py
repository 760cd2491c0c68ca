"""`envisat adapt`: teach the detector the look of a user's own frames from a cold start, with no labels.

The steps (one round; `rounds` repeats 2-5 from the last track):
1. track the sequence cold with the given weights (pipelines/runs/track.py `track_frames`): the 'before' run;
2. take the frames of the first part (all but the held-out final `held_out` share) where the tracker claims
   tracking with its half-turn decided (pseudo_labels.trusted_frames, over the smoothed segments) and whose label
   is tight (the largest corner 1-sigma of the smoothed covariance, label_sigma_px, below `max_label_sigma_px`);
   a lost, coasting or never-decided frame contributes nothing;
3. label them at the smoothed estimate (pipelines/adaptation/pseudo_labels.py: an unscented RTS smoother over each tracked
   segment, the box's corners projected with the face test's visibility), its range first corrected by the
   frames' own silhouette edges (`edge_range`, pipelines/adaptation/edge_range.py) where they can be measured, read in
   linear light: the camera's response and PSF from its TOML file where it gives them, else estimated from the
   labelled frames' edge profiles (pipelines/adaptation/edge_look.py; frames_look), the edges read again under the
   responses the estimate leaves open (look_record: the scale's look term);
4. fine-tune the detector on those (image, label) pairs in memory with the project's crops, augmentation and
   losses (perception/data.make_sample, perception/train's step): the normalization layers and the heads
   (`params='norm_heads'`), the whole network (`params='all'`), or nothing (`params='none'`, the default: the
   original network, recalibrated in step 5 only; docs/design.md has the figures behind that default);
5. recalibrate on the pseudo-labels: the covariance scale on their residuals (perception/calibrate.fit_cov_scale, the
   network's own covariances, the labels' region of interest, as `envisat calibrate`) and, when the labels' range
   was corrected by the edges, the detector's apparent scale on this look (the error model's bias_scale, which
   the tracker undoes in every frame: `tracker.noise.correct_scale`; `adapted_scale`), its sd (the fit's, the
   outline's own offset, the look's) the error model's bias_scale_sd, so the tracker's range covariance carries
   it; where the detector's own corners read that scale beyond AGREE_Z sd of the edges', or the scale lies
   within MOVE_Z of its sd of the one the track undid, the original scale is kept and the report's scale_note
   says why in one line (`disagreement`, `no_evidence`);
then track again with the adapted weights: the 'after' run. The held-out final part decides: if the adapted
weights do worse there than the original ones (tracked share, mean NIS per degree of freedom, the frame from which
the pose stays tracked: `worse_reason`), the original weights are kept and the report says why in one line.

Pseudo-labels carry what the tracker believes, its biases included: a detector that sees the target a little
smaller than it is gives a range a little long, and labels projected from that pose are a little small. Fine-tuning
on them alone teaches the look, not the size. The image's silhouette edges do not share the detector's bias: the
box's outline in the frames against the outline projected at the smoothed pose gives the image's scale error
delta, and the labels' range is divided by (1 + delta) (edge_range: one delta for the whole labelled set,
'sequence'; one per frame, 'frame'; or 'off'). A few dozen fine-tune steps hardly move a sub-pixel scale, so the
detector's apparent scale on this look is stored as the adapted weights' error model's bias_scale, which the
tracker undoes as it undoes the shipped weights' own: for the unchanged network (params 'none') the track's own
scale over (1 + delta), every measured station of the sequence behind it; for a fine-tuned one its corners'
scale against the corrected labels. The truth never enters here.

Outputs (staged inside out_dir and moved into place at the end, io.staged_folder; an error leaves out_dir as it
was):
    detector.safetensors   the adapted weights, only when adopted (their cov_scale and apparent scale recalibrated)
    detector.json          the model card: the source frames by content hash, the command, the figures
    report.json            the same figures and, when not adopted, the reason
    before/, after/        the two track runs (est.npz, det.npz, summary.json, recording.rrd, ...)
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from envisat_pose.camera_response import GAMMA_RANGE, LINEAR, SRGB, Response
from envisat_pose.config import InputError, check, to_dict
from envisat_pose.filtering.dynamics import load_inertia_T_kg_m2
from envisat_pose.io import STAGE_PREFIX, atomic_write_text, staged_folder
from envisat_pose.out_dirs import check_out_dir, make_out_dir
from envisat_pose.perception.calibrate import fit_cov_scale, nees_px
from envisat_pose.perception.errormodel import SCALE_MIN_FRAMES, mean_se
from envisat_pose.pipelines.adaptation.edge_look import estimate_look
from envisat_pose.pipelines.adaptation.edge_range import correct_range, frame_scale, sequence_scale
from envisat_pose.pipelines.adaptation.pseudo_labels import corner_labels, label_record, label_sigma_px, smooth_track
from envisat_pose.pipelines.detector.calibrate import collect_frames, flat_errors
from envisat_pose.pipelines.runs.track import TrackConfig, prepare_frames, track_frames
from envisat_pose.pipelines.tracking.build import tracker_filter
from envisat_pose.pipelines.tracking.camera_file import camera_look
from envisat_pose.pipelines.tracking.onboard import chaser_function
from envisat_pose.status import TRACKING

OUTPUTS = ("detector.safetensors", "detector.json", "report.json")
RUN_DIRS = ("before", "after")
# what "worse on the held-out part" means (worse_reason): margins below which a change is noise
SHARE_MARGIN = 0.02          # tracked share may drop by at most 2 points
STAY_MARGIN_FRAMES = 3       # the pose may start to stay tracked at most 3 frames later
NIS_MARGIN = np.log(1.5)     # |ln(mean NIS / dof)| may grow by at most ln 1.5
# How far a rendered outline's edge may sit from the true one, px: on MuJoCo Filament frames at the true pose the
# area method reads the lit faces' edges up to 0.12 px inward, the more the brighter the face (a darker rim pixel),
# and a sequence's scale error -0.02 to -0.16 % at 512 px (0.01-0.13 px over an outline radius of ~80 px), 0.00 to
# -0.10 % at 1024 px (bench/edge_truth.py, default scenario, seeds 0-3): the scale the edges give is not known
# better than this over the outline's radius.
EDGE_OFFSET_PX = 0.08
# The edge cue's scale bias at the true pose over the grid of looks, each read in linear light by its known
# response and blur (bench/edge_truth.py --looks, own renders of default seed 0 at 512 px): RMS 0.045 % over the
# 12 measurable looks with a PSF sigma of 0.3 or 1 px, 0.23 % over the 6 at 2.5 px. Carried in the adapted scale's
# sd beside the outline's own offset (edge_look_sd).
EDGE_LOOK_SD = 4.5e-4
EDGE_LOOK_SD_WIDE = 2.3e-3
WIDE_PSF_PX = 1.75      # a PSF sigma above this takes EDGE_LOOK_SD_WIDE
LOOK_FRAMES = 30        # labelled frames the response and blur are estimated from (evenly spread)
# How far an estimated power is from the rendered frames' own: RMS 0.62 over 17 looks of the project's renders
# (the grid at 512 px with a power measured, and three adapt runs: sRGB read 1.25, gamma 2.4 read 1.49, linear
# 1.15); the edges are read again at the estimate +- this (or its own standard error, if larger).
GAMMA_EST_SD = 0.6
AGREE_Z = 3.0           # edges and corners disagree beyond this many standard deviations of their difference
MOVE_Z = 2.0            # a scale is moved only by more than this many of its standard deviations
EDGE_RANGE_MODES = ("sequence", "frame", "off")
ADAPT_PARAMS = ("norm_heads", "all", "none")  # what the fine-tune trains (AdaptConfig.params)


@dataclass(frozen=True)
class AdaptConfig:
    """One `envisat adapt` job. track: the tracker's job (TrackConfig.from_scenario resolves it; its weights the
    ones adapted, "" the shipped); held_out: the final share of the sequence kept out of the labels and used to
    judge (0.25: the final quarter); rounds: track-label-fine-tune-track rounds; steps, lr, batch_size: the
    fine-tune's AdamW steps, peak rate (short warm-up, cosine decay) and batch; params: 'norm_heads' (the
    normalization layers and the heads), 'all' (the whole network) or 'none' (no fine-tune: the original network
    with its covariance and apparent scale recalibrated on the labels); min_trusted: the fewest labelled frames
    accepted; max_label_sigma_px: a label's largest corner 1-sigma (px) under the smoothed covariance;
    max_labels: at most this many labelled frames, evenly spread (memory); edge_range: how the labels' range is
    corrected by the frames' silhouette edges (pipelines/adaptation/edge_range.py): 'sequence' (one scale for all labelled
    frames: the detector's bias is the sequence's), 'frame' (each frame's own; a frame without a measurable outline
    keeps its range), 'off'; edge_min_frames: the fewest measured frames 'sequence' corrects with (fewer: no
    correction); max_calibration_frames: the
    recalibration's frames (evenly spread over the labelled ones); seed: the fine-tune's crops,
    augmentation and batches; device: torch device of the fine-tune ('cpu', 'cuda'); threads: torch CPU threads of
    the fine-tune (0: torch's default). Validated when built."""

    track: TrackConfig = field(default_factory=TrackConfig)
    held_out: float = 0.25
    rounds: int = 1
    steps: int = 60
    lr: float = 5e-4
    batch_size: int = 8
    params: str = "none"
    min_trusted: int = 20
    max_label_sigma_px: float = 0.5
    max_labels: int = 240
    edge_range: str = "sequence"
    edge_min_frames: int = 10
    max_calibration_frames: int = 60
    seed: int = 0
    device: str = "cpu"
    threads: int = 0

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        check(0.05 <= self.held_out <= 0.5, f"{p}held_out", self.held_out, "a share of the sequence in [0.05, 0.5]")
        check(1 <= self.rounds <= 10, f"{p}rounds", self.rounds, "1 to 10 rounds")
        check(self.steps >= 1, f"{p}steps", self.steps, "at least 1 fine-tune step")
        check(self.lr > 0, f"{p}lr", self.lr, "a positive learning rate")
        check(self.batch_size >= 1, f"{p}batch_size", self.batch_size, "at least 1 sample per batch")
        check(self.params in ADAPT_PARAMS, f"{p}params", self.params, "'norm_heads', 'all' or 'none'")
        check(self.min_trusted >= 1, f"{p}min_trusted", self.min_trusted, "at least 1 frame")
        check(self.max_label_sigma_px > 0, f"{p}max_label_sigma_px", self.max_label_sigma_px, "pixels > 0")
        check(self.max_labels >= self.min_trusted, f"{p}max_labels", self.max_labels, "at least min_trusted")
        check(self.edge_range in EDGE_RANGE_MODES, f"{p}edge_range", self.edge_range,
              "'sequence', 'frame' or 'off'")
        check(self.edge_min_frames >= 1, f"{p}edge_min_frames", self.edge_min_frames, "at least 1 frame")
        check(self.max_calibration_frames >= 1, f"{p}max_calibration_frames", self.max_calibration_frames,
              "at least 1 frame")
        check(self.threads >= 0, f"{p}threads", self.threads, "threads >= 0 (0: torch's default)")
        self.track.validate(f"{p}track")

    def __post_init__(self) -> None:
        self.validate()


# ---------------------------------------------------------------------------------------------------------
# Figures of a track run


def track_figures(run_dir: str, held_from: int) -> dict:
    """What a track run (est.npz) did on its held-out frames [held_from, T): tracked_share (of those frames),
    mean_nis_per_dof (sum NIS / sum dof over them; None without a measurement), stays_tracked_from (the first
    frame from which the status stays tracking to the end of the sequence; None when the last frame is not
    tracking), and the same over the whole sequence (tracked_share_all, frames)."""
    with np.load(os.path.join(run_dir, "est.npz")) as est:
        status, nis, dof = est["status"][0], est["nis"][0], est["nis_dof"][0]
    T = len(status)
    tracking = status == TRACKING
    held = slice(held_from, T)
    n_dof = float(np.sum(dof[held]))
    not_tracking = np.flatnonzero(~tracking)
    stays = None if not tracking[-1] else int(not_tracking[-1] + 1 if len(not_tracking) else 0)
    return {"frames": T, "held_out_from": int(held_from), "tracked_share": float(np.mean(tracking[held])),
            "mean_nis_per_dof": float(np.sum(nis[held]) / n_dof) if n_dof else None,
            "stays_tracked_from": stays, "tracked_share_all": float(np.mean(tracking))}


def worse_reason(before: dict, after: dict) -> str | None:
    """One line saying how the adapted weights did worse on the held-out part than the original ones (beyond the
    margins SHARE_MARGIN, STAY_MARGIN_FRAMES, NIS_MARGIN), or None."""
    if after["tracked_share"] < before["tracked_share"] - SHARE_MARGIN:
        return (f"the adapted weights tracked {after['tracked_share']:.0%} of the held-out frames, the original "
                f"ones {before['tracked_share']:.0%}")
    b, a = before["stays_tracked_from"], after["stays_tracked_from"]
    if b is not None and (a is None or a > b + STAY_MARGIN_FRAMES):
        return (f"with the adapted weights the pose stays tracked from frame {a}, with the original ones from "
                f"frame {b}" if a is not None else
                f"with the adapted weights the track does not hold to the end (the original ones: from frame {b})")
    nb, na = before["mean_nis_per_dof"], after["mean_nis_per_dof"]
    if nb is not None and (na is None or abs(np.log(na)) > abs(np.log(nb)) + NIS_MARGIN):
        return (f"the held-out mean NIS per degree of freedom is {na:.2f} with the adapted weights, {nb:.2f} with "
                "the original ones" if na is not None else
                "the adapted weights gave the filter no measurement on the held-out frames")
    return None


# ---------------------------------------------------------------------------------------------------------
# Labels from a track


def track_run_labels(run_dir: str, camera, orbit, q_sigma, dyn: dict, cut: int, cfg: AdaptConfig) -> dict:
    """The labels of a track run: the smoothed segments (pseudo_labels.smooth_track), the trusted frames before
    `cut` whose largest corner sigma is below cfg.max_label_sigma_px, at most cfg.max_labels of them evenly
    spread. Returns {frames (N,) int, x (N, 12) their smoothed states, sigma_px (N,) the largest corner sigma,
    trusted: all trusted frames before cut}; label_record(x[i], camera) labels frame i."""

    with np.load(os.path.join(run_dir, "est.npz")) as est, np.load(os.path.join(run_dir, "det.npz")) as det:
        t_s, x_hat, P, status = est["t_s"], est["x_hat"][0], est["P"][0], est["status"][0]
        n_hyp = det["n_hypotheses"]
    chaser_at = chaser_function(orbit)
    chaser = np.array([chaser_at(t) for t in t_s])
    sm = smooth_track(t_s, x_hat, P, status, chaser, q_sigma, n_hyp, **dyn)
    trusted = np.flatnonzero(sm.trusted[:cut])
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


def frames_look(x: np.ndarray, images: list[np.ndarray], camera, given: tuple) -> dict:
    """The frames' response and blur: given (the camera file's (response, psf_sigma_px), each None where not
    given) or estimated from LOOK_FRAMES of the labelled frames, evenly spread (pipelines/adaptation/edge_look.py, along the
    outline of each label's visible corners). Returns {response (Response), psf_sigma_px, estimate (the
    estimate's record), given: which came from the file, alternatives: the responses the edges are read under
    too, what the estimate leaves open (its power GAMMA_EST_SD either side, or for a response without a measured
    power the other named curve; none when the response was given)}."""

    response, psf = given
    pick = calibration_frames(len(images), LOOK_FRAMES)
    lab = corner_labels(x[pick], camera)
    fit = estimate_look([images[i] for i in pick], lab["corners_px"], lab["visible"] & lab["in_frame"])
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


def read_frames(source, remap, keep: np.ndarray) -> dict[int, np.ndarray]:
    """The frames `keep` of the source as the tracker saw them (remapped to its pinhole): {k: (H, W) uint8}."""
    import cv2

    want, out = set(int(k) for k in keep), {}
    for k, image in source.frames():
        if k in want:
            out[k] = image if remap is None else cv2.remap(image, remap[0], remap[1], cv2.INTER_LINEAR)
    return out


# ---------------------------------------------------------------------------------------------------------
# The fine-tune


def trainable(model, params: str) -> list:
    """The parameters fine-tuned: every one ('all'), the normalization layers' and the heads' ('norm_heads':
    batch-norm affine weights, the junction head, the line head), or none ('none')."""
    import torch

    if params == "all":
        return list(model.parameters())
    if params == "none":
        return []
    chosen = {id(p) for m in model.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)
              for p in m.parameters()}
    for name in ("jhead", "line_reduce", "line_mlp"):
        chosen |= {id(p) for p in getattr(model, name).parameters()}
    return [p for p in model.parameters() if id(p) in chosen]


def fine_tune(weights: str, images: list[np.ndarray], labels: list[dict], cfg: AdaptConfig,
              seed: np.random.SeedSequence, bar=None) -> tuple[object, dict]:
    """Fine-tune the detector in `weights` on (image, label) pairs (label: label_record's fields) with the
    project's crops, augmentation and losses (perception/data.make_sample, perception/train's step). Returns the
    model (CPU, eval mode) and {loss_first, loss_last (mean of the first and last tenth of the steps), steps,
    trainable (parameters)}."""
    import torch
    from torch.utils.data import default_collate

    from envisat_pose.perception.data import DataConfig, decode_label, make_sample
    from envisat_pose.perception.train import TrainConfig, _train_step, cosine_factor, to_device
    from envisat_pose.perception.weights import load_model

    dev = torch.device(cfg.device)
    model = load_model(weights, device=cfg.device)
    params = trainable(model, cfg.params)
    if not params:
        return model.cpu().eval(), {"steps": 0, "trainable": 0, "loss_first": None, "loss_last": None}
    for p in model.parameters():
        p.requires_grad_(False)
    for p in params:
        p.requires_grad_(True)
    model.train()
    for m in model.modules():  # running statistics kept: a batch of one sequence's frames is no population
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            m.eval()
    data = DataConfig(input_px=model.cfg.input_px, stride=model.cfg.stride)
    warmup = max(1, min(20, cfg.steps // 10))
    tcfg = TrainConfig(steps=cfg.steps, batch_size=cfg.batch_size, lr=cfg.lr, warmup_steps=warmup,
                       seed=int(seed.generate_state(1)[0]), model=model.cfg, data=data)
    opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=0.0)
    decoded = [decode_label(json.dumps(lab).encode(), f"pseudo-label {i}") for i, lab in enumerate(labels)]
    rng = np.random.default_rng(seed)
    losses = []
    for step in range(cfg.steps):
        lr = cfg.lr * min(1.0, (step + 1) / warmup) * cosine_factor(step / max(cfg.steps - 1, 1))
        for g in opt.param_groups:
            g["lr"] = lr
        pick = rng.integers(0, len(images), size=cfg.batch_size)
        batch = default_collate([make_sample(images[i], decoded[i], data, rng) for i in pick])
        terms = _train_step(model, model, opt, to_device(batch, dev), tcfg, step, dev, False)
        losses.append(float(terms["loss"]))
        if bar is not None:
            bar.update(1)
            bar.set_postfix_str(f"loss {losses[-1]:.3f}", refresh=False)
    tenth = max(1, len(losses) // 10)
    return model.cpu().eval(), {"steps": cfg.steps, "trainable": int(sum(p.numel() for p in params)),
                                "loss_first": float(np.mean(losses[:tenth])),
                                "loss_last": float(np.mean(losses[-tenth:]))}


def save_adapted(model, base: str, path: str, extra: dict) -> bool:
    """Write the model's tensors with the base weights' metadata (error model, face cue, ...) and `extra` on top.
    False (nothing written) when a tensor is not finite (a diverged fine-tune)."""
    import torch

    from envisat_pose.perception.weights import read_metadata, save_weights

    if not all(torch.isfinite(v).all() for v in model.state_dict().values() if v.is_floating_point()):
        return False
    meta = {k: v for k, v in read_metadata(base).items() if k not in ("format", "model_config")}
    save_weights(path, model, {**meta, **extra})
    return True


def edge_look_sd(psf_sigma_px: float | None) -> float:
    """The edge cue's look-dependence at the true pose (EDGE_LOOK_SD; EDGE_LOOK_SD_WIDE above WIDE_PSF_PX)."""
    return EDGE_LOOK_SD_WIDE if psf_sigma_px is not None and psf_sigma_px > WIDE_PSF_PX else EDGE_LOOK_SD


def adapted_scale(params: str, applied: float, edges: dict, cal: dict) -> dict | None:
    """The apparent scale the adapted weights' error model holds, or None. params 'none' (the network that made
    the track, unchanged) with the sequence's edge fit: its range was off by (1 + delta) with the scale `applied`
    undone (the track's bias_scale; 1 when the tracker does not correct it), so the detector's scale on this look
    is applied / (1 + delta), from every measured station of the sequence (edge_range.sequence_scale). Otherwise
    (a fine-tuned network, or no sequence fit) the corners' least-squares scale against the corrected labels
    (recalibrate's apparent_scale; None below SCALE_MIN_FRAMES frames). sd: how far it may be from the truth:
    the fit's standard error and the outline's own offset (EDGE_OFFSET_PX over the outline's median radius),
    in quadrature, and with the look's part: the cue's dependence on what the frames leave open of their response
    (edges' look delta_sd) and its bias at the true pose over the grid of looks (edge_look_sd). Returns
    {value, se, sd, method}."""
    seq = edges.get("sequence") or {}
    radius = edges.get("outline_radius_px")
    look = edges.get("look") or {}
    floor = float(np.hypot(EDGE_OFFSET_PX / radius if radius else 0.0,
                           np.hypot(look.get("delta_sd", 0.0), edge_look_sd(look.get("psf_sigma_px")))))
    if params == "none" and seq.get("delta") is not None:
        value, se = applied / (1.0 + seq["delta"]), applied * seq["delta_se"] / (1.0 + seq["delta"]) ** 2
        return {"value": value, "se": se, "sd": float(np.hypot(se, floor)), "method": "edges"}
    if cal.get("apparent_scale") is None:
        return None
    se = cal["apparent_scale_se"]
    return {"value": cal["apparent_scale"], "se": se, "sd": float(np.hypot(se, floor)), "method": "corners"}


def recalibrate(weights: str, images: list[np.ndarray], labels: list[dict], bar=None) -> dict:
    """The covariance scale of `weights` refitted on the pseudo-labels' residuals (perception/calibrate.fit_cov_scale
    over the correctly named corners, the network's own covariances, the labels' region of interest: what
    `envisat calibrate --roi labels` fits), and the detector's apparent scale against the labels (each frame's
    least-squares scale of its right corners about their centroid, perception/errormodel.apparent_scale: the
    quantity the error model's bias_scale holds). {scale, corners, mean_nees_before (at the file's scale),
    apparent_scale, apparent_scale_se, apparent_scale_frames}; scale None when fewer than 20 corners matched,
    apparent_scale None below SCALE_MIN_FRAMES frames with one."""
    from envisat_pose.perception.data import decode_label
    from envisat_pose.perception.detect import DetectConfig, load_detector, weights_cov_scale

    det = load_detector(weights, config=dataclasses.replace(DetectConfig(), cov_scale=1.0, refine=False,
                                                            refine_cov_floor_px2=0.0))
    samples = ((str(i), im, decode_label(json.dumps(lab).encode(), f"pseudo-label {i}"))
               for i, (im, lab) in enumerate(zip(images, labels)))
    frames = collect_frames(det, samples, bar=bar, roi="labels")
    err, cov, _ = flat_errors(frames)
    s_mean, s_se, s_n = mean_se(frames["scale"])
    scale = {"apparent_scale": s_mean if s_n >= SCALE_MIN_FRAMES else None,
             "apparent_scale_se": s_se if s_n >= SCALE_MIN_FRAMES else None, "apparent_scale_frames": s_n}
    if len(err) < 20:
        return {"scale": None, "corners": int(len(err)), "mean_nees_before": None, **scale}
    old = weights_cov_scale(weights)
    return {"scale": fit_cov_scale(err, cov), "corners": int(len(err)),
            "mean_nees_before": float(np.mean(nees_px(err, cov * old))), **scale}


# ---------------------------------------------------------------------------------------------------------
# The job


def content_sha256(source) -> str:
    """The source frames by content: sha256 of the sorted list of its files' sha256 (an image folder's frames, a
    dataset's shards, a video file)."""
    files = list(source.files) or [source.path]
    hashes = []
    for f in files:
        h = hashlib.sha256()
        with open(f, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
        hashes.append(h.hexdigest())
    return hashlib.sha256("\n".join(sorted(hashes)).encode()).hexdigest()


def _bar(progress: bool, total: int, desc: str, unit: str):
    if not progress:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, mininterval=0.5)


def _close(bar) -> None:
    if bar is not None:
        bar.close()


def adapt(cfg: AdaptConfig, source, out_dir: str, *, camera=None, progress: bool = True,
          command: list[str] | None = None) -> dict:
    """Adapt the detector in cfg.track.weights ("" the shipped) to the frames of `source` (a FrameSource or a path
    open_source opens at cfg.track.rate_hz) and write out_dir (module doc). camera: a PinholeCamera, a camera TOML
    file or None (the MJCF's chaser_cam at the frames' size), as track_frames; command: the command line, for the
    model card. Returns the report: {adopted, reason (None when adopted), scale_note (one line when the edges'
    scale was not adopted: disagreement; else None), before, after (track_figures), rounds
    (per round: labels, fine-tune, calibration), source, timing_s}. InputError (one line) when the first part
    holds fewer than cfg.min_trusted labelled frames; nothing is written then."""

    check_out_dir(out_dir, field="out_dir")
    look = camera_look(camera) if isinstance(camera, str) else (None, None)
    tcfg, source, camera, remap, _ = prepare_frames(cfg.track, source, camera)
    make_out_dir(out_dir, field="out_dir")
    with staged_folder(out_dir, OUTPUTS) as stage:
        report = _adapt(cfg, tcfg, source, camera, remap, stage, progress, command, look)
        _replace_dirs(out_dir, stage)
    return report


def _replace_dirs(out_dir: str, stage: str) -> None:
    """Make room for the staged before/ and after/ folders: an earlier run's go to a folder removed at once."""
    import shutil
    import tempfile

    old = [d for d in RUN_DIRS if os.path.isdir(os.path.join(out_dir, d))]
    if old:
        trash = tempfile.mkdtemp(prefix=STAGE_PREFIX, dir=out_dir)
        for d in old:
            os.replace(os.path.join(out_dir, d), os.path.join(trash, d))
        shutil.rmtree(trash, ignore_errors=True)


@dataclass(frozen=True)
class AdaptRun:
    """What every step of one adapt job reads: the job (cfg) and the tracker's (tcfg, its weights the base), the
    frames (source, remap: cv2.remap maps to the pinhole, or None), the pinhole camera, the stage folder, whether
    to show progress, the first held-out frame (cut), the smoother's model (q_sigma, dyn: smoother_model) and
    the camera's response and PSF sigma where its file gives them (look)."""

    cfg: AdaptConfig
    tcfg: TrackConfig
    source: object
    camera: object
    remap: tuple | None
    stage: str
    progress: bool
    cut: int
    q_sigma: tuple
    dyn: dict
    look: tuple = (None, None)  # the camera file's (response, psf_sigma_px), None where it does not say


def smoother_model(tcfg: TrackConfig) -> tuple[tuple, dict]:
    """The filter's model as the tracker builds it (pipelines/tracking/tracker.Tracker), for the smoother: q_sigma, each
    component the larger of the filter's and the detector's (tracker.noise.detector_q_sigma), and the dynamics
    (J_T, mu_m3_s2, gravity_gradient, max_step_s). Nothing of the detector is needed."""

    fcfg = tracker_filter(dataclasses.asdict(tcfg.filter))
    q = tuple(max(a, b) for a, b in zip(fcfg.q_sigma, tcfg.tracker.noise.detector_q_sigma))
    return q, {"J_T": load_inertia_T_kg_m2(), "mu_m3_s2": float(tcfg.orbit.mu_m3_s2),
               "gravity_gradient": tcfg.gravity_gradient, "max_step_s": fcfg.max_rk4_step_s}


@contextmanager
def torch_threads(n: int):
    """torch's CPU thread count set to n (0: os.cpu_count()) inside the block, restored on every way out."""
    import torch

    old = torch.get_num_threads()
    torch.set_num_threads(n or os.cpu_count() or 1)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def label_step(run: AdaptRun, track_dir: str) -> tuple[dict, list[np.ndarray]]:
    """Step 2-3: the labelled frames of a track run (track_run_labels), their images, their states corrected by
    the silhouette edges (edge_corrected) and labelled there. Returns (lab with 'labels' and 'edges' added,
    images); InputError (one line) below cfg.min_trusted labelled frames."""

    cfg = run.cfg
    lab = track_run_labels(track_dir, run.camera, run.tcfg.orbit, run.q_sigma, run.dyn, run.cut, cfg)
    if len(lab["frames"]) < cfg.min_trusted:
        raise InputError(
            f"src {run.source.path!r}: only {len(lab['frames'])} trusted frames in the first {1 - cfg.held_out:.0%} "
            f"of the sequence (tracking, half-turn decided, label sigma < {cfg.max_label_sigma_px:g} px; "
            f"{lab['trusted']} before the sigma test); adapt needs at least {cfg.min_trusted} (min_trusted)")
    frames = read_frames(run.source, run.remap, lab["frames"])
    images = [frames[int(k)] for k in lab["frames"]]
    look = frames_look(lab["x"], images, run.camera, run.look)
    x_lab, lab["edges"] = edge_corrected(lab["x"], images, run.camera, cfg.edge_range, cfg.edge_min_frames,
                                         look["response"], look["psf_sigma_px"])
    lab["edges"]["look"] = look_record(look, lab["x"], images, run.camera, lab["edges"], cfg.edge_min_frames)
    lab["labels"] = [label_record(v, run.camera) for v in x_lab]
    return lab, images


def look_record(look: dict, x: np.ndarray, images: list[np.ndarray], camera, edges: dict, min_frames: int
                ) -> dict:
    """The look the edges were read with (frames_look) as JSON data, and the sequence's delta under each of its
    alternative responses: delta_sd, the largest difference from the delta applied (0 without alternatives or a
    fit), is how much the cue depends on what the frames leave open of their response (adapted_scale's look
    term)."""
    delta, alt = edges["sequence"]["delta"], []
    if delta is not None:
        for r in look["alternatives"]:
            _, rec = edge_corrected(x, images, camera, "off", min_frames, r, look["psf_sigma_px"])
            alt.append(rec["sequence"]["delta"])
    spread = [abs(a - delta) for a in alt if a is not None]
    if len(spread) < len(alt):  # an alternative reading measures nothing: the cue is not held
        spread.append(float("inf"))
    return {"response": look["response"].name(), "psf_sigma_px": look["psf_sigma_px"], "given": look["given"],
            "estimate": look["estimate"], "alternatives": [r.name() for r in look["alternatives"]],
            "alternative_deltas": alt, "delta_sd": max(spread, default=0.0)}


def calibration_frames(n: int, most: int) -> np.ndarray:
    """Indices of at most `most` of n labelled frames, evenly spread."""
    return np.unique(np.linspace(0, n - 1, min(n, most)).round().astype(int))


def recalibration_step(run: AdaptRun, weights: str, candidate: str, model, images: list[np.ndarray],
                       lab: dict) -> dict:
    """Step 5: the candidate's covariance scale and apparent scale on the labels (recalibrate, adapted_scale),
    written into its file (save_adapted). weights: the network that made the labels' track. Returns
    {calibration, apparent_scale, apparent_scale_adopted}."""
    cfg, edges = run.cfg, lab["edges"]
    sub = calibration_frames(len(images), cfg.max_calibration_frames)
    bar = _bar(run.progress, len(sub), "recalibrate", "frame")
    try:
        cal = recalibrate(candidate, [images[i] for i in sub], [lab["labels"][i] for i in sub], bar)
    finally:
        _close(bar)
    extra = {}
    if cal["scale"] is not None:
        extra |= {"cov_scale": cal["scale"], "cov_calibration": json.dumps(
            {"scale": cal["scale"], "corners": cal["corners"], "data": "pseudo-labels of "
             f"{content_sha256(run.source)}", "roi": "labels", "by": "envisat adapt"}, sort_keys=True)}
    scale = scale_step(run, weights, edges, cal)
    if scale is not None and "error_model" in scale:
        extra["error_model"] = scale.pop("error_model")
    if extra:
        save_adapted(model, run.tcfg.weights, candidate, extra)
    return {"calibration": cal, "apparent_scale": scale,
            "apparent_scale_adopted": scale is not None and "kept" not in scale}


def no_evidence(scale: dict, applied: float) -> str | None:
    """One line saying why a scale is not adopted, or None: a scale within MOVE_Z of its own sd of the one the
    track undid (`applied`) is no evidence that it should move (an estimated response can leave the edges' scale
    uncertain by most of a per cent: its look term)."""
    if abs(scale["value"] - applied) > MOVE_Z * scale["sd"]:
        return None
    return (f"the original scale kept: the {scale['method']}' scale {scale['value']:.5f} +- {scale['sd']:.5f} is "
            f"within {MOVE_Z:g} sd of the one the track undid ({applied:.5f})")


def disagreement(scale: dict, cal: dict) -> str | None:
    """One line saying why an edges' scale is not adopted, or None: the detector's own corners, measured against
    the same edge-corrected labels (recalibrate's apparent_scale), are a second reading of the same scale; where
    the two differ by more than AGREE_Z standard deviations of their difference (the edges' sd, look included,
    and the corners' standard error), one of them is wrong and neither is evidence. No check without a corners'
    reading (fewer than SCALE_MIN_FRAMES frames with one) or for the corners' own scale."""
    corners, se = cal.get("apparent_scale"), cal.get("apparent_scale_se")
    if scale["method"] != "edges" or corners is None or se is None:
        return None
    sd = float(np.hypot(scale["sd"], se))
    if abs(scale["value"] - corners) <= AGREE_Z * sd:
        return None
    return (f"the original scale kept: the edges read the detector's scale as {scale['value']:.5f} +- "
            f"{scale['sd']:.5f}, its own corners as {corners:.5f} +- {se:.5f} ({abs(scale['value'] - corners) / sd:.1f}"
            f" sd apart, over {AGREE_Z:g})")


def scale_step(run: AdaptRun, weights: str, edges: dict, cal: dict) -> dict | None:
    """The apparent scale the candidate's error model takes (adapted_scale) with that error model as JSON under
    'error_model'; with 'kept' (one line, disagreement) instead where the evidence does not hold; or None. Only labels whose range the edges corrected teach a scale: uncorrected ones carry the
    track's own, so measuring against them gives back the scale the tracker assumed."""
    from envisat_pose.perception.detect import weights_error_model

    if not any(f != 1.0 for f in edges["range_factor"]):
        return None
    tracked = weights_error_model(weights)
    applied = tracked.bias_scale if run.tcfg.tracker.noise.correct_scale else 1.0
    scale = adapted_scale(run.cfg.params, applied, edges, cal)
    if scale is None:
        return None
    reason = disagreement(scale, cal) or no_evidence(scale, applied)
    if reason is not None:
        return {**scale, "kept": reason}
    em = dataclasses.replace(weights_error_model(run.tcfg.weights), bias_scale=scale["value"],
                             bias_scale_sd=max(tracked.bias_scale_sd, scale["sd"]))
    return {**scale, "error_model": em.to_json()}


def round_dir(run: AdaptRun, r: int) -> str:
    """Where round r's track goes: after/ for the last round, round-r/ (removed later) before it."""
    return os.path.join(run.stage, "after" if r == run.cfg.rounds - 1 else f"round-{r}")


def adapt_round(run: AdaptRun, r: int, track_dir: str, weights: str, seed: np.random.SeedSequence,
                timing: dict) -> tuple[dict, str | None]:
    """One round: label the track in track_dir, fine-tune `weights` on the labels, recalibrate, write the
    candidate round-r.safetensors into the stage and track with it (into after/ on the last round, round-r/
    before). Returns (the round's record, the candidate's path; None when the fine-tune diverged: the record
    says so and nothing was tracked)."""

    cfg, t1 = run.cfg, time.perf_counter()
    lab, images = label_step(run, track_dir)
    timing[f"labels_{r}"] = time.perf_counter() - t1
    info = {"round": r, "labels": int(len(lab["frames"])), "trusted_before_sigma_test": lab["trusted"],
            "label_sigma_px_median": float(np.median(lab["sigma_px"])),
            "label_frames": [int(k) for k in lab["frames"]], "edge_range": lab["edges"]}
    candidate = os.path.join(run.stage, f"round-{r}.safetensors")
    with torch_threads(cfg.threads):
        bar = _bar(run.progress, cfg.steps, f"fine-tune {r + 1}/{cfg.rounds}", "step")
        t1 = time.perf_counter()
        try:
            model, info["fine_tune"] = fine_tune(weights, images, lab["labels"], cfg, seed, bar)
        finally:
            _close(bar)
        timing[f"fine_tune_{r}"] = time.perf_counter() - t1
        if not save_adapted(model, run.tcfg.weights, candidate, {}):
            return {**info, "diverged": True}, None
        t1 = time.perf_counter()
        info |= recalibration_step(run, weights, candidate, model, images, lab)
        timing[f"recalibrate_{r}"] = time.perf_counter() - t1
    after_dir = round_dir(run, r)
    t1 = time.perf_counter()
    track_frames(dataclasses.replace(run.tcfg, weights=candidate), run.source, run.camera, run.remap, after_dir,
                 progress=run.progress)
    timing[f"track_after_{r}"] = time.perf_counter() - t1
    info["after"] = track_figures(after_dir, run.cut)
    return info, candidate


def _adapt(cfg: AdaptConfig, tcfg: TrackConfig, source, camera, remap, stage: str, progress: bool,
           command: list[str] | None, look: tuple = (None, None)) -> dict:
    """The job inside its stage: track before, cfg.rounds adapt_round's (each from the last round's track and
    weights, the earlier round's files removed), the held-out verdict (worse_reason), _finish."""
    import shutil

    t0 = time.perf_counter()
    T = len(source.t_s)
    run = AdaptRun(cfg, tcfg, source, camera, remap, stage, progress, int(np.floor(T * (1.0 - cfg.held_out))),
                   *smoother_model(tcfg), look)
    before_dir = os.path.join(stage, "before")
    track_frames(tcfg, source, camera, remap, before_dir, progress=progress)
    timing = {"track_before": time.perf_counter() - t0}
    before = track_figures(before_dir, run.cut)
    seeds = np.random.SeedSequence(cfg.seed).spawn(cfg.rounds)
    last_dir, weights, rounds = before_dir, tcfg.weights, []
    for r in range(cfg.rounds):
        info, candidate = adapt_round(run, r, last_dir, weights, seeds[r], timing)
        rounds.append(info)
        if candidate is None:
            return _finish(cfg, tcfg, source, stage, command, before, None, rounds, timing, t0,
                           "the fine-tune diverged (non-finite weights)")
        if last_dir != before_dir:
            shutil.rmtree(last_dir, ignore_errors=True)
        if weights != tcfg.weights:
            os.remove(weights)
        last_dir, weights = round_dir(run, r), candidate
    after = rounds[-1]["after"]
    reason = worse_reason(before, after)
    if reason is None:
        os.replace(weights, os.path.join(stage, "detector.safetensors"))
    else:
        os.remove(weights)
    return _finish(cfg, tcfg, source, stage, command, before, after, rounds, timing, t0, reason)


def _finish(cfg, tcfg, source, stage, command, before, after, rounds, timing, t0, reason) -> dict:
    """Write report.json and the model card detector.json into the stage; the report."""

    for f in os.listdir(stage):
        if f.startswith("round-"):
            p = os.path.join(stage, f)
            if os.path.isdir(p):
                import shutil

                shutil.rmtree(p, ignore_errors=True)
            else:
                os.remove(p)
    timing["total"] = time.perf_counter() - t0
    adopted = reason is None
    report = {
        "adopted": adopted,
        "reason": reason,
        "source": {"path": source.path, "kind": source.kind, "frames": len(source.t_s),
                   "size_px": list(source.size_px), "content_sha256": content_sha256(source)},
        "base_weights": tcfg.weights,
        "command": command,
        "config": to_dict(dataclasses.replace(cfg, track=tcfg)),
        "held_out_from_frame": int(np.floor(len(source.t_s) * (1.0 - cfg.held_out))),
        "before": before,
        "after": after,
        "scale_note": (rounds[-1].get("apparent_scale") or {}).get("kept") if rounds else None,
        "rounds": rounds,
        "timing_s": timing,
    }
    text = json.dumps(report, indent=1, sort_keys=True, default=str) + "\n"
    atomic_write_text(os.path.join(stage, "report.json"), text)
    if adopted:  # the model card beside the weights
        card = {k: report[k] for k in ("source", "base_weights", "command", "config", "held_out_from_frame",
                                       "before", "after", "rounds")}
        card["weights"] = "detector.safetensors"
        atomic_write_text(os.path.join(stage, "detector.json"),
                          json.dumps(card, indent=1, sort_keys=True, default=str) + "\n")
    return report
