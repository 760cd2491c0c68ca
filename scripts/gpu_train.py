"""One leg of detector training on a borrowed GPU machine: fresh data on every core, then `envisat
train` from the last leg's weights for what is left of the time, the results written where they come back.

The data of a leg (seeds 1,000,000 + 1,000 x leg + chunk: never an evaluation seed, new every leg; the looks'
texture, appearance, Earth and camera seeds 2,000,000 + 10 x leg + 0..3 move with the leg too), generated in rounds
until --gen-s is spent. A round runs its chunks at once, each an `envisat generate` with its share of the cores,
sized to its time at the rate the last round measured (leg 1, one `generate` per chunk in turn, spent 140 of its
163 s starting workers: about 10 s a chunk). Each round, in these proportions:
- random views of the default generate config at 1024 px (the held-out sets' look), the Earth behind in 40 %;
- random views at 512, 768, 1024, 1536 and 2048 px with the Earth behind the target in 35-50 % of them;
- the space camera at every severity: uncorrupted, a benign camera, the default ranges and a harsh one, and the
  paper's per-kind corruptions (severities drawn per image);
- wider looks than the factory's defaults (materials, brightness, sun intensity, texture sets, more backlit
  views) on all but the default chunk; the trainer adds gain, contrast, gamma, blur, glare and noise;
- frames of every named scenario (sequence mode, 1024 px, the Earth wherever it reaches the image; appearance
  off in even rounds as the closed loop renders it, on in odd ones).
Then `envisat train --init W --workers N --bf16 --time-budget-s T` into a run folder, and into --out:
detector.safetensors, leg.json (this leg's number, data, init hash, the end line), metrics.jsonl,
config.json, generate.json (every chunk's command, images and seconds), and candidates.json: the leg's own check,
bench/detector_candidates.py on 60 held-out views each of seeds 7171, 7272 and 7373 (the Earth behind), init
against the leg's weights, so that a leg that made things worse is seen before its weights travel on.

    python3 scripts/gpu_train.py --init W --leg-file L --out DIR --deadline-s EPOCH [--device cuda] ...
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time

from envisat_pose.whole_flags import WholeFlagParser

SEED_BASE = 1_000_000  # training data seeds: evaluation sets use seeds far below
SEED_LEG = 1_000
LOOK_SEED_BASE = 2_000_000  # the looks' seeds (textures, appearance, Earth, camera pattern): 10 per leg
IMAGE_COST = {512: 0.3, 768: 0.6, 1024: 1.0, 1536: 2.2, 2048: 4.0}  # render + write, relative to 1024 px
IMAGES_PER_S = 170.0  # 1024-px images/s, 16 cores with EGL, start-up apart (2026-11-27, an H200 machine: 165-176)
RENDERER_MB = 650.0  # host memory of one SceneRenderer with a 12-texture set and the Earth (OSMesa, 512-2048 px)
MEMORY_SHARE = 0.6  # of the available memory, for the online leg's renderers
START_S = 12.0  # a round's start-up: every generate process's workers build the model and the looks
FIRST_SHARE = 0.6  # the first round takes this share of the generation time, at the expected rate
MIN_ROUND_S = 30.0
GRACE_S = 15.0  # a chunk still running this long after the generation time is left out
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# the leg's own check, init against the leg's weights: held-out random views of seeds no leg trains on (and not
# the README's test seeds 8181, 9191, 8282), the default config and the Earth behind the target in every view
VALIDATION = (("v7171", 7171, None), ("v7272", 7272, None),
              ("e7373", 7373, os.path.join(ROOT, "bench", "configs", "earth_eval.toml")))

WIDE_LOOKS = {
    "random": {"backlit_probability": 0.25, "sun_phase_max_deg": 130.0},
    "appearance": {"specular": [0.0, 1.0], "shininess": [0.0, 1.0], "reflectance": [0.0, 0.3],
                   "brightness": [0.4, 1.9], "texture_set_size": 12},  # 32 passes MuJoCo's 1000 materials
    "lighting": {"sun_intensity": [0.5, 2.6], "earth_albedo": [0.2, 0.5]},
}
CAMERAS = {  # the space camera (datagen/sensor.py) at every severity
    "clean": {"corruption": {k: "none" for k in ("exposure", "motion_blur", "gaussian_blur", "shot_noise",
                                                 "gaussian_noise")}},
    "benign": {"corruption": {"sensor": {"exposure_s": [0.001, 0.005], "read_noise_e": [2.0, 5.0],
                                         "dark_current_e_per_s": [10.0, 50.0], "psf_sigma_px_1024": [0.3, 0.6],
                                         "white_fill": [0.5, 1.0], "blooming_decay_px": [1.0, 2.0],
                                         "vignetting_cos_power": [0.0, 1.0]}}},
    "harsh": {"corruption": {"sensor": {"exposure_s": [0.01, 0.05], "read_noise_e": [10.0, 40.0],
                                        "dark_current_e_per_s": [200.0, 2000.0], "psf_sigma_px_1024": [0.8, 2.5],
                                        "white_fill": [1.0, 3.0], "blooming_decay_px": [3.0, 12.0],
                                        "vignetting_cos_power": [2.0, 6.0], "f_number": [8.0, 16.0],
                                        "full_well_e": [5000.0, 15000.0], "prnu_sigma": 0.03}}},
    "paper": {"corruption": {"model": "paper"}},
}


def merge(a: dict, b: dict) -> dict:
    out = dict(a)
    for k, v in b.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def leg_seeds(leg: int) -> dict:
    """The look seeds of a leg (textures, appearance draws, Earth textures, the camera's fixed pattern)."""
    s = LOOK_SEED_BASE + 10 * leg
    return {"appearance": {"texture_seed": s, "seed": s + 1}, "earth_seed": s + 2,
            "corruption": {"sensor": {"camera_seed": s + 3}}}


def round_chunks(leg: int, round_index: int, scenarios: list[str]) -> list[dict]:
    """The chunks of one round in their proportions: {"name", "images", "resolution", "config" (GenerateConfig
    keys)}; the round is sized to its time later (sized_round), the seeds given then."""
    base = leg_seeds(leg)
    wide = merge(base, WIDE_LOOKS)
    chunks = [
        {"name": "random-1024-default", "images": 2000, "resolution": 1024,
         "config": merge(base, {"earth_probability": 0.4})},
        {"name": "random-512-wide", "images": 800, "resolution": 512,
         "config": merge(wide, {"earth_probability": 0.5})},
        {"name": "random-768-paper", "images": 400, "resolution": 768,
         "config": merge(merge(wide, CAMERAS["paper"]), {"earth_probability": 0.35})},
        {"name": "random-1536-wide", "images": 300, "resolution": 1536,
         "config": merge(wide, {"earth_probability": 0.4})},
        {"name": "random-2048-wide", "images": 150, "resolution": 2048,
         "config": merge(wide, {"earth_probability": 0.4})},
    ]
    for cam in ("clean", "benign", "harsh"):
        chunks.append({"name": f"random-1024-{cam}", "images": 300, "resolution": 1024,
                       "config": merge(merge(wide, CAMERAS[cam]), {"earth_probability": 0.4})})
    sequences = [{"name": f"sequence-{name}", "images": 120, "resolution": 1024, "scenario": name,
                  "config": merge(base, {"mode": "sequence", "sequence": {"scenario": name, "frame_dt_s": 2.0},
                                         "earth_probability": 1.0,
                                         "appearance": {"enabled": round_index % 2 == 1}})} for name in scenarios]
    # interleaved: the seeds alternate between the kinds
    mixed = []
    for i in range(max(len(chunks), len(sequences))):
        mixed += chunks[i:i + 1] + sequences[i:i + 1]
    return mixed


def to_toml(data: dict, prefix: str = "") -> str:
    """A small TOML writer for the chunk configs (numbers, strings, booleans, lists, tables)."""
    def value(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return repr(v)

    lines = [f"{k} = {value(v)}" for k, v in data.items() if not isinstance(v, dict)]
    for k, v in data.items():
        if isinstance(v, dict):
            lines += ["", f"[{prefix}{k}]", to_toml(v, f"{prefix}{k}.").strip()]
    return "\n".join(lines) + "\n"


def chunk_command(chunk: dict, seed: int, workers: int, work: str) -> tuple[list[str], str]:
    """The `envisat generate` command of one chunk (its config written beside its folder) and the folder."""
    folder = os.path.join(work, f"d{seed}-{chunk['name']}")
    toml = folder + ".toml"
    with open(toml, "w", encoding="utf-8") as fh:
        fh.write(to_toml(chunk["config"]))
    shard = max(1, min(64, chunk["images"] // max(workers, 1)))
    return [sys.executable, "-m", "envisat_pose.app.cli", "generate", "--config", toml, "--num-images",
            str(chunk["images"]), "--shard-size", str(shard), "--resolution", str(chunk["resolution"]), "--seed",
            str(seed), "--workers", str(workers), "--out", folder, "--quiet"], folder


def load_of(chunk: dict) -> float:
    """A chunk's rendering load in 1024-px image equivalents."""
    return chunk["images"] * IMAGE_COST[chunk["resolution"]]


def sized_round(chunks: list[dict], seconds: float, rate: float, cores: int) -> list[dict]:
    """The round's chunks scaled so their load takes about `seconds` at `rate` (1024-px images/s on all the
    cores) after the start-up, each given workers in proportion to its load (at least one)."""
    total = sum(load_of(c) for c in chunks)
    factor = max(0.0, seconds - START_S) * rate / total
    out = []
    for c in chunks:
        c = dict(c, images=max(2, int(round(c["images"] * factor))))
        out.append(dict(c, workers=max(1, int(round(cores * load_of(c) / (total * factor or 1.0))))))
    return out


def run_round(chunks: list[dict], first_seed: int, work: str, deadline: float, log) -> list[dict]:
    """Every chunk of a round at once, each its own `envisat generate` with its share of the cores (one start-up
    per round, not per chunk: a start-up costs every worker about 10 s). A chunk still running at the deadline
    is stopped and left out (generate writes its manifest last). Returns the chunks made, with their seconds."""
    procs = []
    for i, chunk in enumerate(chunks):
        cmd, folder = chunk_command(chunk, first_seed + i, chunk["workers"], work)
        log.write("$ " + " ".join(cmd) + "\n")
        log.flush()
        procs.append((chunk, first_seed + i, cmd, folder, time.time(),
                      subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)))
    ended = {}  # index: (return code, seconds), each chunk timed to its own end
    while len(ended) < len(procs) and time.time() < deadline:
        for i, (_, _, _, _, t0, proc) in enumerate(procs):
            if i not in ended and proc.poll() is not None:
                ended[i] = (proc.returncode, time.time() - t0)
        time.sleep(0.2)
    made = []
    for i, (chunk, seed, cmd, folder, _, proc) in enumerate(procs):
        if i not in ended:
            proc.kill()
            proc.wait()
            print(f"chunk {chunk['name']} seed {seed}: stopped at the deadline, left out", flush=True)
            continue
        rc, sec = ended[i]
        if rc != 0:
            raise SystemExit(f"generate failed: {' '.join(cmd)} (see the log)")
        made.append({"name": chunk["name"], "seed": seed, "images": chunk["images"],
                     "resolution": chunk["resolution"], "workers": chunk["workers"], "seconds": round(sec, 1),
                     "folder": folder, "config": chunk["config"],
                     "command": "envisat generate " + " ".join(
                         os.path.basename(c) if c in (folder + ".toml", folder) else c for c in cmd[4:])})
        print(f"chunk {chunk['name']} seed {seed}: {chunk['images']} images, {chunk['workers']} workers, "
              f"{sec:.1f} s", flush=True)
    return made


def generate(work: str, leg: int, scenarios: list[str], gen_s: float, rate: float, cores: int) -> list[dict]:
    """Rounds of chunks until gen_s is spent: the first sized to FIRST_SHARE of it at the expected rate, the
    next ones to what is left at the rate the last round measured (no round under MIN_ROUND_S). Returns the
    chunks made."""
    t0 = time.time()
    made, r, k = [], 0, 0
    log = open(os.path.join(work, "commands.log"), "a", encoding="utf-8")
    while True:
        left = gen_s - (time.time() - t0)
        if made and left < MIN_ROUND_S:
            return made
        if r and k + len(round_chunks(leg, r, scenarios)) > SEED_LEG:
            return made  # the leg's block of seeds is used up
        share = FIRST_SHARE if r == 0 else 0.9
        chunks = sized_round(round_chunks(leg, r, scenarios), max(left * share, MIN_ROUND_S), rate, cores)
        tr = time.time()
        new = run_round(chunks, SEED_BASE + SEED_LEG * leg + k, work, t0 + gen_s + GRACE_S, log)
        k += len(chunks)
        made += new
        sec = time.time() - tr
        rate = max(sum(load_of(c) for c in new) / max(sec - START_S, 1.0), 1e-3)
        print(f"round {r}: {sum(c['images'] for c in new)} images in {len(new)} chunks, {sec:.0f} s "
              f"({rate:.0f} 1024-px images/s after start-up)", flush=True)
        r += 1


def start_validation(work: str, images: int, log) -> list[tuple[str, str, subprocess.Popen]]:
    """Generate the validation sets in the background (3 workers each), beside the first round."""
    procs = []
    for name, seed, config in VALIDATION:
        folder = os.path.join(work, f"val-{name}")
        cmd = [sys.executable, "-m", "envisat_pose.app.cli", "generate", "--num-images", str(images),
               "--seed", str(seed), "--workers", "3", "--out", folder, "--quiet"] + (
                   ["--config", config] if config else [])
        log.write("$ " + " ".join(cmd) + "\n")
        log.flush()
        procs.append((name, folder, subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)))
    return procs


def validate(procs, init: str, weights: str, out_json: str, device: str, deadline: float) -> str | None:
    """bench/detector_candidates.py on the validation sets, init against the leg's weights; None when it
    cannot finish before the deadline (the weights matter more than their check)."""
    sets = []
    for name, folder, proc in procs:
        try:
            if proc.wait(timeout=max(1.0, deadline - time.time())) == 0:
                sets.append(f"{name}={folder}")
        except subprocess.TimeoutExpired:
            proc.kill()
    if not sets:
        return None
    cmd = [sys.executable, os.path.join(ROOT, "bench", "detector_candidates.py"), "--weights", f"init={init}",
           f"leg={weights}", "--data", *sets, "--device", device,
           "--threads", "4", "--out", out_json]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=max(1.0, deadline - time.time()))
    except subprocess.TimeoutExpired:
        return None
    return proc.stdout if proc.returncode == 0 else None


def render_workers(looks_path: str, cores: int) -> int:
    """Renderer processes for an online leg: the cores less two, fewer where memory would not hold every
    worker's renderers (one per resolution and texture set among the looks, ~RENDERER_MB each, built as the looks
    first need them) within MEMORY_SHARE of the memory available."""
    from envisat_pose.pipelines.detector.look_mix import read_looks, renderer_key

    keys = len({renderer_key(look.generate) for look in read_looks(looks_path)})
    available_mb = cores * 8000.0
    try:
        with open("/proc/meminfo", encoding="utf-8") as fh:
            available_mb = next(int(line.split()[1]) / 1024 for line in fh if line.startswith("MemAvailable:"))
    except (OSError, StopIteration, ValueError):
        pass
    fit = int(MEMORY_SHARE * available_mb / (keys * RENDERER_MB))
    workers = max(1, min(cores - 2, fit))
    print(f"online: {keys} renderers a worker (~{keys * RENDERER_MB / 1000:.1f} GB), {available_mb / 1000:.0f} GB "
          f"available: {workers} renderer workers", flush=True)
    return workers


def online_looks(work: str, leg: int, scenarios: list[str]) -> str:
    """The looks of an online leg (a looks file for `envisat train --looks`): the offline recipe's mix, each chunk
    of a round a look weighted by its images (resolutions, cameras, wide looks, the Earth), every scenario's
    sequences twice at half weight (appearance off, as the closed loop renders it, and on), each look seeded
    with the leg's data seeds in turn (SEED_BASE + SEED_LEG x leg + its index)."""
    from envisat_pose.config import from_dict
    from envisat_pose.datagen.generate_config import GenerateConfig
    from envisat_pose.pipelines.detector.look_mix import WeightedLook, looks_toml

    chunks = round_chunks(leg, 0, scenarios)
    chunks += [dict(c, name=c["name"] + "-appearance") for c in round_chunks(leg, 1, scenarios) if "scenario" in c]
    looks = []
    for j, c in enumerate(chunks):
        sequence = "scenario" in c
        cfg = merge(c["config"], {"resolution_px": c["resolution"], "seed": SEED_BASE + SEED_LEG * leg + j})
        if sequence:
            cfg["num_images"] = c["images"]
        looks.append(WeightedLook(c["name"], from_dict(GenerateConfig, cfg, c["name"]),
                          c["images"] / 2 if sequence else c["images"]))
    path = os.path.join(work, "online_looks.toml")
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(looks_toml(looks))
    return path


def start_args(init: str | None, backbone: str | None) -> list[str]:
    """`envisat train`'s arguments for where a leg's network starts: the init weights, or (a fresh --target leg)
    another detector's backbone ('none': from scratch), or nothing (envisat train's default)."""
    if init:
        return ["--init", init]
    return ["--backbone", backbone] if backbone else []


def main() -> int:
    ap = WholeFlagParser(description=__doc__.splitlines()[0])
    ap.add_argument("--init", help="weights to start from (required but with --target, whose leg may start fresh)")
    ap.add_argument("--target", help="another target's MJCF file: train its keypoint detector (envisat train "
                    "--target: online, the target's default look; no held-out check, which is ENVISAT's)")
    ap.add_argument("--backbone", help="with --target and no --init: the network starts from this detector's "
                    "backbone (envisat train --backbone; 'shipped': ENVISAT's, 'none': from scratch)")
    ap.add_argument("--leg-file", help="leg.json of the init weights (their leg number; none: leg 0 before)")
    ap.add_argument("--out", required=True, help="folder whose files come back")
    ap.add_argument("--work", default="/tmp/gpu-leg", help="scratch folder (data, run)")
    ap.add_argument("--deadline-s", type=float, required=True, help="epoch seconds by which everything is written")
    ap.add_argument("--gen-s", type=float, default=170.0, help="seconds of generation")
    ap.add_argument("--rate", type=float, default=IMAGES_PER_S,
                    help="expected 1024-px images/s on all the cores, to size the first round (dry runs: 1)")
    ap.add_argument("--gen-workers", type=int, default=os.cpu_count())
    ap.add_argument("--workers", type=int, default=max(0, (os.cpu_count() or 2) - 2))
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--batch-size", type=int, default=64)
    ap.add_argument("--lr", type=float, default=1.5e-3)
    ap.add_argument("--no-bf16", action="store_true")
    ap.add_argument("--reserve-s", type=float, default=25.0, help="kept for the train process's start and the copy")
    ap.add_argument("--validate-images", type=int, default=60, help="views in each validation set")
    ap.add_argument("--validate-s", type=float, default=50.0,
                    help="kept for the leg's check of its weights against init on held-out views (0: none)")
    ap.add_argument("--scenarios", nargs="*", help="named scenarios (default: all)")
    ap.add_argument("--online", action="store_true",
                    help="train on frames rendered as training goes (envisat train --online --looks: the offline "
                    "recipe's mix of looks, --render-workers = the cores less two, K = --uses-per-frame) instead "
                    "of generating shards first; the rate constant, then a cooldown; the pre-cooldown weights and "
                    "the moving average come back beside the last ones")
    ap.add_argument("--uses-per-frame", type=int, default=8)
    args = ap.parse_args()
    if args.init is None and args.target is None:
        ap.error("--init is required (but with --target)")
    if args.backbone and (args.init or not args.target):
        ap.error("--backbone starts a fresh --target leg: not with --init, only with --target")
    if args.target:
        args.online, args.validate_s = True, 0.0
    from envisat_pose import named_scenarios
    from envisat_pose.io import sha256_file

    prev = 0
    if args.leg_file and os.path.isfile(args.leg_file):
        with open(args.leg_file, encoding="utf-8") as fh:
            prev = int(json.load(fh)["leg"])
    leg = prev + 1
    os.makedirs(args.out, exist_ok=True)
    if os.path.isdir(args.work):
        shutil.rmtree(args.work)
    os.makedirs(args.work)
    scenarios = args.scenarios if args.scenarios is not None else named_scenarios.names()
    t0 = time.time()
    val = []
    if args.validate_s > 0:
        log = open(os.path.join(args.work, "validation.log"), "w", encoding="utf-8")
        val = start_validation(args.work, args.validate_images, log)
    chunks = [] if args.online else generate(args.work, leg, scenarios, args.gen_s, args.rate, args.gen_workers)
    gen_s = time.time() - t0
    images = sum(c["images"] for c in chunks)
    print(f"leg {leg}: {images} images in {len(chunks)} chunks, {gen_s:.0f} s ({images / gen_s:.0f} images/s)",
          flush=True)
    with open(os.path.join(args.out, "generate.json"), "w", encoding="utf-8") as fh:
        json.dump({"leg": leg, "seconds": round(gen_s, 1), "images": images,
                   "chunks": [{k: v for k, v in c.items() if k != "folder"} for c in chunks]}, fh, indent=1)
    budget = args.deadline_s - time.time() - args.reserve_s - (args.validate_s if val else 0.0)
    if budget < 30:
        raise SystemExit(f"no time left to train ({budget:.0f} s)")
    toml = os.path.join(args.work, "train.toml")
    with open(toml, "w", encoding="utf-8") as fh:
        fh.write(f"lr = {args.lr!r}\nwarmup_steps = 200\ncheckpoint_every = 1000\nseed = {SEED_BASE + leg}\n"
                 + ('schedule = "constant_cooldown"\nema_decay = 0.999\n' if args.online else ""))
    run_dir = os.path.join(args.work, "run")
    if args.target:
        source = ["--target", args.target, "--render-workers", str(max(1, args.gen_workers - 2)),
                  "--uses-per-frame", str(args.uses_per_frame)]
    elif args.online:
        looks = online_looks(args.work, leg, scenarios)
        source = ["--online", "--render-workers", str(render_workers(looks, args.gen_workers)), "--uses-per-frame",
                  str(args.uses_per_frame), "--looks", looks]
    else:
        source = ["--data", *[c["folder"] for c in chunks], "--workers", str(args.workers)]
    cmd = [sys.executable, "-m", "envisat_pose.app.cli", "train", *source, "--out", run_dir, "--config", toml,
           *start_args(args.init, args.backbone), "--device", args.device, "--batch-size", str(args.batch_size), "--steps",
           "10000000", "--time-budget-s", f"{budget:.0f}", "--quiet"] + ([] if args.no_bf16 else ["--bf16"])
    print(f"training for {budget:.0f} s: {' '.join(cmd[3:6])} ...", flush=True)
    rc = subprocess.run(cmd).returncode
    if rc != 0:
        raise SystemExit(f"envisat train failed ({rc})")
    end = [json.loads(line) for line in open(os.path.join(run_dir, "metrics.jsonl"), encoding="utf-8")][-1]
    shutil.copy2(os.path.join(run_dir, "checkpoint.safetensors"), os.path.join(args.out, "detector.safetensors"))
    for name in ("metrics.jsonl", "config.json", "state.json", "pre_cooldown.safetensors", "ema.safetensors"):
        if os.path.exists(os.path.join(run_dir, name)):  # the last three: online legs (their schedule)
            shutil.copy2(os.path.join(run_dir, name), os.path.join(args.out, name))
    with open(os.path.join(args.out, "leg.json"), "w", encoding="utf-8") as fh:
        json.dump({"leg": leg, "previous_leg": prev, "target": args.target,
                   "init_sha256": sha256_file(args.init) if args.init else None, "backbone": args.backbone,
                   "weights_sha256": sha256_file(os.path.join(args.out, "detector.safetensors")),
                   "data_seeds": [c["seed"] for c in chunks], "images": images, "generate_s": round(gen_s, 1),
                   "train_budget_s": round(budget), "end": end}, fh, indent=1)
    print(f"leg {leg} done: step {end['step']}, loss {end.get('loss', float('nan')):.4f}, "
          f"{end.get('samples_s')} samples/s, {end.get('data_wait_s')} s waiting for frames, "
          f"{time.time() - t0:.0f} s", flush=True)
    state_path = os.path.join(args.out, "state.json")
    if args.online and os.path.exists(state_path):  # where a frame's time goes in its render worker
        print(f"a rendered frame, ms: {json.load(open(state_path, encoding='utf-8'))['online'].get('frame_ms')}",
              flush=True)
    if val:
        table = validate(val, args.init, os.path.join(args.out, "detector.safetensors"),
                         os.path.join(args.out, "candidates.json"), args.device, args.deadline_s - 5.0)
        print(table if table else "validation: not finished in its time (no candidates.json)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
