"""What checking a dataset's shards costs its readers: `shard_reader.checked_shards` (each shard's size,
then its sha256, then its samples counted from the tar's headers, against manifest.json; once per run) next to one training epoch's data loading over the same
dataset on this CPU.

Protocol: a dataset as users make it (`envisat generate` defaults but the count: 1024 px, shards of 100; here
BENCH_IMAGES images), its files in the page cache (the loader reads them too, right after the check). The check is
timed REPEATS times a round (the median), as the verbs call it, in ROUNDS rounds interleaved with the loader's
epoch (the machine's load drifts alike for both; the median share over the rounds is the floor's). The epoch is estimated from the measured per-sample
cost of perception/stream.py's epoch_loader over the whole dataset (in this process, workers 0: one core, the
trainer's default input size 320 px and augmentation): per-sample cost x the dataset's samples. That is the data
side of an epoch only (no network step), so the ratio is an upper bound of the check's share of a real epoch.
Floor: check < 2 % of an epoch. The check hashes the shards one per core (threads: hashlib and file reads
release the GIL); its one-thread time, the CPU it costs, is reported beside it. Both costs grow with the images (bytes hashed, images decoded), so the ratio holds
for any count; the table also gives MB/s hashed and ms per sample.

Run: .venv/bin/python bench/shard_check.py [--data DIR] [--images N]  (writes bench/results/shard_check.json)
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import json  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

BENCH_IMAGES = 200
REPEATS = 5
ROUNDS = 3
FLOOR_SHARE = 0.02
HERE = os.path.dirname(os.path.abspath(__file__))


def make_dataset(out_dir: str, images: int) -> None:
    """The default generate config (1024 px, shards of 100) with `images` images."""
    from envisat_pose.datagen.factory import run_generate
    from envisat_pose.datagen.generate_config import GenerateConfig

    cfg = GenerateConfig(num_images=images)
    if not run_generate(cfg, out_dir)["complete"]:
        raise SystemExit("generate did not finish")


def time_check(data_dir: str, repeats: int) -> tuple[float, list[float], list[str]]:
    """Median seconds of checked_shards (what every reader calls: shards hashed one per core) over `repeats`
    calls, every time, and the shard files it returned."""
    from envisat_pose.shard_reader import checked_shards

    times, paths = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        paths, _ = checked_shards(data_dir)
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times, paths


def time_check_one_thread(data_dir: str, repeats: int) -> float:
    """Median seconds of the same check on one thread (the CPU time it takes)."""
    from envisat_pose.shard_reader import load_dataset_manifest, shard_problems

    entries = [e for e in load_dataset_manifest(data_dir)["shards"] if e["count"]]
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        shard_problems(data_dir, entries, threads=1)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def time_loader(paths: list[str], input_px: int, batch_size: int) -> tuple[float, int]:
    """Seconds and samples of one epoch of epoch_loader over paths (workers 0: this process, one core)."""
    import torch

    from envisat_pose.perception.data import DataConfig
    from envisat_pose.perception.stream import epoch_loader

    torch.set_num_threads(1)
    n = 0
    t0 = time.perf_counter()
    for batch in epoch_loader(paths, DataConfig(input_px=input_px), 0, 0, batch_size, 0):
        n += int(batch["image"].shape[0])
    return time.perf_counter() - t0, n


def measure(data_dir: str, input_px: int, batch_size: int, repeats: int, rounds: int) -> dict:
    """Rounds of (the check, its one-thread time, one epoch of the loader), interleaved so the machine's load
    drifts alike for both; the median share over the rounds is the floor's."""
    from envisat_pose.shard_reader import load_dataset_manifest

    manifest = load_dataset_manifest(data_dir)
    n_samples = sum(e["count"] for e in manifest["shards"])
    per_round = []
    for _ in range(rounds):
        check_s, check_all, paths = time_check(data_dir, repeats)
        one_thread_s = time_check_one_thread(data_dir, repeats)
        loader_s, samples = time_loader(paths, input_px, batch_size)
        epoch_s = loader_s / max(samples, 1) * n_samples
        per_round.append({"check_s": check_s, "check_s_all": check_all, "check_one_thread_s": one_thread_s,
                          "loader_s": loader_s, "samples": samples, "epoch_s": epoch_s,
                          "share": check_s / epoch_s, "one_thread_share": one_thread_s / epoch_s})
    med = {k: statistics.median(r[k] for r in per_round) for k in ("check_s", "check_one_thread_s", "epoch_s",
                                                                   "share", "one_thread_share")}
    nbytes = sum(os.path.getsize(p) for p in paths)
    return {"dataset": {"images": manifest.get("num_images"), "shards": len(paths), "bytes": nbytes,
                        "resolution_px": manifest.get("config", {}).get("resolution_px")},
            "check_s_median": med["check_s"], "hash_mb_s": nbytes / 1e6 / med["check_s"],
            "check_one_thread_s_median": med["check_one_thread_s"],
            "check_one_thread_share_of_epoch": med["one_thread_share"],
            "loader": {"input_px": input_px, "batch_size": batch_size, "workers": 0, "samples": n_samples,
                       "ms_per_sample": 1000 * med["epoch_s"] / n_samples},
            "epoch_s_estimate": med["epoch_s"], "check_share_of_epoch": med["share"], "rounds": per_round,
            "floor_share": FLOOR_SHARE, "floor_met": med["share"] < FLOOR_SHARE, "cpu_count": os.cpu_count(),
            "load_average_1min": os.getloadavg()[0]}


