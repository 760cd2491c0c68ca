"""`envisat generate`: the image factory (reading a dataset back is `envisat dataset`, app/dataset.py)."""

from __future__ import annotations

import argparse

from envisat_pose.app.common import add_common
from envisat_pose.config import InputError
from envisat_pose.datagen.factory import run_generate
from envisat_pose.datagen.generate_config import layered_generate

# the config fields the flags set, named as the flag in an error where the user typed it (app/flag_rules.py)
FLAGS = {"mode": "--mode", "num_images": "--num-images", "shard_size": "--shard-size", "resolution_px": "--resolution",
         "scenario": "--scenario", "sequence.scenario": "--scenario", "target": "--target",
         "workers": "--workers", "backend": "--backend", "scheduler": "--scheduler"}  # run_generate's arguments


def register(sub: argparse._SubParsersAction) -> None:
    g = sub.add_parser(
        "generate",
        help="render labelled, corrupted images of ENVISAT (or another --target) into WebDataset shards",
        description="Render images of the tumbling target with MuJoCo (off-screen), label them (keypoints: "
        "ENVISAT's corners A-H or another target's kp_ sites; visibility by ray casts through the target, pose, "
        "mask, depth), corrupt them, and write tar shards plus manifest.json. Running it again on the same --out "
        "finishes an interrupted dataset.",
    )
    g.add_argument("--config", metavar="FILE.toml", help="generate config (keys of GenerateConfig; tables [random], [sequence], [corruption], ...)")
    g.add_argument("--mode", help="random (domain-randomized views) or sequence (frames of a simulated truth)")
    g.add_argument("--num-images", type=int, help="number of images (default 1000)")
    g.add_argument("--shard-size", type=int, help="images per shard (default 100)")
    g.add_argument("--resolution", type=int, metavar="PX", help="square image side in pixels (default 1024)")
    g.add_argument("--seed", type=int, help="root seed (default 0)")
    g.add_argument("--scenario", help="named truth scenario of sequence mode (default: default)")
    g.add_argument("--target", metavar="FILE.xml", help="the target's MJCF file: a body 'target' with its inertial, "
                   "geoms and keypoint sites kp_<name> (default models/envisat.xml; models/cubesat_3u.xml and "
                   "models/upper_stage.xml ship too)")
    g.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    g.add_argument("--backend", default="local", choices=("local", "dask"), help="local process pool or Dask")
    g.add_argument("--scheduler", metavar="ADDRESS", help="Dask scheduler address (default: a LocalCluster on 127.0.0.1)")
    g.add_argument("--out", required=True, metavar="DIR", help="dataset folder (created, parents too; resumed if it "
                   "holds a dataset; a folder of other files is refused)")
    add_common(g, quiet=True, flag_names=FLAGS)
    g.set_defaults(func=run_generate_cli, resumable=True)


def resolve_config(args: argparse.Namespace):
    """Defaults, then the TOML file, then the flags; validated before any work."""

    flags = {"mode": args.mode, "num_images": args.num_images, "shard_size": args.shard_size,
             "resolution_px": args.resolution, "seed": args.seed, "sequence.scenario": args.scenario,
             "target": args.target}
    cfg = layered_generate({}, args.config, flags)
    if args.scenario is not None and cfg.mode != "sequence":
        raise InputError(f"--scenario {args.scenario}: applies to --mode sequence (random views draw their own "
                         f"poses; this run's mode is {cfg.mode})")
    return cfg


def run_generate_cli(args: argparse.Namespace) -> int:
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
        return (f"nothing to do: {counted(n_all, 'image')} already there in {counted(len(manifest['shards']), 'shard')}"
                f" in {out}")
    before = f"; {counted(n_all - n_now, 'image')} already there" if n_all > n_now else ""
    return (f"wrote {counted(n_now, 'image')} in {counted(len(written), 'shard')} to {out}{before} (manifest.json, "
            "generate.config.toml)")


def counted(n: int, noun: str) -> str:
    """'1 image', '2 images'."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"
