"""`envisat dataset verify|inspect|export`: a generated dataset read back: checked against its manifest,
summarised with a labelled montage, or exported into the formats the field trains on (docs/formats.md)."""

from __future__ import annotations

import argparse
import json

from envisat_pose.app.common import add_common, add_skip_damaged_argument, check_rrd_output, skipped_line
from envisat_pose.datagen.dataset import DEPRECATED_CORNER_KEYS, verify_dataset
from envisat_pose.pipelines.datasets.export import ExportConfig, export_dataset
from envisat_pose.pipelines.datasets.inspect import OUTPUT_KEYS, inspect_dataset
from envisat_pose.pools import usable_cores
from envisat_pose.shard_reader import skip_hint


def register(sub: argparse._SubParsersAction) -> None:
    d = sub.add_parser("dataset", help="check, summarise or export a generated dataset")
    dsub = d.add_subparsers(dest="dataset_verb", metavar="ACTION")
    dsub.required = True
    v = dsub.add_parser("verify", help="report missing, partial or corrupt shards (exit 1 if any)")
    v.add_argument("dir", metavar="DIR")
    v.set_defaults(func=run_verify_cli)
    i = dsub.add_parser("inspect", help="print statistics and write a montage PNG with the labelled keypoints "
                        "(ENVISAT's: its corners)")
    i.add_argument("dir", metavar="DIR")
    i.add_argument("--montage", metavar="FILE.png", help="montage path (default DIR/montage.png)")
    i.add_argument("--count", type=int, default=16, help="images in the montage (default 16)")
    i.add_argument("--rrd", metavar="FILE.rrd", help="also write the first --count samples as a Rerun recording: "
                   "images with labelled keypoints, masks, depth (`envisat view FILE`)")
    i.add_argument("--target", metavar="FILE.xml", help="with --rrd: the dataset's target file, where the path its "
                   "manifest records is not found from here (its sha256 must match)")
    add_skip_damaged_argument(i)
    i.set_defaults(func=run_inspect_cli, flag_names={"src": "DIR", "montage": "--montage", "count": "--count",
                                                     "rrd": "--rrd", "target": "--target"})
    e = dsub.add_parser("export", help="write a dataset as SPEED+, COCO keypoints, BOP or YOLO-pose",
                        description="Export a generated dataset (random or sequence mode) into a new folder of a "
                        "format the field trains on; conventions in the folder's README.md and docs/formats.md.")
    e.add_argument("src", metavar="SRC", help="dataset folder written by `envisat generate`")
    e.add_argument("--format", required=True, choices=("speedplus", "coco", "bop", "yolo-pose"))
    e.add_argument("--target", metavar="FILE.xml", help="the dataset's target file, where the path its manifest "
                   "records is not found from here (its sha256 must match; default: the recorded one)")
    e.add_argument("--image-format", default="png", choices=("png", "jpg"),
                   help="png: the shards' bytes unchanged (default); jpg: re-encoded at quality 95")
    e.add_argument("--val-fraction", type=float, metavar="F", help="share of images in the validation split "
                   "(default 0.2 for random views; a sequence: 0, else its last frames)")
    e.add_argument("--workers", type=int, default=usable_cores(), help="local worker processes (default: one per "
                   "usable core)")
    add_common(e, out="new folder (refused if it exists and is not empty)", seed="seed of the train/validation "
               "split (default 0)", flag_names={"src": "SRC", "fmt": "--format", "image_format": "--image-format",
                                                "val_fraction": "--val-fraction", "workers": "--workers",
                                                "target": "--target"})
    add_skip_damaged_argument(e)
    e.set_defaults(func=run_export_cli)


def run_verify_cli(args: argparse.Namespace) -> int:
    problems = verify_dataset(args.dir)
    for line in problems:
        print(f"PROBLEM {line}")
    if problems:
        print(f"{args.dir}: {len(problems)} problem(s)")
        return 1
    print(f"{args.dir}: all shards present and verified")
    return 0


def run_inspect_cli(args: argparse.Namespace) -> int:
    if args.rrd:
        check_rrd_output(args.rrd)
    with skip_hint():
        result = inspect_dataset(args.dir, args.montage, args.count, args.rrd, args.skip_damaged, args.target)
    print(json.dumps({k: v for k, v in result.items() if k not in OUTPUT_KEYS}, indent=1))
    for line in stats_lines(result):
        print(line)
    print(f"wrote {result['montage']} ({result['montage_images']} images)")
    if args.rrd:
        print(f"wrote {args.rrd} (Rerun recording; open it with `envisat view {args.rrd}`)")
    if result.get("skipped_damaged_shards"):
        print(skipped_line(result["skipped_damaged_shards"]))
    return 0


def stats_lines(stats: dict) -> list[str]:
    """The statistics in words: the keypoints per image, as the labels call them ("corners (of 8)": ENVISAT's A-H;
    "keypoints (of K)"), and the deprecated keys the JSON holds (DEPRECATED_CORNER_KEYS)."""
    hist = stats.get("visible_keypoints_histogram")
    if not hist:
        return []
    visible = sum(i * c for i, c in enumerate(hist)) / sum(hist)
    lines = [f"{stats['keypoints_noun']} (of {len(hist) - 1}) per image: {visible:.2f} visible, "
             f"{stats['in_frame_keypoints_mean']:.2f} in frame, on average"]
    old = [key for key in DEPRECATED_CORNER_KEYS if key in stats]
    if old:
        lines.append(f"deprecated: {', '.join(old)}, the same as {', '.join(DEPRECATED_CORNER_KEYS[k] for k in old)} "
                     "(ENVISAT's old names, kept for this release only)")
    return lines


def run_export_cli(args: argparse.Namespace) -> int:
    cfg = ExportConfig(args.format, args.image_format, args.val_fraction, 0 if args.seed is None else args.seed,
                       args.target)
    summary = export_dataset(args.src, args.out, cfg, workers=args.workers, skip_damaged=args.skip_damaged,
                             progress=not args.quiet)
    counts = ", ".join(f"{n} {name}" for name, n in summary.images.items())
    print(f"wrote {summary.fmt} export of {args.src} to {summary.out_dir} ({counts}; conventions in README.md)")
    if summary.skipped:
        print(skipped_line(summary.skipped))
    return 0
