"""One leg of detector training on a borrowed GPU machine (issue 26): fresh data on every core, then `envisat
train` from the last leg's weights for what is left of the time, the results written where they come back.

The data of a leg (seeds 1,000,000 + 1,000 x leg + chunk: never an evaluation seed, new every leg; the looks'
texture, appearance, Earth and camera seeds 2,000,000 + 10 x leg + 0..3 move with the leg too), generated in rounds until --gen-s is spent
(a round, at --scale 1, is about 4,700 images, about 45 s on 16 cores with EGL), each round:
- random views at 512, 768, 1024, 1536 and 2048 px with the Earth behind the target in 35-50 % of them;
- the space camera at every severity: uncorrupted, a benign camera, the default ranges and a harsh one, and the
  paper's per-kind corruptions (severities drawn per image);
- wider looks than the factory's defaults (materials, brightness, sun intensity, texture sets, more backlit
  views) on all but the default chunk; the trainer adds gain, contrast, gamma, blur, glare and noise;
- frames of every named scenario (sequence mode, 1024 px, the Earth wherever it reaches the image; appearance
  off in even rounds as the closed loop renders it, on in odd ones).
Then `envisat train --init W --workers N --bf16 --time-budget-s T` into a run folder, and into --out:
detector.safetensors, leg.json (this leg's number, data, init hash, the end line), metrics.jsonl,
config.json, generate.json (every chunk's command, images and seconds).

    python3 scripts/gpu_train.py --init W --leg-file L --out DIR --deadline-s EPOCH [--device cuda] ...
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time

SEED_BASE = 1_000_000  # training data seeds: evaluation sets use seeds far below
SEED_LEG = 1_000
LOOK_SEED_BASE = 2_000_000  # the looks' seeds (textures, appearance, Earth, camera pattern): 10 per leg
IMAGE_COST = {512: 0.3, 768: 0.6, 1024: 1.0, 1536: 2.2, 2048: 4.0}  # render + write, relative to 1024 px

WIDE_LOOKS = {
    "backlit_probability": 0.25, "sun_phase_max_deg": 130.0,
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


def round_chunks(leg: int, round_index: int, scenarios: list[str], scale: float) -> list[dict]:
    """The chunks of one round: {"name", "images", "resolution", "config" (GenerateConfig keys)}; seeds later."""
    n = lambda k: max(2, int(round(k * scale)))  # noqa: E731
    base = leg_seeds(leg)
    wide = merge(base, WIDE_LOOKS)
    chunks = [
        {"name": "random-1024-default", "images": n(800), "resolution": 1024,
         "config": merge(base, {"earth_probability": 0.4})},
        {"name": "random-512-wide", "images": n(800), "resolution": 512,
         "config": merge(wide, {"earth_probability": 0.5})},
        {"name": "random-768-paper", "images": n(400), "resolution": 768,
         "config": merge(merge(wide, CAMERAS["paper"]), {"earth_probability": 0.35})},
        {"name": "random-1536-wide", "images": n(300), "resolution": 1536,
         "config": merge(wide, {"earth_probability": 0.4})},
        {"name": "random-2048-wide", "images": n(150), "resolution": 2048,
         "config": merge(wide, {"earth_probability": 0.4})},
    ]
    for cam in ("clean", "benign", "harsh"):
        chunks.append({"name": f"random-1024-{cam}", "images": n(300), "resolution": 1024,
                       "config": merge(merge(wide, CAMERAS[cam]), {"earth_probability": 0.4})})
    sequences = [{"name": f"sequence-{name}", "images": n(120), "resolution": 1024, "scenario": name,
                  "config": merge(base, {"mode": "sequence", "scenario": name, "frame_dt_s": 2.0,
                                         "earth_probability": 1.0,
                                         "appearance": {"enabled": round_index % 2 == 1}})} for name in scenarios]
    # interleaved, so a round cut short by the clock still holds both kinds
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


def run(cmd: list[str], log) -> int:
    log.write("$ " + " ".join(cmd) + "\n")
    log.flush()
    return subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT).returncode


def generate(work: str, leg: int, scenarios: list[str], gen_s: float, scale: float, workers: int, log) -> list[dict]:
    """Chunks in rounds until the next one would pass gen_s (the first always runs). Returns the made chunks."""
    t0 = time.time()
    done, cost_s, k, r = [], None, 0, 0
    while True:
        for chunk in round_chunks(leg, r, scenarios, scale):
            load = chunk["images"] * IMAGE_COST[chunk["resolution"]]
            if done and (time.time() - t0 + (cost_s or 0.0) * load > gen_s or k >= SEED_LEG):
                return done  # out of time, or of the leg's block of seeds
            seed = SEED_BASE + SEED_LEG * leg + k
            k += 1
            folder = os.path.join(work, f"d{seed}-{chunk['name']}")
            toml = folder + ".toml"
            with open(toml, "w", encoding="utf-8") as fh:
                fh.write(to_toml(chunk["config"]))
            cmd = [sys.executable, "-m", "envisat_pose.app.cli", "generate", "--config", toml, "--num-images",
                   str(chunk["images"]), "--shard-size", str(max(1, min(64, chunk["images"] // max(workers, 1)))),
                   "--resolution", str(chunk["resolution"]), "--seed", str(seed), "--workers", str(workers),
                   "--out", folder, "--quiet"]
            tc = time.time()
            if run(cmd, log) != 0:
                raise SystemExit(f"generate failed: {' '.join(cmd)} (see the log)")
            sec = time.time() - tc
            cost_s = sec / load if cost_s is None else 0.5 * cost_s + 0.5 * sec / load
            done.append({"name": chunk["name"], "seed": seed, "images": chunk["images"],
                         "resolution": chunk["resolution"], "seconds": round(sec, 1), "folder": folder,
                         "config": chunk["config"],
                         "command": "envisat generate " + " ".join(
                             os.path.basename(c) if c in (toml, folder) else c for c in cmd[4:])})
            print(f"chunk {chunk['name']} seed {seed}: {chunk['images']} images in {sec:.1f} s", flush=True)
        r += 1


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--init", required=True, help="weights to start from")
    ap.add_argument("--leg-file", help="leg.json of the init weights (their leg number; none: leg 0 before)")
    ap.add_argument("--out", required=True, help="folder whose files come back")
    ap.add_argument("--work", default="/tmp/gpu-leg", help="scratch folder (data, run)")
    ap.add_argument("--deadline-s", type=float, required=True, help="epoch seconds by which everything is written")
    ap.add_argument("--gen-s", type=float, default=170.0, help="seconds of generation")
    ap.add_argument("--scale", type=float, default=1.0, help="images per chunk x this (dry runs: 0.01)")
    ap.add_argument("--gen-workers", type=int, default=os.cpu_count())
    ap.add_argument("--workers", type=int, default=max(0, (os.cpu_count() or 2) - 2))
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--batch-size", type=int, default=64)
    ap.add_argument("--lr", type=float, default=1.5e-3)
    ap.add_argument("--no-bf16", action="store_true")
    ap.add_argument("--reserve-s", type=float, default=25.0, help="kept for the train process's start and the copy")
    ap.add_argument("--scenarios", nargs="*", help="named scenarios (default: all)")
    args = ap.parse_args()
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
    log = open(os.path.join(args.work, "commands.log"), "w", encoding="utf-8")
    t0 = time.time()
    chunks = generate(args.work, leg, scenarios, args.gen_s, args.scale, args.gen_workers, log)
    gen_s = time.time() - t0
    images = sum(c["images"] for c in chunks)
    print(f"leg {leg}: {images} images in {len(chunks)} chunks, {gen_s:.0f} s ({images / gen_s:.0f} images/s)",
          flush=True)
    with open(os.path.join(args.out, "generate.json"), "w", encoding="utf-8") as fh:
        json.dump({"leg": leg, "seconds": round(gen_s, 1), "images": images,
                   "chunks": [{k: v for k, v in c.items() if k != "folder"} for c in chunks]}, fh, indent=1)
    budget = args.deadline_s - time.time() - args.reserve_s
    if budget < 30:
        raise SystemExit(f"no time left to train ({budget:.0f} s)")
    toml = os.path.join(args.work, "train.toml")
    with open(toml, "w", encoding="utf-8") as fh:
        fh.write(f"lr = {args.lr!r}\nwarmup_steps = 200\ncheckpoint_every = 1000\nseed = {SEED_BASE + leg}\n")
    run_dir = os.path.join(args.work, "run")
    cmd = [sys.executable, "-m", "envisat_pose.app.cli", "train", "--data", *[c["folder"] for c in chunks],
           "--out", run_dir, "--config", toml, "--init", args.init, "--device", args.device, "--workers",
           str(args.workers), "--batch-size", str(args.batch_size), "--steps", "10000000", "--time-budget-s",
           f"{budget:.0f}", "--quiet"] + ([] if args.no_bf16 else ["--bf16"])
    print(f"training for {budget:.0f} s: {' '.join(cmd[3:6])} ...", flush=True)
    rc = subprocess.run(cmd).returncode
    if rc != 0:
        raise SystemExit(f"envisat train failed ({rc})")
    end = [json.loads(line) for line in open(os.path.join(run_dir, "metrics.jsonl"), encoding="utf-8")][-1]
    shutil.copy2(os.path.join(run_dir, "checkpoint.safetensors"), os.path.join(args.out, "detector.safetensors"))
    for name in ("metrics.jsonl", "config.json"):
        shutil.copy2(os.path.join(run_dir, name), os.path.join(args.out, name))
    with open(os.path.join(args.out, "leg.json"), "w", encoding="utf-8") as fh:
        json.dump({"leg": leg, "previous_leg": prev, "init_sha256": sha256_file(args.init),
                   "weights_sha256": sha256_file(os.path.join(args.out, "detector.safetensors")),
                   "data_seeds": [c["seed"] for c in chunks], "images": images, "generate_s": round(gen_s, 1),
                   "train_budget_s": round(budget), "end": end}, fh, indent=1)
    print(f"leg {leg} done: step {end['step']}, loss {end.get('loss', float('nan')):.4f}, "
          f"{end.get('samples_s')} samples/s, {time.time() - t0:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
