"""Write the model card (models/detector.json) of the shipped detector weights from what the runs recorded.

Usage: python scripts/model_card.py --weights models/detector.safetensors --runs RUN_DIR [RUN_DIR ...]
           --datasets DIR [DIR ...] --evaluation NAME=EVAL.json [NAME=EVAL.json ...] [--commands FILE]
           [--idle RUN_DIR=SECONDS ...] --hardware TEXT --out models/detector.json
       python scripts/model_card.py --refresh models/detector.json --weights models/detector.safetensors
           [--datasets DIR ...] [--evaluation NAME=EVAL.json ...] [--error-model NAME=W.safetensors ...]
           [--runs RUN_DIR ...] [--commands FILE] --out models/detector.json
           (keeps the card's runs and adds the new legs given; rewrites its weights entry from the file's metadata,
           adds the datasets, evaluations and commands given: the metadata written after training, e.g. the error
           model; when the weights changed, the old weights' evaluations move to previous_weights)

Everything in the card comes from files: each training run's config.json (its exact `envisat train` command, git
hash, torch), state.json (the steps done) and metrics.jsonl (the last epoch's losses); each dataset's manifest
(seed, size, config); the weights file (sha256, size, cov_scale and its calibration record); and `envisat
evaluate`'s JSON per held-out set (the metrics).
`--commands` adds the lines that made the datasets and the calibration, as they were typed.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from envisat_pose.io import atomic_write_text, sha256_file  # noqa: E402
from envisat_pose.perception.weights import read_metadata  # noqa: E402


def run_record(run_dir: str, idle_s: float = 0.0) -> dict:
    """One training run from its folder; idle_s: seconds it stood stopped before a --resume, left out of its
    wall time (and recorded)."""
    cfg = json.load(open(os.path.join(run_dir, "config.json"), encoding="utf-8"))
    rows = [json.loads(line) for line in open(os.path.join(run_dir, "metrics.jsonl"), encoding="utf-8")]
    last = rows[-1] if rows else {}
    state = json.load(open(os.path.join(run_dir, "state.json"), encoding="utf-8"))
    stopped = state["step"] < cfg["train"]["steps"]
    return {"command": cfg.get("command"), "git": cfg.get("git"), "torch": cfg.get("torch"),
            "device": cfg.get("device"), "init": cfg.get("init"), "steps_done": state["step"],
            "stopped_early": stopped, "weights_used": "checkpoint.safetensors at step %d" % state["step"],
            # from the run folder's creation (config.json) to its last checkpoint
            "wall_time_s": round(os.path.getmtime(os.path.join(run_dir, "checkpoint.safetensors"))
                                 - os.path.getmtime(os.path.join(run_dir, "config.json")) - idle_s, 1),
            "idle_s_excluded": idle_s,
            "last_epoch_losses": {k: last[k] for k in ("loss", "heatmap", "offset", "line", "nll") if k in last},
            "train_config": cfg.get("train")}


def dataset_record(path: str) -> dict:
    man = json.load(open(os.path.join(path, "manifest.json"), encoding="utf-8"))
    c = man.get("config", {})
    n = sum(int(s.get("count", 0)) for s in man.get("shards", []))
    return {"path": os.path.abspath(path), "images": n, "seed": c.get("seed"),
            "resolution_px": c.get("resolution_px"), "mode": c.get("mode"), "storage": c.get("storage"),
            "corruption_model": c.get("corruption", {}).get("model")}


def headline(evaluation: dict) -> dict:
    """The floors' numbers per group, detector next to the classical peers."""
    out = {}
    for group, per in evaluation["groups"].items():
        if not per.get("detector", {}).get("frames"):
            continue
        row = {}
        for method, s in per.items():
            if not s.get("frames"):
                continue
            row[method] = {"frames": s["frames"], "median_px": s["errors"]["all"]["median_px"],
                           "p95_px": s["errors"]["all"]["p95_px"], "pck_2px": s["pck_2px"], "pck_5px": s["pck_5px"],
                           "swap_rate_strict": s["swap_rate_strict"], "ambiguous_share": s["ambiguous_share"]}
            if "visibility" in s:
                row[method]["visibility"] = s["visibility"]
            if "calibration" in s:
                row[method]["mean_nees"] = s["calibration"]["mean_nees"]
            if "pose" in s:
                row[method]["pose"] = s["pose"]
            if "bias" in s:
                row[method]["bias"] = s["bias"]
        out[group] = row
    return out


def tensors_sha256(path: str) -> str:
    """sha256 of a safetensors file's tensors alone (their header entries, sorted, and the data bytes), not of its
    metadata: the same for weights whose calibration alone was rewritten."""
    import hashlib
    import struct

    with open(path, "rb") as fh:
        (n,) = struct.unpack("<Q", fh.read(8))
        header = json.loads(fh.read(n))
        header.pop("__metadata__", None)
        h = hashlib.sha256(json.dumps(header, sort_keys=True).encode())
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def weights_record(path: str) -> dict:
    """The card's weights entry: file, sha256, size, model config and the metadata written after training
    (cov_scale and its calibration; the error model and its record when present)."""
    meta = read_metadata(path)
    out = {"file": os.path.basename(path), "sha256": sha256_file(path), "tensors_sha256": tensors_sha256(path),
           "bytes": os.path.getsize(path),
           "model_config": json.loads(meta["model_config"]),
           "cov_scale": float(json.loads(meta.get("cov_scale", "1.0"))),
           "cov_calibration": json.loads(meta["cov_calibration"]) if "cov_calibration" in meta else None}
    for key in ("error_model", "error_model_record", "refine_cov_floor_px2", "refine_cov_calibration"):
        if key in meta:
            out[key] = json.loads(meta[key])
    return out


