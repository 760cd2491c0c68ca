"""Write the model card (models/detector.json) of the shipped detector weights from what the runs recorded.

Usage: python scripts/model_card.py --weights models/detector.safetensors --runs RUN_DIR [RUN_DIR ...]
           --datasets DIR [DIR ...] --evaluation NAME=EVAL.json [NAME=EVAL.json ...] [--commands FILE]
           [--idle RUN_DIR=SECONDS ...] --hardware TEXT --out models/detector.json
       python scripts/model_card.py --refresh models/detector.json --weights models/detector.safetensors
           [--datasets DIR ...] [--evaluation NAME=EVAL.json ...] [--error-model NAME=W.safetensors ...]
           [--runs RUN_DIR ...] [--commands FILE] --out models/detector.json
           (keeps the card's runs and adds the new legs given; rewrites its weights entry from the file's metadata,
           adds the datasets, evaluations and commands given: the metadata written after training, e.g. the error
           model; when the weights changed, the old weights' evaluations move to the history file)

Everything in the card comes from files: each training run's config.json (its exact `envisat train` command, git
hash, torch), state.json (the steps done) and metrics.jsonl (the last epoch's losses); each dataset's manifest
(seed, size, config); the weights file (sha256, size, cov_scale and its calibration record); and `envisat
evaluate`'s JSON per held-out set (the metrics).
`--commands` adds the lines that made the datasets and the calibration, as they were typed.

The card describes the weights it lies beside. What was measured of earlier weights (their evaluations and error
models, under their sha256, oldest first) lives in a file of its own beside it, detector_history.json
(HISTORY_FILE; the card names it under `previous_weights_file`), so the card stays the size of one set of weights.

The card travels: it names a dataset by its folder's name, the generate command its manifest implies and the
sha256 of that manifest; a run by its command and git hash; no absolute path of the machine anywhere (a card that
would hold one is refused, as is a card written from a tree with uncommitted changes: its git hash would not name
the code). `--scrub CARD.json` rewrites an older card's history without paths.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from envisat_pose.io import atomic_write_text, sha256_file  # noqa: E402
from envisat_pose.perception import weights_keys as wk  # noqa: E402
from envisat_pose.perception.weights import read_metadata  # noqa: E402
from envisat_pose.provenance import dataset_ref, find_absolute_paths, manifest_sha256, relative_name, scrub_paths  # noqa: E402
from envisat_pose.shard_reader import load_dataset_manifest  # noqa: E402
from envisat_pose.whole_flags import WholeFlagParser  # noqa: E402

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
HISTORY_FILE = "detector_history.json"  # beside the card: what was measured of the earlier weights
HISTORY_ABOUT = ("What was measured of the detector's earlier weights, oldest first, each under its sha256: the "
                 "card (detector.json, beside this file) describes the current weights only. Written by "
                 "scripts/model_card.py --refresh when the weights change.")


class Refused(Exception):
    """A card that would not travel or not name its code: one line saying why."""


def git_state(repo: str = REPO) -> tuple[str, list[str]]:
    """(HEAD hash, the lines of `git status --porcelain`: empty for a clean tree). Refused where git is not
    installed or the folder is not a git checkout: a card names the commit that made it."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True, check=True)
        st = subprocess.run(["git", "status", "--porcelain"], cwd=repo, capture_output=True, text=True, check=True)
    except FileNotFoundError:
        raise Refused("refused: no git on PATH; a card names the commit that made it (install git)") from None
    except subprocess.CalledProcessError as err:
        raise Refused(f"refused: {repo} is not a git checkout with a commit (git says: "
                      f"{' '.join(err.stderr.split())}); a card names the commit that made it") from None
    return head.stdout.strip(), [line for line in st.stdout.splitlines() if line.strip()]


