"""`envisat adapt`: teach the detector a user's own frames from a cold start, with no labels.

The steps (one round; `rounds` repeats 2-5 from the last track):
1. track the sequence cold with the given weights (pipelines/runs/track.py `track_frames`): the 'before' run;
2. take the frames of the first part (all but the held-out final `held_out` share) where the tracker claims
   tracking with its half-turn decided (pseudo_labels.trusted_frames, over the smoothed segments) and whose label
   is tight (the largest corner 1-sigma of the smoothed covariance, label_sigma_px, below `max_label_sigma_px`);
   a lost, coasting or never-decided frame contributes nothing;
3. label them (pipelines/adaptation/track_labels.py) at the smoothed estimate
   (pipelines/adaptation/pseudo_labels.py: an unscented RTS smoother over each tracked segment, cut at the held-out part, the box's corners projected with the face test's visibility), its range first corrected by the
   frames' own silhouette edges (`edge_range`, pipelines/adaptation/edge_range.py) where they can be measured, read in
   linear light: the camera response (its response curve and PSF) from its TOML file where it gives them, else
   estimated from the labelled frames' edge profiles (pipelines/adaptation/edge_response.py; frames_response), the
   edges read again under the responses the estimate leaves open (response_record: the scale's response term);
4. fine-tune the detector on those (image, label) pairs in memory through the project's Trainer (its crops,
   augmentation, schedule, step and losses: pipelines/adaptation/fine_tune.py): the normalization layers and the
   heads (`params='norm_heads'`), the whole network (`params='all'`), or nothing (`params='none'`, the default:
   the original network, recalibrated in step 5 only; docs/design.md has the figures behind that default);
5. recalibrate on the pseudo-labels (pipelines/adaptation/recalibrate.py): the covariance scale on their
   residuals (perception/calibrate.fit_cov_scale, the network's own covariances, the labels' region of interest,
   as `envisat calibrate`) and, when the labels' range was corrected by the edges, the detector's apparent scale
   on these frames (the error model's bias_scale, which the tracker undoes in every frame:
   `tracker.noise.correct_scale`; pipelines/adaptation/scale_decision.py), its sd (the fit's, the outline's own
   offset, the camera response's) the error model's bias_scale_sd, so the tracker's range covariance carries it; where the detector's own corners read that scale beyond AGREE_Z sd of the edges', or the scale lies
   within MOVE_Z of its sd of the one the track undid, the original scale is kept and the report's scale_note
   says why in one line (`disagreement`, `no_evidence`);
then track again with the adapted weights: the 'after' run. The held-out final part decides: if the adapted
weights do worse there than the original ones (tracked share, mean NIS per degree of freedom, the frame from which
the pose stays tracked: `worse_reason`), the original weights are kept and the report says why in one line.

Pseudo-labels carry what the tracker believes, its biases included: a detector that sees the target a little
smaller than it is gives a range a little long, and labels projected from that pose are a little small. Fine-tuning
on them alone teaches the detector these frames, not the size. The image's silhouette edges do not share the
detector's bias: the box's outline in the frames against the outline projected at the smoothed pose gives the image's scale error
delta, and the labels' range is divided by (1 + delta) (edge_range: one delta for the whole labelled set,
'sequence'; one per frame, 'frame'; or 'off'). A few dozen fine-tune steps hardly move a sub-pixel scale, so the
detector's apparent scale on these frames is stored as the adapted weights' error model's bias_scale, which the
tracker undoes as it undoes the shipped weights' own: for the unchanged network (params 'none') the track's own
scale over (1 + delta), every measured station of the sequence behind it; for a fine-tuned one its corners'
scale against the corrected labels. The truth never enters here.

This module runs the job (the rounds, the held-out verdict) and writes its files.
Outputs (staged inside out_dir and moved into place at the end, io.staged_folder; an error leaves out_dir as it
was):
    detector.safetensors   the adapted weights, only when adopted (their cov_scale and apparent scale recalibrated;
                           a fine-tuned network's metadata without the base's calibration adapt does not measure
                           again: recalibration_step; their metadata `adaptation`: the frames and base weights they
                           were adapted on); a rejected run leaves an earlier adopted pair (with detector.json) in
                           out_dir as it was
    detector.json          the model card: the source frames by content hash, the command, the figures
    report.json            the same figures and, when not adopted, the reason (earlier_weights_kept: an earlier
                           run's detector.safetensors stays in out_dir)
    before/, after/        the two track runs (est.npz, det.npz, summary.json, recording.rrd, ...)
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import time
from dataclasses import dataclass, field

import numpy as np

from envisat_pose.config import Config, InputError, as_path_or_object, check, config_arg, path_arg, to_dict
from envisat_pose.io import atomic_write_text, stage_prefix, staged_folder
from envisat_pose.out_dirs import check_out_dir, made_out_dir, refuse_overlap, written_by
from envisat_pose.out_lock import locks_output
from envisat_pose.perception import weights_keys as wk
from envisat_pose.pipelines.adaptation.fine_tune import ADAPT_PARAMS, check_fine_tune, fine_tune, save_adapted
from envisat_pose.pipelines.adaptation.pseudo_labels import label_record
from envisat_pose.pipelines.adaptation.recalibrate import recalibrate
from envisat_pose.pipelines.adaptation.run_records import (
    NOT_KEPT,
    adaptation_record,
    content_sha256,
    name_run_weights,
    removed_calibration,
)
from envisat_pose.pipelines.adaptation.scale_decision import decide_scale
from envisat_pose.pipelines.adaptation.track_labels import (
    EDGE_RANGE_MODES,
    calibration_frames,
    edge_corrected,
    frames_response,
    read_frames,
    response_record,
    smoother_model,
    track_run_labels,
)
from envisat_pose.pipelines.adaptation.verdict import track_figures, unchanged_track, worse_reason
from envisat_pose.pipelines.common.job_defaults import job_record, weights_name
from envisat_pose.pipelines.common.threads import compute_threads, default_torch_threads
from envisat_pose.pipelines.runs.track import TrackConfig, prepare_frames, track_frames
from envisat_pose.pipelines.tracking.camera_file import read_camera_response
from envisat_pose.target import require_envisat

OUTPUTS = ("detector.safetensors", "detector.json", "report.json")
# the outputs a run's own replace (every run writes report.json); an earlier adopted detector.safetensors and its
# card are replaced only by adopted ones: a rejected rerun in the same folder loses no adopted result
STALE_OUTPUTS = ("report.json",)
RUN_DIRS = ("before", "after")


@dataclass(frozen=True)
class AdaptConfig(Config):
    """One `envisat adapt` job. track: the tracker's job (TrackConfig(scenario=NAME, ...); its weights the ones
    adapted, the shipped ones by default); held_out: the final share of the sequence kept out of the labels and used to
    judge (0.25: the final quarter); rounds: track-label-fine-tune-track rounds; steps, lr, batch_size: the
    fine-tune's AdamW steps, peak rate (the trainer's schedule: a warm-up over a tenth of the steps, at most 20,
    then its cosine decay) and batch; params: 'norm_heads' (the normalization layers and the heads), 'all' (the
    whole network) or 'none' (no fine-tune: the original network with its covariance and apparent scale
    recalibrated on the labels); min_trusted: the fewest labelled frames
    accepted; max_label_sigma_px: a label's largest corner 1-sigma (px) under the smoothed covariance;
    max_labels: at most this many labelled frames, evenly spread (memory); edge_range: how the labels' range is
    corrected by the frames' silhouette edges (pipelines/adaptation/edge_range.py): 'sequence' (one scale for all labelled
    frames: the detector's bias is the sequence's), 'frame' (each frame's own; a frame without a measurable outline
    keeps its range), 'off'; edge_min_frames: the fewest measured frames 'sequence' corrects with (fewer: no
    correction); max_calibration_frames: the
    recalibration's frames (evenly spread over the labelled ones); seed: the fine-tune's crops,
    augmentation and batches; device: torch device of the fine-tune ('cpu', 'cuda'); threads: torch CPU threads of
    the fine-tune (0: torch's default, no more than the usable cores). Validated when built."""

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
        check(self.params in ADAPT_PARAMS, f"{p}params", self.params, "'norm_heads', 'all' or 'none'")
        unset = {f.name: f.default for f in dataclasses.fields(self) if f.name in ("steps", "lr")}
        given = [name for name in ("steps", "lr") if getattr(self, name) != unset[name]] or ["steps"]  # the one set
        check(self.params != "none" or {"steps": self.steps, "lr": self.lr} == unset, f"{p}{given[0]}",
              getattr(self, given[0]), "the defaults of steps and lr with params 'none' (they set the fine-tune, "
              "which is off: params 'norm_heads' or 'all')")
        check(0 <= self.seed < 2**63, f"{p}seed", self.seed, "a non-negative integer seed below 2^63 (numpy's "
              "generators take no negative one)")
        check(self.min_trusted >= 1, f"{p}min_trusted", self.min_trusted, "at least 1 frame")
        check(self.max_label_sigma_px > 0, f"{p}max_label_sigma_px", self.max_label_sigma_px, "pixels > 0")
        check(self.max_labels >= self.min_trusted, f"{p}max_labels", self.max_labels, "at least min_trusted")
        check(self.edge_range in EDGE_RANGE_MODES, f"{p}edge_range", self.edge_range,
              "'sequence', 'frame' or 'off'")
        # the fine-tune and the recalibration know ENVISAT's corner network alone
        require_envisat(self.track.target, f"{p}track.target", "adapt")
        if self.params != "none":  # the fine-tune's batch and rate, as its TrainConfig takes them for these weights
            check_fine_tune(self, p)
        check(self.batch_size >= 1, f"{p}batch_size", self.batch_size, "at least 1 sample per batch")
        check(self.edge_min_frames >= 1, f"{p}edge_min_frames", self.edge_min_frames, "at least 1 frame")
        check(self.max_calibration_frames >= 1, f"{p}max_calibration_frames", self.max_calibration_frames,
              "at least 1 frame")
        check(0 <= self.threads <= 256, f"{p}threads", self.threads, "0 to 256 threads (0: torch's default; 256, "
              "as track's and run's)")
        check(re.fullmatch(r"cpu|cuda(:\d+)?", self.device) is not None, f"{p}device", self.device, "cpu or cuda")
        if self.device.startswith("cuda"):
            import torch

            check(torch.cuda.is_available(), f"{p}device", self.device, "a CUDA device (none is available here)")
        self.track.validate(f"{p}track")


# ---------------------------------------------------------------------------------------------------------
# The job: its rounds


@dataclass(frozen=True)
class AdaptRun:
    """What every step of one adapt job reads: the job (cfg) and the tracker's (tcfg, its weights the base), the
    frames (source, remap: cv2.remap maps to the pinhole, or None), the pinhole camera, the stage folder, whether
    to show progress, the first held-out frame (cut), the smoother's model (q_sigma, dyn: smoother_model) and
    the camera's response and PSF sigma where its file gives them (given_response)."""

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
    given_response: tuple = (None, None)  # the camera file's (response, psf_sigma_px), None where it does not say
    camera_file: str | None = None  # the camera TOML given: the tracks read it again and record it by name

    def track_camera(self) -> tuple:
        """(camera, remap) as track_frames takes them: the file given, else the pinhole and its remap."""
        return (self.camera_file, None) if self.camera_file else (self.camera, self.remap)


def label_step(run: AdaptRun, track_dir: str) -> tuple[dict, list[np.ndarray]]:
    """Step 2-3: the labelled frames of a track run (track_run_labels), their images, their states corrected by
    the silhouette edges (edge_corrected) and labelled there. Returns (lab with 'labels' and 'edges' added,
    images); InputError (one line) below cfg.min_trusted labelled frames."""

    cfg = run.cfg
    lab = track_run_labels(track_dir, run.camera, run.tcfg.orbit, run.q_sigma, run.dyn, run.cut, cfg)
    if len(lab["frames"]) < cfg.min_trusted:
        tracked = track_figures(track_dir, run.cut)["tracked_share_all"]
        raise InputError(
            f"source {run.source.path!r}: only {len(lab['frames'])} trusted frames in the first {1 - cfg.held_out:.0%} "
            f"of the sequence (tracking, half-turn decided, label sigma < {cfg.max_label_sigma_px:g} px; "
            f"{lab['trusted']} before the sigma test; the tracker tracked {tracked:.0%} of all frames, after a cold "
            f"start of 20 or more); adapt needs at least {cfg.min_trusted} (min_trusted): a longer sequence")
    frames = read_frames(run.source, run.remap, lab["frames"])
    images = [frames[int(k)] for k in lab["frames"]]
    resp = frames_response(lab["x"], images, run.camera, run.given_response)
    x_lab, lab["edges"] = edge_corrected(lab["x"], images, run.camera, cfg.edge_range, cfg.edge_min_frames,
                                         resp["response"], resp["psf_sigma_px"])
    # the report's key 'look' (report.json's rounds[].edge_range.look), unchanged for readers of the report
    lab["edges"]["look"] = response_record(resp, lab["x"], images, run.camera, lab["edges"], cfg.edge_min_frames)
    lab["labels"] = [label_record(v, run.camera) for v in x_lab]
    return lab, images


def recalibration_step(run: AdaptRun, weights: str, candidate: str, model, images: list[np.ndarray],
                       lab: dict) -> dict:
    """Step 5: the candidate's covariance scale and apparent scale on the labels (recalibrate, decide_scale),
    written into its file (save_adapted) with the record of what it was adapted on (run_records.adaptation_record).
    weights: the network that made the labels' track (the base weights in the first round, the last round's
    after it), whose metadata the unchanged network (params 'none') keeps where this round measures nothing new (a
    scale kept is that network's); a fine-tuned one keeps none of the calibration measured on the network before it
    (wk.COV_CALIBRATION_KEYS) but what this round measures again. Returns {calibration, apparent_scale,
    apparent_scale_adopted, removed_calibration (run_records.removed_calibration: one line, or None)}."""
    cfg, edges = run.cfg, lab["edges"]
    sub = calibration_frames(len(images), cfg.max_calibration_frames)
    bar = _bar(run.progress, len(sub), "recalibrate", "frame")
    try:
        cal = recalibrate(candidate, [images[i] for i in sub], [lab["labels"][i] for i in sub], bar)
    finally:
        _close(bar)
    sha = content_sha256(run.source)
    extra = {wk.ADAPTATION_KEY: adaptation_record(cfg, run.tcfg, run.source, sha, run.cut)}  # what it adapted on
    if cal["scale"] is not None:
        extra |= {wk.COV_SCALE_KEY: cal["scale"], wk.COV_CALIBRATION_KEY: json.dumps(
            {"scale": cal["scale"], "corners": cal["corners"], "data": f"pseudo-labels of {sha}", "roi": "labels",
             "by": "envisat adapt"}, sort_keys=True)}
    scale = decide_scale(cfg.params, run.tcfg, weights, edges, cal, source=f"envisat adapt: pseudo-labels of {sha}")
    if scale is not None and "error_model" in scale:
        extra[wk.ERROR_MODEL_KEY] = scale.pop("error_model")
    drop = () if cfg.params == "none" else wk.COV_CALIBRATION_KEYS
    removed = removed_calibration(weights, extra, drop, os.path.join(os.path.dirname(run.stage), OUTPUTS[0]))
    save_adapted(model, weights, candidate, extra, drop)
    return {"calibration": cal, "apparent_scale": scale,
            "apparent_scale_adopted": scale is not None and "kept" not in scale, "removed_calibration": removed}


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
    with compute_threads(cfg.threads or default_torch_threads()):
        bar = _bar(run.progress, cfg.steps, f"fine-tune {r + 1}/{cfg.rounds}", "step")
        t1 = time.perf_counter()
        try:
            model, info["fine_tune"] = fine_tune(weights, images, lab["labels"], cfg, seed, bar)
        finally:
            _close(bar)
        timing[f"fine_tune_{r}"] = time.perf_counter() - t1
        if not save_adapted(model, weights, candidate, {}):  # the last round's metadata: its scale, if kept
            return {**info, "diverged": True}, None
        t1 = time.perf_counter()
        info |= recalibration_step(run, weights, candidate, model, images, lab)
        timing[f"recalibrate_{r}"] = time.perf_counter() - t1
    after_dir = round_dir(run, r)
    t1 = time.perf_counter()
    track_frames(dataclasses.replace(run.tcfg, weights=candidate), run.source, *run.track_camera(), after_dir,
                 progress=run.progress)
    timing[f"track_after_{r}"] = time.perf_counter() - t1
    info["after"] = track_figures(after_dir, run.cut)
    return info, candidate


def _adapt(cfg: AdaptConfig, tcfg: TrackConfig, source, camera, remap, stage: str, progress: bool,
           command: list[str] | None, given_response: tuple = (None, None), camera_file: str | None = None) -> dict:
    """The job inside its stage: track before, cfg.rounds adapt_round's (each from the last round's track and
    weights, the earlier round's files removed), the held-out verdict (worse_reason), _finish."""
    import shutil

    t0 = time.perf_counter()
    T = len(source.t_s)
    run = AdaptRun(cfg, tcfg, source, camera, remap, stage, progress, int(np.floor(T * (1.0 - cfg.held_out))),
                   *smoother_model(tcfg), given_response, camera_file)
    before_dir = os.path.join(stage, "before")
    track_frames(tcfg, source, *run.track_camera(), before_dir, progress=progress)
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
    reason = worse_reason(before, after) or unchanged_track(before_dir, last_dir)
    final = os.path.join(os.path.dirname(stage), "detector.safetensors")  # after/ names what is left, not the stage
    name_run_weights(last_dir, weights, final if reason is None else NOT_KEPT)
    if reason is None:
        os.replace(weights, os.path.join(stage, "detector.safetensors"))
    else:
        os.remove(weights)
    return _finish(cfg, tcfg, source, stage, command, before, after, rounds, timing, t0, reason)


# ---------------------------------------------------------------------------------------------------------
# The job's files


@locks_output("out_dir", "adapt")
def adapt(cfg: AdaptConfig, source, out_dir: str, *, camera=None, progress: bool = False,
          command: list[str] | None = None) -> dict:
    """Adapt the detector in cfg.track.weights ("" the shipped) to the frames of `source` (a FrameSource or a path
    open_source opens at cfg.track.rate_hz) and write out_dir (module doc). camera: a PinholeCamera, a camera TOML
    file or None (the MJCF's chaser_cam: camera_file.default_camera), as track_frames; command: the command line, for the
    model card. Returns the report: {adopted, reason (None when adopted), earlier_weights_kept (not adopted and an
    earlier run's detector.safetensors in out_dir, left as it was with its detector.json), scale_note (one line
    when the edges' scale was not adopted: disagreement; else None), removed_calibration (adopted fine-tuned
    weights: one line naming the base's calibration they no longer carry and what measures it again; else None),
    before, after (track_figures), rounds (per round: labels, fine-tune, calibration), source, timing_s}.
    InputError (one line) when the first part holds fewer than cfg.min_trusted labelled frames; nothing is
    written then (an --out this job made is removed again on any failure or interrupt)."""

    cfg, out_dir = config_arg(cfg, AdaptConfig), path_arg(out_dir, "out_dir")
    source, camera = as_path_or_object(source), as_path_or_object(camera)
    check_out_dir(out_dir, field="out_dir")
    refuse_overlap(out_dir, source if isinstance(source, str) else getattr(source, "path", None))
    check_adapt_folder(out_dir)
    camera_file = camera if isinstance(camera, str) else None
    given_response = read_camera_response(camera) if camera_file else (None, None)
    tcfg, source, camera, remap, _ = prepare_frames(cfg.track, source, camera)
    with made_out_dir(out_dir), staged_folder(out_dir, STALE_OUTPUTS) as stage:  # a failed job's new folders go
        report = _adapt(cfg, tcfg, source, camera, remap, stage, progress, command, given_response, camera_file)
        _replace_dirs(out_dir, stage)
    return report


def check_adapt_folder(out_dir: str) -> None:
    """InputError in one line, before any work, when out_dir holds an entry a finished run replaces (OUTPUTS; the
    RUN_DIRS whole, with all they hold) that no earlier adapt run wrote: without adapt's report.json there, the
    entries are another's (a user's own before/ folder, once removed); in an adapt run's folder, before/ and after/
    are track runs (a folder with track.config.toml written by `envisat track`)."""
    present = [n for n in (*OUTPUTS, *RUN_DIRS) if os.path.lexists(os.path.join(out_dir, n))]
    if not present:
        return
    try:
        with open(os.path.join(out_dir, "report.json"), encoding="utf-8") as fh:
            report = json.load(fh)
        ours = isinstance(report, dict) and {"adopted", "held_out_from_frame", "rounds"} <= set(report)
    except (OSError, ValueError):
        ours = False
    if not ours:
        raise InputError(f"out_dir {out_dir!r} holds {', '.join(present)} but no report.json of an earlier `envisat "
                         "adapt`: not its outputs to replace; move them out or use another folder")
    for d in (d for d in RUN_DIRS if d in present):
        if not written_by(os.path.join(out_dir, d, "track.config.toml"), "track"):
            raise InputError(f"out_dir {out_dir!r} holds {d}/ without the track.config.toml of an `envisat track`: "
                             f"not an earlier adapt run's track to replace; move it out or use another folder")


def _finish(cfg, tcfg, source, stage, command, before, after, rounds, timing, t0, reason) -> dict:
    """Write report.json and the model card detector.json into the stage; the report."""

    import shutil

    for f in os.listdir(stage):
        if f.startswith("round-"):
            p = os.path.join(stage, f)
            shutil.rmtree(p, ignore_errors=True) if os.path.isdir(p) else os.remove(p)
    timing["total"] = time.perf_counter() - t0
    adopted = reason is None
    earlier = os.path.join(os.path.dirname(stage), "detector.safetensors")  # an earlier run's, left where it is
    report = {
        "adopted": adopted,
        "reason": reason,
        "earlier_weights_kept": not adopted and os.path.isfile(earlier),
        "source": {"path": source.path, "kind": source.kind, "frames": len(source.t_s), "size_px": list(source.size_px),
                   "bit_depth": source.bit_depth, "content_sha256": content_sha256(source)},
        "base_weights": weights_name(tcfg.weights),
        "command": command,
        "config": {**to_dict(cfg), "track": job_record(tcfg)},
        "held_out_from_frame": int(np.floor(len(source.t_s) * (1.0 - cfg.held_out))),
        "before": before,
        "after": after,
        "scale_note": (rounds[-1].get("apparent_scale") or {}).get("kept") if rounds else None,
        # what of the base weights' calibration the written weights no longer carry (the first round's removal)
        "removed_calibration": rounds[0].get("removed_calibration") if adopted else None,
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


def _bar(progress: bool, total: int, desc: str, unit: str):
    if not progress:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, mininterval=0.5)


def _close(bar) -> None:
    if bar is not None:
        bar.close()


def _replace_dirs(out_dir: str, stage: str) -> None:
    """Make room for the staged before/ and after/ folders: an earlier run's go to a folder removed at once."""
    import shutil
    import tempfile

    old = [d for d in RUN_DIRS if os.path.isdir(os.path.join(out_dir, d))]
    if old:
        trash = tempfile.mkdtemp(prefix=stage_prefix(), dir=out_dir)
        for d in old:
            os.replace(os.path.join(out_dir, d), os.path.join(trash, d))
        shutil.rmtree(trash, ignore_errors=True)