def evaluation_record(e: dict) -> dict:
    return {"data": e.get("data"), "frames": e.get("frames"), "roi": e.get("roi"),
            "detect_config": e.get("detect_config"), "metrics": headline(e)}


def idle_seconds(items: list[str]) -> dict[str, float]:
    """--idle RUN_DIR=SECONDS items -> {absolute run folder: seconds}."""
    return {os.path.abspath(k): float(v) for k, _, v in (item.partition("=") for item in items)}


def training_time_s(runs: list[dict]) -> float:
    """Wall seconds of all training runs (a run without a measured time counts 0)."""
    return sum(r["wall_time_s"] or 0.0 for r in runs)


def refresh(a) -> int:
    """--refresh: the card kept, its weights entry rewritten, datasets, evaluations and commands added. Weights
    whose tensors are the card's (only their calibration metadata rewritten) keep the card's evaluations."""
    card = json.load(open(a.refresh, encoding="utf-8"))
    weights = weights_record(a.weights)
    old = card.get("weights", {})
    same = old.get("sha256") == weights["sha256"] or old.get("tensors_sha256") == weights["tensors_sha256"]
    if not same:
        # other weights (a new training leg): what was measured of the old ones stays, under their sha256
        card.setdefault("previous_weights", []).append(
            {"sha256": card.get("weights", {}).get("sha256"), "evaluations": card.pop("evaluations", {}),
             "error_model_measurements": card.pop("error_model_measurements", {})})
    card["weights"] = weights
    idle = idle_seconds(a.idle)
    for r in a.runs or []:  # new training legs
        card.setdefault("training_runs", []).append(run_record(r, idle.get(os.path.abspath(r), 0.0)))
    card["training_time_s"] = training_time_s(card.get("training_runs", []))
    known = {d["path"] for d in card.get("datasets", [])}
    card.setdefault("datasets", []).extend(dataset_record(d) for d in a.datasets or []
                                           if os.path.abspath(d) not in known)
    for item in a.evaluation or []:
        name, _, path = item.partition("=")
        card.setdefault("evaluations", {})[name] = evaluation_record(json.load(open(path, encoding="utf-8")))
    for item in a.error_model or []:
        name, _, path = item.partition("=")
        meta = read_metadata(path)
        card.setdefault("error_model_measurements", {})[name] = {
            "error_model": json.loads(meta["error_model"]), "record": json.loads(meta["error_model_record"])}
    if a.commands:
        card.setdefault("commands", []).extend(open(a.commands, encoding="utf-8").read().strip().splitlines())
    atomic_write_text(a.out, json.dumps(card, indent=1, sort_keys=False, allow_nan=False,
                                        default=lambda x: None) + "\n")
    print(f"wrote {a.out}")
    return 0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--weights", required=True)
    p.add_argument("--refresh", metavar="CARD.json", help="update this card instead of writing one from the runs")
    p.add_argument("--runs", nargs="+")
    p.add_argument("--datasets", nargs="+")
    p.add_argument("--evaluation", nargs="+", metavar="NAME=EVAL.json",
                   help="envisat evaluate's JSON per held-out set, each under a name")
    p.add_argument("--error-model", nargs="+", metavar="NAME=W.safetensors",
                   help="--refresh: error models measured into other weights files (e.g. another ROI mode), "
                   "kept in the card under error_model_measurements")
    p.add_argument("--commands", help="text file: the commands that made the datasets, the calibration, the card")
    p.add_argument("--idle", nargs="*", default=[], metavar="RUN_DIR=SECONDS",
                   help="time a run stood stopped before it was resumed, left out of its wall time")
    p.add_argument("--hardware")
    p.add_argument("--out", required=True)
    a = p.parse_args()
    if a.refresh:
        return refresh(a)
    for name in ("runs", "datasets", "evaluation", "hardware"):
        if not getattr(a, name):
            p.error(f"--{name} is required without --refresh")
    idle = idle_seconds(a.idle)
    evaluations = {}
    for item in a.evaluation:
        name, _, path = item.partition("=")
        evaluations[name] = json.load(open(path, encoding="utf-8"))
    card = {
        "weights": weights_record(a.weights),
        "hardware": a.hardware,
        "training_runs": [run_record(r, idle.get(os.path.abspath(r), 0.0)) for r in a.runs],
        "datasets": [dataset_record(d) for d in a.datasets],
        "commands": open(a.commands, encoding="utf-8").read().strip().splitlines() if a.commands else [],
        "evaluations": {name: evaluation_record(e) for name, e in evaluations.items()},
    }
    card["training_time_s"] = training_time_s(card["training_runs"])
    atomic_write_text(a.out, json.dumps(card, indent=1, sort_keys=False, allow_nan=False,
                                        default=lambda x: None) + "\n")
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
