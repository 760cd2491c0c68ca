"""`envisat train`: the verb over the training pipeline (pipelines/detector/train.py): the corner detector
trained on the factory's shards into a run directory, or with --target another target's keypoint detector on
frames of it rendered as training goes. Here: the flags, the config and the printed line."""

from __future__ import annotations

import argparse
import os
import shlex
import sys

from envisat_pose.app.common import add_common, add_skip_damaged_argument, as_flags, skipped_line
from envisat_pose.app.flag_rules import not_applying, training_source
from envisat_pose.app.interrupts import interrupt_code
from envisat_pose.config import ConfigError, InputError
from envisat_pose.datagen.generate_config import layered_generate
from envisat_pose.pipelines.detector.look_mix import read_looks
from envisat_pose.pipelines.detector.train import (
    ddp_rank,
    default_render_workers,
    layered_train,
    missing_data,
    online_kind,
    train_detector,
)
from envisat_pose.pipelines.detector.train_records import (
    nothing_to_do_line,
    read_run_config,
    saved_online,
    trained_line,
)
from envisat_pose.shard_reader import skip_hint
from envisat_pose.target import other_target


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train",
        help="train the corner detector, or with --target FILE.xml a keypoint detector (run dir: config, metrics)",
        description="Train the L-CNN-style corner network on a dataset written by `envisat generate` (or with "
        "--online on frames rendered as it goes; --target: another target's keypoint network, online): crops "
        "around the target, style augmentation, checkpoints as safetensors. Under torchrun it trains with DDP.",
    )
    p.add_argument("--data", nargs="+", metavar="DIR", help="dataset folder(s) (shards + manifest.json), read together")
    p.add_argument("--online", action="store_true",
                   help="instead of --data: train on frames rendered as training goes (no files; crops and "
                   "augmentation on the device), each frame cropped at most --uses-per-frame times")
    p.add_argument("--target", metavar="FILE.xml", help="another spacecraft's MJCF file: train its keypoint "
                   "detector online (--online implied, --resolution default 512; ENVISAT's file: its corners)")
    p.add_argument("--generate-config", metavar="FILE.toml", help="--online: the look, as `envisat generate "
                   "--config` takes it (random mode)")
    p.add_argument("--looks", metavar="FILE.toml", help="--online: a mix of looks instead, [[look]] tables of a "
                   "name, a weight and generate keys (random or sequence mode; docs/usage.md)")
    p.add_argument("--resolution", type=int, metavar="PX", help="--online: the renders' side (1024; --target 512)")
    p.add_argument("--uses-per-frame", type=int, metavar="K", help="--online: crops per rendered frame (1-8, default 8)")
    p.add_argument("--render-workers", type=int, metavar="N", help="--online: renderer processes (default: the "
                   "usable cores less one, at least 1, at most what the memory holds)")
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="run directory (created with its parents)")
    p.add_argument("--config", metavar="FILE.toml", help="training config (keys of TrainConfig, [model], [data], [loss])")
    p.add_argument("--resume", action="store_true", help="go on from the run directory's last checkpoint, with its "
                   "own config (--steps and --time-budget-s may change; the data may not); Ctrl-C writes one")
    p.add_argument("--init", metavar="WEIGHTS", help="start from these weights (same architecture; fine-tuning)")
    p.add_argument("--backbone", metavar="WEIGHTS", help="a new run's backbone: any detector's weights, 'shipped' "
                   "(ENVISAT's; a new --target run's default where it fits) or 'none'; not with --init")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="cpu (default) or cuda")
    p.add_argument("--steps", type=int, help="optimizer steps in all (default 20000; with --time-budget-s a cap)")
    p.add_argument("--batch-size", type=int, help="samples per batch and rank (default 16)")
    p.add_argument("--seed", type=int, help="root seed (default 0)")
    p.add_argument("--time-budget-s", type=float, metavar="S", help="train for S seconds (S > 0): the rate decays "
                   "over them, the run stops inside them with a checkpoint; --resume: S s more (default: --steps)")
    p.add_argument("--workers", type=int, metavar="N", help="DataLoader processes building the batches (default: "
                   "the usable cores less one, at most a shard each; 0: in this process; a resumed run keeps its own)")
    p.add_argument("--bf16", action="store_true", help="bfloat16 autocast of the network (CUDA or CPU)")
    p.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    add_common(p)  # the shared --quiet
    add_skip_damaged_argument(p)
    p.set_defaults(func=run_train_cli, flag_names=FLAGS)