def require_clean_tree(repo: str = REPO) -> str:
    """The HEAD hash, or Refused when the tree has uncommitted changes."""
    head, dirty = git_state(repo)
    if dirty:
        raise Refused(f"refused: the tree has {len(dirty)} uncommitted change(s) (git status --porcelain: "
                      f"{dirty[0].strip()}{' ...' if len(dirty) > 1 else ''}); commit first, so that the card's "
                      "git hash names the code that made it")
    return head


def scrub(x):
    """Every string in a JSON value with its absolute machine paths replaced by relative names."""
    if isinstance(x, str):
        return scrub_paths(x)
    if isinstance(x, list):
        return [scrub(v) for v in x]
    if isinstance(x, dict):
        return {k: scrub(v) for k, v in x.items()}
    return x


def card_text(card: dict) -> str:
    """The card's JSON, or Refused when an absolute machine path is left in it."""
    text = json.dumps(card, indent=1, sort_keys=False, allow_nan=False, default=lambda x: None) + "\n"
    left = find_absolute_paths(text)
    if left:
        raise Refused(f"refused: the card would hold {len(left)} absolute machine path(s), e.g. {left[0]!r}")
    return text


def run_record(run_dir: str, idle_s: float = 0.0) -> dict:
    """One training run from its folder: its command and each --resume's; its training time, the run's own clock
    over every leg (state.json's time_s; a run from before it was kept: config.json's time to the last checkpoint,
    less idle_s, the seconds it stood stopped before a --resume)."""
    cfg = json.load(open(os.path.join(run_dir, "config.json"), encoding="utf-8"))
    rows = [json.loads(line) for line in open(os.path.join(run_dir, "metrics.jsonl"), encoding="utf-8")]
    last = rows[-1] if rows else {}
    state = json.load(open(os.path.join(run_dir, "state.json"), encoding="utf-8"))
    stopped = state["step"] < cfg["train"]["steps"]
    if isinstance(state.get("time_s"), (int, float)):  # the run's own clock, over every leg (idle not counted)
        wall_s = float(state["time_s"])
    else:  # an older run: from config.json (rewritten by each resume) to its last checkpoint
        wall_s = (os.path.getmtime(os.path.join(run_dir, "checkpoint.safetensors"))
                  - os.path.getmtime(os.path.join(run_dir, "config.json")) - idle_s)
    return {"command": scrub(cfg.get("command")), "git": cfg.get("git"), "torch": cfg.get("torch"),
            "resumes": [{"command": scrub(r.get("command")), "git": r.get("git"), "step": r.get("step")}
                        for r in cfg.get("resumes", [])],
            "device": cfg.get("device"), "init": scrub(cfg.get("init")), "steps_done": state["step"],
            "stopped_early": stopped, "weights_used": "checkpoint.safetensors at step %d" % state["step"],
            "wall_time_s": round(wall_s, 1), "idle_s_excluded": idle_s,
            "last_epoch_losses": {k: last[k] for k in ("loss", "heatmap", "offset", "line", "nll") if k in last},
            "train_config": scrub(cfg.get("train"))}


def generate_command(config: dict, name: str) -> str:
    """The `envisat generate` line a manifest's config implies: its flags, and the keys that differ from the
    default config as the TOML (--config) lines that set them."""
    from envisat_pose.config import to_dict
    from envisat_pose.datagen.generate_config import GenerateConfig, nest_moved_keys

    config = nest_moved_keys(config)  # a dataset written before [random] and [sequence]
    default = to_dict(GenerateConfig())
    line = ["envisat generate"]
    if config.get("mode") != default["mode"]:
        line.append(f"--mode {config.get('mode')}")
    if config.get("mode") == "sequence":
        line.append(f"--scenario {config.get('sequence', {}).get('scenario')}")
    line.append(f"--num-images {config.get('num_images')} --seed {config.get('seed')}")
    if config.get("resolution_px") != default["resolution_px"]:
        line.append(f"--resolution {config.get('resolution_px')}")
    flags = {"mode", "sequence.scenario", "num_images", "seed", "resolution_px", "shard_size"}

    def diff(cur: dict, ref: dict, prefix: str) -> list[str]:
        out = []
        for k in sorted(set(cur) | set(ref)):
            if prefix + k in flags:
                continue
            a, b = cur.get(k), ref.get(k)
            if isinstance(a, dict) and isinstance(b, dict):
                out += diff(a, b, f"{prefix}{k}.")
            elif a != b:
                out.append(f"{prefix}{k} = {json.dumps(a)}")
        return out

    keys = diff(config, default, "")
    if keys:
        line.append("--config CONFIG.toml  # CONFIG.toml: " + "; ".join(keys))
    return " ".join(line)


