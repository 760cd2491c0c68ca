"""`envisat adapt`'s after/ track run named by the weights it leaves (pipelines/adaptation/adapt.py): the run tracked
with the candidate inside the job's stage folder, a file that is gone once the job ends; its records (summary.json,
track.config.toml, est.npz's and det.npz's config_json) name instead RUN_DIR/detector.safetensors where the weights
were adopted, else NOT_KEPT (the candidate's sha256 stays in summary.json's weights_sha256). And the adapted weights'
own record of what they were adapted on (adaptation_record), the frames by content (content_sha256)."""

from __future__ import annotations

import hashlib
import json
import os

import numpy as np

from envisat_pose.io import atomic_write_text, open_npz, save_npz, sha256_file
from envisat_pose.perception.errormodel import ErrorModel
from envisat_pose.perception.weights_keys import COV_SCALE_KEY, ERROR_MODEL_KEY, ERROR_MODEL_KEYS
from envisat_pose.pipelines.common.job_defaults import weights_name

NOT_KEPT = "adapted weights, not kept (report.json says why)"


def name_run_weights(run_dir: str, candidate: str, name: str) -> None:
    """Write `name` where the track run in run_dir records the weights file `candidate` it was tracked with
    (weights_name(candidate): summary.json's weights, track.config.toml's weights, est.npz's config_json
    track.weights, det.npz's config_json weights). A record naming other weights is left as it is."""
    old = weights_name(candidate)
    path = os.path.join(run_dir, "summary.json")
    summary = json.loads(open(path, encoding="utf-8").read())
    if summary.get("weights") == old:
        summary["weights"] = name
        atomic_write_text(path, json.dumps(summary, indent=1, sort_keys=True) + "\n")
    path = os.path.join(run_dir, "track.config.toml")
    lines = open(path, encoding="utf-8").read().split("\n")
    line = f"weights = {json.dumps(old)}"
    if line in lines:
        lines[lines.index(line)] = f"weights = {json.dumps(name)}"
        atomic_write_text(path, "\n".join(lines))
    for file, keys in (("est.npz", ("track", "weights")), ("det.npz", ("weights",))):
        path = os.path.join(run_dir, file)
        with open_npz(path) as npz:
            arrays = {k: npz[k] for k in npz.files}
        config = json.loads(str(arrays["config_json"]))
        inner = config
        for k in keys[:-1]:
            inner = inner[k]
        if inner.get(keys[-1]) == old:
            inner[keys[-1]] = name
            arrays["config_json"] = np.array(json.dumps(config, sort_keys=True))
            save_npz(path, arrays)


def adaptation_record(cfg, tcfg, source, sha: str, held_out_from: int) -> str:
    """The adapted weights' own record of what they were adapted on (their metadata's ADAPTATION_KEY, JSON): the
    frames (path, kind, count, size, content_sha256), the base weights (weights_name and sha256), the first
    held-out frame and the job's fine-tune settings; detector.json beside them holds the figures."""
    fine_tune = {"params": cfg.params, "rounds": cfg.rounds, "seed": cfg.seed}
    if cfg.params != "none":
        fine_tune |= {"steps": cfg.steps, "lr": cfg.lr, "batch_size": cfg.batch_size}
    return json.dumps({"by": "envisat adapt", "source": {
        "path": source.path, "kind": source.kind, "frames": len(source.t_s), "size_px": list(source.size_px),
        "bit_depth": source.bit_depth, "content_sha256": sha}, "base_weights": weights_name(tcfg.weights),
        "base_sha256": sha256_file(tcfg.weights), "held_out_from_frame": int(held_out_from), **fine_tune},
        sort_keys=True)


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


def removed_calibration(base: str, extra: dict, drop: tuple[str, ...], out_weights: str) -> str | None:
    """The line saying what of the base weights' calibration (the file base) the adapted weights no longer carry
    (the keys in drop, measured on the network before the fine-tune, that `extra` does not measure again; its
    error model even where extra holds a new one, which keeps only adapt's scales) and what measures it again on
    out_weights; None when nothing was removed."""
    from envisat_pose.perception.weights import read_metadata

    if not drop:
        return None
    meta = read_metadata(base)
    removed = {k: meta[k] for k in drop if k in meta and (k not in extra or k in ERROR_MODEL_KEYS)}
    parts = []
    if ERROR_MODEL_KEY in removed:
        try:
            model = ErrorModel.from_json(removed[ERROR_MODEL_KEY])
            src = model.source or "data it did not record"  # a calibration's lists every dataset: its start
            what = f"{src if len(src) <= 80 else src[:77] + '...'} ({model.n_frames} frames)"
        except (ValueError, TypeError):
            what = "data it did not record (unreadable)"
        parts.append(f"error model from the earlier calibration removed: measured on sequences of {what} for the "
                     "network before the fine-tune (its frame-to-frame correlation and radial bias; adapt measures "
                     "the covariance and apparent scales only, so the tracker takes the errors as white)")
    if COV_SCALE_KEY in removed:
        parts.append("covariance scale from the earlier calibration removed: too few corners in the labelled "
                     "frames to measure it again (the network's own covariances stand)")
    if not parts:
        return None
    keep = "" if COV_SCALE_KEY in removed else " --keep-scale"
    return "; ".join(parts) + (f"; to measure them again on the adapted weights: envisat calibrate --weights "
                               f"{out_weights} --data SEQUENCE_DIR... --roi labels{keep} --out {out_weights} "
                               "(labelled sequences: envisat generate --mode sequence)")