def table(r: dict) -> str:
    d, lo = r["dataset"], r["loader"]
    rows = [("dataset", f"{d['images']} images of {d['resolution_px']} px, {d['shards']} shards, "
                        f"{d['bytes'] / 1e6:.1f} MB"),
            ("check (size + sha256), median", f"{1000 * r['check_s_median']:.1f} ms ({r['hash_mb_s']:.0f} MB/s, "
                                              f"{r['cpu_count']} cores)"),
            ("the same on one thread", f"{1000 * r['check_one_thread_s_median']:.1f} ms "
                                       f"({100 * r['check_one_thread_share_of_epoch']:.2f} % of the epoch)"),
            ("loader per sample (1 core)", f"{lo['ms_per_sample']:.1f} ms at {lo['input_px']} px"),
            ("one epoch's loading, estimated", f"{r['epoch_s_estimate']:.2f} s"),
            ("check / epoch", f"{100 * r['check_share_of_epoch']:.2f} % (floor < {100 * FLOOR_SHARE:.0f} %: "
                              f"{'met' if r['floor_met'] else 'NOT met'})")]
    w = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:{w}s}  {v}" for k, v in rows)


def main() -> int:
    from _common import WholeFlagParser, count, dataset, description, out_file, provenance  # bench/_common.py

    from envisat_pose.io import atomic_write_text

    ap = WholeFlagParser(description=description(__doc__))
    ap.add_argument("--data", metavar="DIR", type=dataset,
                    help="an existing generated dataset (default: generate one)")
    ap.add_argument("--images", type=count(), default=BENCH_IMAGES, help=f"images to generate (default {BENCH_IMAGES})")
    ap.add_argument("--input-px", type=count(), default=320, help="the loader's input size (default 320)")
    ap.add_argument("--batch-size", type=count(), default=8)
    ap.add_argument("--repeats", type=count(), default=REPEATS, help="check calls timed per round")
    ap.add_argument("--rounds", type=count(), default=ROUNDS, help="interleaved rounds of check and loader")
    ap.add_argument("--out", type=out_file, default=os.path.join(HERE, "results", "shard_check.json"))
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        data = args.data
        if data is None:
            data = os.path.join(tmp, "ds")
            make_dataset(data, args.images)
        result = measure(data, args.input_px, args.batch_size, args.repeats, args.rounds)
    print(table(result))
    result["provenance"] = provenance(args)
    atomic_write_text(args.out, json.dumps(result, indent=1, sort_keys=True) + "\n")
    print(f"wrote {args.out}")
    return 0 if result["floor_met"] else 1


if __name__ == "__main__":
    from _common import run_main  # bench/_common.py, beside this script

    run_main(main)