def dataset_record(path: str) -> dict:
    from envisat_pose.datagen.generate_config import nest_moved_keys

    man = load_dataset_manifest(path)

    c = nest_moved_keys(man.get("config", {}))
    n = sum(int(s.get("count", 0)) for s in man.get("shards", []))
    name = os.path.basename(os.path.normpath(path))
    return {"name": name, "manifest_sha256": manifest_sha256(path), "generate": generate_command(c, name),
            "images": n, "seed": c.get("seed"), "resolution_px": c.get("resolution_px"), "mode": c.get("mode"),
            "scenario": c.get("sequence", {}).get("scenario") if c.get("mode") == "sequence" else None, "storage": c.get("storage"),
            "corruption_model": c.get("corruption", {}).get("model"),
            "earth_probability": c.get("earth_probability")}


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
           "model_config": json.loads(meta[wk.MODEL_CONFIG_KEY]),
           "cov_scale": float(json.loads(meta.get(wk.COV_SCALE_KEY, "1.0"))),
           "cov_calibration": json.loads(meta[wk.COV_CALIBRATION_KEY]) if wk.COV_CALIBRATION_KEY in meta else None}
    for key in (wk.ERROR_MODEL_KEY, wk.ERROR_MODEL_RECORD_KEY, wk.REFINE_FLOOR_KEY, wk.REFINE_CALIBRATION_KEY,
                wk.TARGET_KEY, wk.SIGMA_KEY, wk.SIGMA_RECORD_KEY):  # the last three: a keypoint detector's
        if key in meta:
            out[key] = json.loads(meta[key])
    return out


def external_runs(path: str) -> list[dict]:
    """Training legs run outside `envisat train` (e.g. a harness on a borrowed GPU): a JSON list of records, each
    with at least its command, the git hash of the code it ran, its device and wall_time_s; kept as given, its
    paths scrubbed."""
    runs = json.load(open(path, encoding="utf-8"))
    for r in runs:
        for key in ("command", "git", "device", "wall_time_s"):
            if key not in r:
                raise Refused(f"refused: {path}: a run without {key!r} (expected command, git, device, wall_time_s)")
    return scrub(runs)


def evaluation_record(e: dict) -> dict:
    data = e.get("data")
    name = dataset_ref(data) if data and os.path.isdir(data) else scrub(data)
    if "as_named" in e:  # another target's keypoint detector (`envisat evaluate --target`): its own layout
        metrics = {k: {"all": e[k]["all"], "pose": e[k]["pose"]} for k in ("as_named", "twin_aware") if e.get(k)}
        return {"data": name, "weights": scrub(e.get("weights")), "frames": e.get("frames"),
                "target": scrub(e["target"]),
                "match_px": e.get("match_px"), "metrics": metrics, "per_keypoint": e["as_named"]["per_keypoint"]}
    return {"data": name, "weights": scrub(e.get("weights")), "frames": e.get("frames"), "roi": scrub(e.get("roi")),
            "detect_config": e.get("detect_config"), "metrics": headline(e)}


def idle_seconds(items: list[str]) -> dict[str, float]:
    """--idle RUN_DIR=SECONDS items -> {absolute run folder: seconds}."""
    return {os.path.abspath(k): float(v) for k, _, v in (item.partition("=") for item in items)}


