"""torchrun with 2 processes (gloo, 127.0.0.1 only) trains a few steps; both ranks end with identical weights. The
run has a time budget it does not reach: every step shares rank 0's clock (the rate follows it), and the ranks
still agree bit for bit. And the group ends with nothing of the training left to hold it (a rank that freed it only
at exit could abort)."""

import json
import os
import socket
import subprocess
import sys

from envisat_pose.perception.weights import load_model


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_ranks_hold_identical_weights(tiny_dataset, tmp_path):
    toml = tmp_path / "t.toml"
    toml.write_text("checkpoint_every = 1000\nwarmup_steps = 2\n[model]\ninput_px = 64\nwidth = 16\ndepth = 2\n"
                    "stem_width = 8\n[data]\ninput_px = 64\n")
    run = tmp_path / "run"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "GLOO_SOCKET_IFNAME": "lo", "MASTER_ADDR": "127.0.0.1"}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nnodes", "1", "--nproc-per-node", "2",
           "--rdzv-backend", "static", "--master-addr", "127.0.0.1", "--master-port", str(free_port()),
           "--node-rank", "0", "-m", "envisat_pose.app.cli", "train", "--data", tiny_dataset, "--out", str(run),
           "--config", str(toml), "--steps", "3", "--batch-size", "2", "--threads", "1", "--quiet",
           "--time-budget-s", "600"]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    end = [json.loads(line) for line in open(run / "metrics.jsonl")][-1]
    assert end["kind"] == "end" and end["step"] == 3
    assert end["world"] == 2.0 and end["ranks_identical"] == 1.0 and end["stopped_by"] == "steps"
    assert json.load(open(run / "config.json"))["device"] == "cpu"
    load_model(str(run / "checkpoint.safetensors"))


PROBE = """
import gc, json, sys
import torch
import torch.distributed as dist
from envisat_pose.perception.data import DataConfig
from envisat_pose.perception.model import ModelConfig
from envisat_pose.perception.train import TrainConfig
from envisat_pose.pipelines.detector.train import train_detector

cfg = TrainConfig(steps=2, batch_size=2, warmup_steps=1, checkpoint_every=10 ** 6,
                  model=ModelConfig(input_px=64, width=16, depth=2, stem_width=8), data=DataConfig(input_px=64))
dist.init_process_group("gloo", store=dist.HashStore(), rank=0, world_size=1)
end = train_detector(cfg, [sys.argv[1]], sys.argv[2], workers=0, progress=False)
standing = dist.is_initialized()
live = sum(type(o) is torch.nn.parallel.DistributedDataParallel for o in gc.get_objects())
print(json.dumps({"world": end["world"], "step": end["step"], "standing": standing, "live_ddp": live}))
"""


def test_the_process_group_ends_with_no_training_object_holding_it(tiny_dataset, tmp_path):
    """A fresh interpreter, as a torchrun rank is (torch's first lazy imports happen inside the training call),
    with a gloo group of one: once train_detector returns, the group is gone and no DistributedDataParallel is
    left, not even as uncollected garbage (gc.get_objects lists it until a collection), so destroy_process_group
    freed the group while the interpreter was whole."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-c", PROBE, tiny_dataset, str(tmp_path / "run")], capture_output=True,
                          text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert got == {"world": 1.0, "step": 2, "standing": False, "live_ddp": 0}
