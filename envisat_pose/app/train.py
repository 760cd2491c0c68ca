"""`envisat train`: train the corner detector on the factory's shards into a run directory."""

from __future__ import annotations

import argparse
import os
import subprocess

from envisat_pose.config import InputError, resolve_job_config


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train",
        help="train the corner detector on WebDataset shards (run directory with config, metrics, checkpoints)",
        description="Train the L-CNN-style corner network on a dataset written by `envisat generate`: crops "
        "around the target, style augmentation, checkpoints as safetensors. Under torchrun it trains with DDP.",
    )
    p.add_argument("--data", required=True, nargs="+", metavar="DIR",
                   help="dataset folder(s) (shards + manifest.json); several are read together")
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="run directory (created)")
    p.add_argument("--config", metavar="FILE.toml", help="training config (keys of TrainConfig, [model], [data], [loss])")
    p.add_argument("--resume", action="store_true", help="go on from the run directory's last checkpoint")
    p.add_argument("--init", metavar="WEIGHTS", help="start from these weights (same architecture; fine-tuning)")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="cpu (default) or cuda")
    p.add_argument("--steps", type=int, help="optimizer steps in all (default 20000)")
    p.add_argument("--batch-size", type=int, help="samples per batch and rank (default 16)")
    p.add_argument("--seed", type=int, help="root seed (default 0)")
    p.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_train_cli)


def git_hash() -> str:
    """The source's commit (with '+dirty' when the tree has changes), or 'unknown' outside a checkout."""
    here = os.path.dirname(os.path.abspath(__file__))
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=10)
        if head.returncode != 0:
            return "unknown"
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                               capture_output=True, text=True, timeout=10)
        return head.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def resolve_config(args: argparse.Namespace):
    """Defaults, then the TOML file, then the flags; validated before any work."""
    from envisat_pose.perception.train import TrainConfig

    flags = {"steps": args.steps, "batch_size": args.batch_size, "seed": args.seed}
    return resolve_job_config(TrainConfig, {}, args.config, flags)


def _init_distributed(device: str):
    """torchrun sets WORLD_SIZE/RANK/MASTER_ADDR: start the process group (gloo on CPU, nccl on CUDA)."""
    import torch
    import torch.distributed as dist

    if int(os.environ.get("WORLD_SIZE", "1")) <= 1 or dist.is_initialized():
        return device
    dist.init_process_group("nccl" if device == "cuda" else "gloo")
    if device == "cuda":
        local = int(os.environ.get("LOCAL_RANK", "0"))
        torch.cuda.set_device(local)
        return f"cuda:{local}"
    return device


def _end_distributed() -> None:
    """Tear the process group down before the interpreter exits: a rank that leaves with gloo's threads still
    running can abort ('terminate called without an active exception'; seen in CI on a loaded machine)."""
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        try:
            dist.barrier()
        finally:
            dist.destroy_process_group()


def run_train_cli(args: argparse.Namespace) -> int:
    import torch

    from envisat_pose.perception.data import shard_paths
    from envisat_pose.perception.train import train

    cfg = resolve_config(args)
    for d in args.data:
        shard_paths(d)  # an empty or missing dataset fails before any work
    if args.init is not None and args.resume:
        raise InputError("--init and --resume: a resumed run goes on from its own checkpoint; give one of them")
    if args.init is not None and not os.path.isfile(args.init):
        raise InputError(f"--init {args.init!r}: no such weights file")
    if args.resume and not os.path.isdir(args.out):
        raise InputError(f"--resume: {args.out!r} does not exist")
    if args.threads is not None:
        if args.threads < 1:
            raise InputError(f"--threads {args.threads}: expected at least 1")
        torch.set_num_threads(args.threads)
    device = _init_distributed(args.device)
    flags = {k: v for k, v in sorted(vars(args).items()) if k not in ("func", "verb") and v not in (None, False)}

    def flag(key, value) -> str:
        shown = "" if value is True else " " + (" ".join(map(str, value)) if isinstance(value, list) else str(value))
        return f"--{key.replace('_', '-')}{shown}"

    provenance = {"command": "envisat train " + " ".join(flag(k, v) for k, v in flags.items()), "git": git_hash(),
                  "data": [os.path.abspath(d) for d in args.data], "torch": torch.__version__, "device": device}
    if args.init is not None:
        from envisat_pose.io import sha256_file
        provenance["init"] = {"path": os.path.abspath(args.init), "sha256": sha256_file(args.init)}
    try:
        last = train(cfg, args.data, args.out, resume=args.resume, device=device, progress=not args.quiet,
                     provenance=provenance, init_weights=args.init)
    finally:
        _end_distributed()
    print(f"trained to step {last.get('step')}: loss {last.get('loss', float('nan')):.4f}; run in {args.out}")
    return 0
