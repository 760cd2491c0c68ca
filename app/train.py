"""`envisat train`: the verb over the training pipeline (pipelines/train.py): the corner detector
trained on the factory's shards into a run directory. Here: the flags, the config and the printed line."""

from __future__ import annotations

import argparse
import os

from envisat_pose.config import resolve_job_config

PATH_FLAGS = ("data", "out", "config", "init")  # recorded by name only: no path of this machine in a run


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train",
        help="train the corner detector on WebDataset shards (run directory with config, metrics, checkpoints)",
        description="Train the L-CNN-style corner network on a dataset written by `envisat generate`: crops "
        "around the target, style augmentation, checkpoints as safetensors, batches built by worker processes "
        "(each reading its own shards). Under torchrun it trains with DDP.",
    )
    p.add_argument("--data", required=True, nargs="+", metavar="DIR",
                   help="dataset folder(s) (shards + manifest.json); several are read together")
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="run directory (created)")
    p.add_argument("--config", metavar="FILE.toml", help="training config (keys of TrainConfig, [model], [data], [loss])")
    p.add_argument("--resume", action="store_true", help="go on from the run directory's last checkpoint")
    p.add_argument("--init", metavar="WEIGHTS", help="start from these weights (same architecture; fine-tuning)")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="cpu (default) or cuda")
    p.add_argument("--steps", type=int, help="optimizer steps in all (default 20000; with --time-budget-s a cap)")
    p.add_argument("--batch-size", type=int, help="samples per batch and rank (default 16)")
    p.add_argument("--seed", type=int, help="root seed (default 0)")
    p.add_argument("--time-budget-s", type=float, metavar="S",
                   help="train for S seconds: the rate decays over them and the run stops inside them with a "
                   "checkpoint (default: over the steps)")
    p.add_argument("--workers", type=int, metavar="N",
                   help="DataLoader worker processes building the batches (default: the cores less one; 0: in this "
                   "process; a resumed run keeps its own)")
    p.add_argument("--bf16", action="store_true", help="bfloat16 autocast of the network (CUDA or CPU)")
    p.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_train_cli)


def resolve_config(args: argparse.Namespace):
    """Defaults, then the TOML file, then the flags; validated before any work."""
    from envisat_pose.perception.train import TrainConfig

    flags = {"steps": args.steps, "batch_size": args.batch_size, "seed": args.seed,
             "time_budget_s": args.time_budget_s}
    return resolve_job_config(TrainConfig, {}, args.config, flags)


def command_line(args: argparse.Namespace) -> str:
    """The command as run, its flags sorted, paths by their last name."""
    def shown(key, value) -> str:
        if value is True:
            return ""
        values = value if isinstance(value, list) else [value]
        if key in PATH_FLAGS:
            values = [os.path.basename(os.path.normpath(str(v))) for v in values]
        return " " + " ".join(map(str, values))

    flags = {k: v for k, v in sorted(vars(args).items()) if k not in ("func", "verb") and v not in (None, False)}
    return "envisat train " + " ".join(f"--{k.replace('_', '-')}{shown(k, v)}" for k, v in flags.items())


def run_train_cli(args: argparse.Namespace) -> int:
    from envisat_pose.pipelines.train import train_detector

    cfg = resolve_config(args)
    last = train_detector(cfg, args.data, args.out, resume=args.resume, init=args.init, device=args.device,
                          workers=args.workers, bf16=args.bf16, threads=args.threads, progress=not args.quiet,
                          command=command_line(args))
    print(f"trained to step {last.get('step')}: loss {last.get('loss', float('nan')):.4f}, "
          f"{last.get('samples_s', 0):.0f} samples/s with {last.get('workers')} workers "
          f"({last.get('stopped_by')}); run in {args.out}")
    return 0