def resolve_config(args: argparse.Namespace):
    """Defaults (a resumed run's own config), then the TOML file, then the flags; validated before any work. The
    config class: ENVISAT's TrainConfig, or another target's KeypointTrainConfig (--target, a run's, a file's)."""
    base = read_run_config(args.out) if args.resume and os.path.isdir(args.out) else {}
    if args.steps is not None and args.time_budget_s is None:
        base.pop("time_budget_s", None)  # a resumed budgeted run given --steps trains to that step
    flags = {"steps": args.steps, "batch_size": args.batch_size, "seed": args.seed,
             "time_budget_s": args.time_budget_s, "target": other_target(args.target)}
    return layered_train(args.target, base, args.config, flags)


def online_config(args: argparse.Namespace, cfg):
    """The online source of the flags (a resumed online run: its own, renderer processes from the flag), or None;
    another target's run (cfg's) is online, its renders that target's (pipelines/detector/train.online_kind)."""
    kind, defaults = online_kind(cfg)
    saved = saved_online(args.out, args.resume, args.config, cfg, args.data)  # a resumed or rerun online run's
    args.online = args.online or saved is not None or "target" in defaults  # a resumed online run; a target's
    training_source(args)
    if saved is not None and not (args.looks or args.generate_config or args.resolution):  # its looks, else
        return kind.from_record(saved, args.render_workers, args.uses_per_frame)  # checked as other data would be
    if not args.online:
        if args.data is None:
            raise missing_data(args.out, args.resume)
        not_applying(args, ("looks", "generate_config", "resolution", "uses_per_frame", "render_workers"),
                     "a flag of --online training (rendered frames), not of training on --data's shards")
        return None
    if args.looks:
        if args.generate_config or args.resolution:
            raise InputError("--looks and --generate-config/--resolution: the looks file holds every look's config")
        gen = read_looks(args.looks)
    else:
        gen = layered_generate(defaults, args.generate_config, {"resolution_px": args.resolution})
    uses = {} if args.uses_per_frame is None else {"uses_per_frame": args.uses_per_frame}
    return kind(gen, args.render_workers or default_render_workers(), **uses)


def resume_command(args: argparse.Namespace) -> str:
    """The command that goes on with an interrupted run: its data (a resumed run rereads its shards) and folder."""
    data, world = ["--data", *args.data] if args.data else [], os.environ.get("WORLD_SIZE", "").strip() or "1"
    launch = ["envisat"] if world == "1" else ["torchrun", "--nproc-per-node", world, "--master-addr", "127.0.0.1",
                                               "-m", "envisat_pose.app.cli"]  # a DDP run resumes as it ran
    return shlex.join([*launch, "train", "--resume", *data, "--out", args.out])


# the library's argument and config field names -> this verb's flags (its errors name what the user typed)
FLAGS = {"data_dirs": "--data", "data": "--data", "run_dir": "--out", **{k: "--" + k.replace("_", "-") for k in
         "init resume backbone workers threads time_budget_s device steps batch_size seed online target".split()},
         "online.workers": "--render-workers"}


def run_train_cli(args: argparse.Namespace) -> int:
    from envisat_pose.perception.train import TrainingInterrupted

    try:
        cfg = resolve_config(args)
        online = online_config(args, cfg)
        with skip_hint():
            last = train_detector(cfg, [] if online else args.data, args.out, resume=args.resume, init=args.init,
                                  backbone=args.backbone, device=args.device, workers=args.workers, bf16=args.bf16,
                                  threads=args.threads, progress=not args.quiet,
                                  command=shlex.join(["envisat", *getattr(args, "argv", [])]),  # as typed
                                  skip_damaged=args.skip_damaged, online=online)
    except ConfigError as err:  # a value of a flag: named as the flag
        raise InputError(as_flags(str(err), FLAGS)) from None
    except TrainingInterrupted as stop:
        hint = f"; go on with: {resume_command(args)}" if stop.step else ""
        if ddp_rank() == 0:  # said once, not by every DDP rank
            print(f"envisat train: {stop}{hint}", file=sys.stderr)
        return interrupt_code(stop)  # 143 after SIGTERM, as every verb
    if ddp_rank() != 0:
        return 0  # rank 0 says how the run ended
    if skipped_line(last.get("skipped_damaged_shards", [])):
        print(skipped_line(last["skipped_damaged_shards"]))
    if last.get("stopped_by") == "nothing_to_do":
        print(nothing_to_do_line(args.out, last, cfg.time_budget_s))
        return 0
    print(trained_line(args.out, last))
    return 0
