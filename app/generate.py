"""`envisat generate` (the image factory) and `envisat dataset verify|inspect` (reading a dataset back)."""

from __future__ import annotations

import argparse
import json
import os

from envisat_pose.config import InputError, resolve_job_config
from envisat_pose.pipelines.dataset_inputs import add_skip_damaged_argument, skip_hint, skipped_line


def register(sub: argparse._SubParsersAction) -> None:
    g = sub.add_parser(
        "generate",
        help="render labelled, corrupted images of ENVISAT into WebDataset shards",
        description="Render images of the tumbling target with MuJoCo (off-screen), label them (corners, "
        "visibility by depth test, pose, mask, depth), corrupt them, and write tar shards plus manifest.json. "
        "Running it again on the same --out finishes an interrupted dataset.",
    )
    g.add_argument("--config", metavar="FILE.toml", help="generate config (keys of GenerateConfig, [corruption])")
    g.add_argument("--mode", help="random (domain-randomized views) or sequence (frames of a simulated truth)")
    g.add_argument("--num-images", type=int, help="number of images (default 1000)")
    g.add_argument("--shard-size", type=int, help="images per shard (default 100)")
    g.add_argument("--resolution", type=int, metavar="PX", help="square image side in pixels (default 1024)")
    g.add_argument("--seed", type=int, help="root seed (default 0)")
    g.add_argument("--scenario", help="named truth scenario of sequence mode (default: default)")
    g.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    g.add_argument("--backend", default="local", choices=("local", "dask"), help="local process pool or Dask")
    g.add_argument("--scheduler", metavar="ADDRESS", help="Dask scheduler address (default: a LocalCluster on 127.0.0.1)")
    g.add_argument("--out", required=True, metavar="DIR", help="dataset folder (created, parents too; resumed if it "
                   "exists)")
    g.add_argument("--quiet", action="store_true", help="no progress bar")
    g.set_defaults(func=run_generate_cli)

    d = sub.add_parser("dataset", help="check or summarise a generated dataset")
    dsub = d.add_subparsers(dest="dataset_verb", metavar="ACTION")
    dsub.required = True
    v = dsub.add_parser("verify", help="report missing, partial or corrupt shards (exit 1 if any)")
    v.add_argument("dir", metavar="DIR")
    v.set_defaults(func=run_verify_cli)
    i = dsub.add_parser("inspect", help="print statistics and write a montage PNG with the labelled corners")
    i.add_argument("dir", metavar="DIR")
    i.add_argument("--montage", metavar="FILE.png", help="montage path (default DIR/montage.png)")
    i.add_argument("--count", type=int, default=16, help="images in the montage (default 16)")
    i.add_argument("--rrd", metavar="FILE.rrd", help="also write the first --count samples as a Rerun recording: "
                   "images with labelled corners, masks, depth (`envisat view FILE`)")
    add_skip_damaged_argument(i)
    i.set_defaults(func=run_inspect_cli)


def resolve_config(args: argparse.Namespace):
    """Defaults, then the TOML file, then the flags; validated before any work."""
    from envisat_pose.datagen.generate_config import GenerateConfig

    flags = {"mode": args.mode, "num_images": args.num_images, "shard_size": args.shard_size,
             "resolution_px": args.resolution, "seed": args.seed, "scenario": args.scenario}
    return resolve_job_config(GenerateConfig, {}, args.config, flags)


def run_generate_cli(args: argparse.Namespace) -> int:
    from envisat_pose.datagen.factory import run_generate

    if args.workers < 1:
        raise InputError(f"--workers {args.workers}: expected at least 1")
    if args.scheduler and args.backend != "dask":
        raise InputError("--scheduler needs --backend dask")
    cfg = resolve_config(args)
    written: list[dict] = []
    manifest = run_generate(cfg, args.out, workers=args.workers, backend=args.backend, scheduler=args.scheduler,
                            progress=not args.quiet, on_shard=written.append)
    print(generate_line(manifest, written, args.out))
    return 0 if manifest["complete"] else 1


def generate_line(manifest: dict, written: list[dict], out: str) -> str:
    """What a generate run did: the images it wrote now, and those an earlier run had written."""
    n_all = sum(e["count"] for e in manifest["shards"])
    n_now = sum(e["count"] for e in written)
    if not written:
        return f"nothing to do: {n_all} images already there in {len(manifest['shards'])} shards in {out}"
    before = f"; {n_all - n_now} images already there" if n_all > n_now else ""
    return (f"wrote {n_now} images in {len(written)} shards to {out}{before} (manifest.json, "
            "generate.config.toml)")


def run_verify_cli(args: argparse.Namespace) -> int:
    from envisat_pose.datagen.dataset import verify_dataset

    problems = verify_dataset(args.dir)
    for line in problems:
        print(f"PROBLEM {line}")
    if problems:
        print(f"{args.dir}: {len(problems)} problem(s)")
        return 1
    print(f"{args.dir}: all shards present and verified")
    return 0


def run_inspect_cli(args: argparse.Namespace) -> int:
    from envisat_pose.datagen.dataset import dataset_stats, load_manifest, montage
    from envisat_pose.runner import check_out_file, make_out_file_dir
    from envisat_pose.shard_reader import checked_shards

    path = args.montage or os.path.join(args.dir, "montage.png")
    check_out_file(path, "--montage")
    if args.rrd:
        from envisat_pose.app.common import check_rrd_output

        check_rrd_output(args.rrd)
    load_manifest(args.dir)
    with skip_hint():
        shards, skipped = checked_shards(args.dir, args.skip_damaged, "dataset")
    stats = dataset_stats(shards)
    if skipped:
        stats["skipped_damaged_shards"] = skipped
    print(json.dumps(stats, indent=1))
    make_out_file_dir(path, "--montage")
    n = montage(shards, path, count=args.count)
    print(f"wrote {path} ({n} images)")
    if args.rrd:
        make_out_file_dir(args.rrd, "--rrd")
        write_samples_rrd(shards, args.rrd, args.count)
        print(f"wrote {args.rrd} (Rerun recording; open it with `envisat view {args.rrd}`)")
    if skipped:
        print(skipped_line(skipped))
    return 0


def write_samples_rrd(source: str | list[str], path: str, count: int) -> None:
    """The first `count` samples as a Rerun recording (analysis.recording.write_samples_recording), read lazily.
    source: a dataset folder or its checked shard files."""
    from envisat_pose.analysis.recording import Sample, write_samples_recording
    from envisat_pose.datagen.dataset import iter_samples, sample_png
    from envisat_pose.datagen.shards import decode_png

    samples = (Sample(key, sample_png(members, label), label,
                      mask=decode_png(members["mask.png"]) if "mask.png" in members else None,
                      depth_png=members.get("depth.png"))
               for key, label, members in iter_samples(source, limit=count))
    write_samples_recording(path, samples)