def training_time_s(runs: list[dict]) -> float:
    """Wall seconds of all training runs (a run without a measured time counts 0)."""
    return sum(r["wall_time_s"] or 0.0 for r in runs)


def history_path(card_path: str) -> str:
    """The history file beside a card."""
    return os.path.join(os.path.dirname(os.path.abspath(card_path)), HISTORY_FILE)


def read_history(path: str) -> list[dict]:
    """The earlier weights' records of a history file ([] when there is none yet)."""
    if not os.path.isfile(path):
        return []
    return json.load(open(path, encoding="utf-8"))["previous_weights"]


def history_text(previous: list[dict]) -> str:
    """The history file's JSON (no machine path, as the card)."""
    return card_text({"about": HISTORY_ABOUT, "previous_weights": previous})


def retire_weights(card: dict, previous: list[dict], new_weights: dict) -> tuple[dict, list[dict]]:
    """(card, history) once the card's weights give way to new_weights: when their tensors differ (a new
    training leg), what was measured of the old ones (evaluations, error models) leaves the card for the history,
    under their sha256; weights whose tensors are the card's (only their calibration metadata rewritten) keep
    the card's evaluations. A card that still holds previous_weights inline (written before the history had its
    own file) hands them over first. Neither argument is changed."""
    card = dict(card)
    previous = list(previous) + list(card.pop("previous_weights", []))
    old = card.get("weights", {})
    same = old.get("sha256") == new_weights["sha256"] or old.get("tensors_sha256") == new_weights["tensors_sha256"]
    if not same:
        previous.append({"sha256": old.get("sha256"), "evaluations": card.pop("evaluations", {}),
                         "error_model_measurements": card.pop("error_model_measurements", {})})
    card["weights"] = new_weights
    if previous:
        card["previous_weights_file"] = HISTORY_FILE
    return card, previous


def refresh(a) -> int:
    """--refresh: the card kept, its weights entry rewritten, datasets, evaluations and commands added; the old
    weights' measurements moved to the history file beside the output card when the weights changed
    (retire_weights)."""
    card = json.load(open(a.refresh, encoding="utf-8"))
    hist_in, hist_out = history_path(a.refresh), history_path(a.out)
    card, previous = retire_weights(card, read_history(hist_in), weights_record(a.weights))
    idle = idle_seconds(a.idle)
    for r in a.runs or []:  # new training legs
        card.setdefault("training_runs", []).append(run_record(r, idle.get(os.path.abspath(r), 0.0)))
    for path in a.external_runs or []:  # legs trained outside `envisat train`, as their own record says
        card.setdefault("training_runs", []).extend(external_runs(path))
    if a.hardware:
        card["hardware"] = a.hardware
    card["training_time_s"] = training_time_s(card.get("training_runs", []))
    known = {(d.get("name"), d.get("manifest_sha256")) for d in card.get("datasets", [])}
    for d in a.datasets or []:
        rec = dataset_record(d)
        if (rec["name"], rec["manifest_sha256"]) not in known:
            card.setdefault("datasets", []).append(rec)
    for item in a.evaluation or []:
        name, _, path = item.partition("=")
        card.setdefault("evaluations", {})[name] = evaluation_record(json.load(open(path, encoding="utf-8")))
    for item in a.error_model or []:
        name, _, path = item.partition("=")
        meta = read_metadata(path)
        card.setdefault("error_model_measurements", {})[name] = {
            "error_model": json.loads(meta[wk.ERROR_MODEL_KEY]), "record": json.loads(meta[wk.ERROR_MODEL_RECORD_KEY])}
    if a.commands:
        card.setdefault("commands", []).extend(
            scrub(open(a.commands, encoding="utf-8").read().strip().splitlines()))
    card["card_git"] = a.git
    text = card_text(card)
    if previous:
        atomic_write_text(hist_out, history_text(previous))
        print(f"wrote {hist_out}")
    atomic_write_text(a.out, text)
    print(f"wrote {a.out}")
    return 0


