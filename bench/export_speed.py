"""What `envisat dataset export` costs: time and peak memory per format on a dataset as users make it (1024 px
random views, the default config, shards of 100), beside the floor any exporter pays, taking the image bytes out
of the shards (a plain tar extraction, the peer row).

Protocol: one dataset of BENCH_IMAGES images made once (or --data), its files in the page cache (read once
before the first timed row); each row runs in its own process (its peak RSS, and its workers' largest, are that
export's alone), with --workers 2. Memory flat: every format is run on a quarter of the dataset too (its first quarter: the same
seed), and the peak RSS of the whole dataset must stay within 1.2x of the quarter's (+ 30 MB).
Floors: 1,000 images at 1024 px in at most 30 s on 2 cores for every format; memory flat. What each row pays beyond
the copy: BOP decodes every image and writes it as a three-channel JPEG, with two masks (mask/, mask_visib/);
SPEED+ decodes and writes each mask (masks/); COCO and YOLO-pose decode the mask for the box.

Run: .venv/bin/python bench/export_speed.py [--data DIR] [--images N]  (writes bench/results/export_speed.json)
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import json  # noqa: E402
import platform  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402

from envisat_pose.datagen.export_formats import FORMATS  # noqa: E402  (every format, timed)

BENCH_IMAGES = 1000
FLOOR_S_PER_1000 = 30.0
HERE = os.path.dirname(os.path.abspath(__file__))

_CHILD = r"""
import json, os, resource, sys, time
os.environ.setdefault("MUJOCO_GL", "osmesa")
kind, src, out, fmt, image_format = sys.argv[1:6]
t0 = time.perf_counter()
if kind == "extract":
    import tarfile
    from envisat_pose.shard_reader import checked_shards
    os.makedirs(out)
    n = 0
    for path in checked_shards(src)[0]:
        with tarfile.open(path) as tar:
            for m in tar:
                if m.name.endswith(".png") and m.name.count(".") == 1:
                    with open(os.path.join(out, m.name), "wb") as fh:
                        fh.write(tar.extractfile(m).read())
                    n += 1
else:
    from envisat_pose.pipelines.datasets.export import ExportConfig, export_dataset
    s = export_dataset(src, out, ExportConfig(fmt, image_format), workers=2, progress=False)
    n = sum(s.images.values())
dt = time.perf_counter() - t0
print(json.dumps({"seconds": dt, "images": n, "rss_self_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "rss_worker_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024}))
"""


def make_dataset(out_dir: str, images: int) -> None:
    from envisat_pose.config import from_dict
    from envisat_pose.datagen.factory import run_generate
    from envisat_pose.datagen.generate_config import GenerateConfig

    run_generate(from_dict(GenerateConfig, {"num_images": images, "shard_size": 100, "seed": 47}), out_dir,
                 workers=2, progress=True)


def run_row(kind: str, src: str, work: str, fmt: str = "-", image_format: str = "png") -> dict:
    out = tempfile.mkdtemp(dir=work)
    shutil.rmtree(out)
    res = subprocess.run([sys.executable, "-c", _CHILD, kind, src, out, fmt, image_format], capture_output=True,
                         text=True, check=True)
    shutil.rmtree(out, ignore_errors=True)
    row = json.loads(res.stdout.strip().splitlines()[-1])
    row["s_per_1000"] = row["seconds"] / row["images"] * 1000
    return row


def main() -> int:
    from _common import WholeFlagParser, count, dataset, description, out_file, provenance  # bench/_common.py

    ap = WholeFlagParser(description=description(__doc__))
    ap.add_argument("--data", type=dataset, help="an existing 1024 px dataset (default: make one)")
    ap.add_argument("--images", type=count(), default=BENCH_IMAGES)
    ap.add_argument("--out", type=out_file, default=os.path.join(HERE, "results", "export_speed.json"))
    args = ap.parse_args()
    from envisat_pose.io import atomic_write_text

    with tempfile.TemporaryDirectory() as work:
        src = args.data or os.path.join(work, "data")
        if not args.data:
            make_dataset(src, args.images)
        small = os.path.join(work, "quarter")  # the same seed: the first quarter of the same images
        n_small = max(100, args.images // 4)
        make_dataset(small, n_small)
        run_row("extract", src, work)  # warm the page cache
        rows = {"extract (peer: the shards' PNG bytes to files)": run_row("extract", src, work)}
        for fmt in FORMATS:
            rows[fmt] = run_row("export", src, work, fmt)
            q = run_row("export", small, work, fmt)
            rows[fmt]["quarter"] = {"images": n_small, "rss_self_mb": q["rss_self_mb"],
                                    "rss_worker_mb": q["rss_worker_mb"]}
        rows["coco, jpg"] = run_row("export", src, work, "coco", "jpg")
    flat = {}
    for name, r in rows.items():
        if "quarter" in r:
            flat[name] = all(r[k] <= 1.2 * r["quarter"][k] + 30 for k in ("rss_self_mb", "rss_worker_mb"))
    result = {
        "protocol": f"1024 px random views (default config, seed 47, shards of 100), {args.images} images; each row "
                    "its own process, --workers 2, page cache warm; peak RSS of the main process and of its largest "
                    "worker; memory flat: whole dataset within 1.2x + 30 MB of its first quarter",
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
                    "load_avg_end": list(os.getloadavg())},
        "rows": rows,
        "floors": {"s_per_1000_max": FLOOR_S_PER_1000,
                   "time_met": {f: rows[f]["s_per_1000"] <= FLOOR_S_PER_1000 for f in FORMATS},
                   "memory_flat": flat},
    }
    print(f"{'row':52s} {'images':>6s} {'s/1000':>7s} {'RSS main MB':>11s} {'RSS worker MB':>13s}")
    for name, r in rows.items():
        print(f"{name:52s} {r['images']:6d} {r['s_per_1000']:7.1f} {r['rss_self_mb']:11.0f} {r['rss_worker_mb']:13.0f}")
    print(f"floors: <= {FLOOR_S_PER_1000:.0f} s per 1000: {result['floors']['time_met']}; memory flat: {flat}")
    result["provenance"] = provenance(args)
    atomic_write_text(args.out, json.dumps(result, indent=1, sort_keys=True) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    from _common import run_main  # bench/_common.py, beside this script

    run_main(main)