def command_for(dataset: dict, commands: list[str]) -> str | None:
    """The card's recorded `envisat generate` line that made an old dataset record (by its seed), scrubbed: a
    line that starts with it, else the generate command quoted in a line's comment, else a line that names the
    seed as '(and N)' with its seed replaced."""
    seed = dataset.get("seed")
    lines = [scrub_paths(c).strip() for c in commands]
    for c in lines:
        if c.startswith("envisat generate") and (f"--seed {seed} " in c + " " or f"seed = {seed}," in c):
            return c
    for c in lines:
        i = c.find("envisat generate", 1)
        if i > 0 and f"--seed {seed} " in c[i:] + " ":
            return c[i:].rstrip(")")
    for c in lines:
        if c.startswith("envisat generate") and f"(and {seed})" in c:
            cmd = c.split("#", 1)[0]
            recorded = re.search(r"--seed (\d+)", cmd).group(1)
            return re.sub(recorded, str(seed), cmd).strip() + f"  # as recorded: {c}"
    return None


def scrub_card(a) -> int:
    """--scrub: an older card rewritten without machine paths: its datasets named (with the generate line the
    card recorded for them; the manifests' sha256 were not recorded then), every string scrubbed; with --weights,
    the weights' metadata scrubbed the same way (the tensors untouched) and the card's weights entry rewritten."""
    card = json.load(open(a.scrub, encoding="utf-8"))
    commands = card.get("commands", [])
    datasets = []
    for d in card.get("datasets", []):
        if "path" in d:
            d = dict(d)
            path = d.pop("path")
            d = {"name": relative_name(path), "manifest_sha256": d.pop("manifest_sha256", None),
                 "generate": command_for(d, commands), **d}
            if d["manifest_sha256"] is None:
                d["manifest_sha256_note"] = "not recorded when this dataset was made (before the card travelled)"
        datasets.append(d)
    card["datasets"] = datasets
    if a.weights:  # the weights' metadata scrubbed too (the tensors untouched), and the card's entry rewritten
        from envisat_pose.perception.weights import with_metadata

        meta = read_metadata(a.weights)
        with_metadata(a.weights, a.weights, {k: scrub_paths(v) for k, v in meta.items() if scrub_paths(v) != v})
        card["weights"] = weights_record(a.weights)
    card = scrub(card)
    card["card_git"] = a.git
    atomic_write_text(a.out, card_text(card))
    print(f"wrote {a.out}")
    return 0


def main() -> int:
    p = WholeFlagParser(description=__doc__.splitlines()[0])
    p.add_argument("--weights")
    p.add_argument("--refresh", metavar="CARD.json", help="update this card instead of writing one from the runs")
    p.add_argument("--scrub", metavar="CARD.json", help="rewrite this older card without machine paths")
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
    p.add_argument("--external-runs", nargs="+", metavar="RUNS.json",
                   help="--refresh: training legs run outside `envisat train` (a JSON list: command, git, device, "
                   "wall_time_s, ...)")
    p.add_argument("--hardware")
    p.add_argument("--out", required=True)
    a = p.parse_args()
    try:
        a.git = require_clean_tree()
        if a.scrub:
            return scrub_card(a)
        if not a.weights:
            p.error("--weights is required")
        if a.refresh:
            return refresh(a)
        return write_card(a, p)
    except Refused as err:
        print(f"model_card: {err}", file=sys.stderr)
        return 2


def write_card(a, p) -> int:
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
        "commands": scrub(open(a.commands, encoding="utf-8").read().strip().splitlines()) if a.commands else [],
        "evaluations": {name: evaluation_record(e) for name, e in evaluations.items()},
        "card_git": a.git,
    }
    card["training_time_s"] = training_time_s(card["training_runs"])
    atomic_write_text(a.out, card_text(card))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
