"""Training another target's keypoint network through the one Trainer (perception/train.py): its config
(KeypointTrainConfig: the TrainConfig's schedule, budget and data fields, the target, the keypoint model and loss)
and its Task (the seeded KeypointNet, the loss terms with the target's symmetric relabelings, the online batches).
Run folder, checkpoints, resume, the time budget, signals and DDP are the Trainer's hooks, as for ENVISAT's corners.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import torch

from envisat_pose.config import UNMARKED, check, filled_for, mark_filled
from envisat_pose.perception.keypoint_batch import keypoint_batch
from envisat_pose.perception.keypoint_loss import KeypointLossConfig, keypoint_losses, relabelings
from envisat_pose.perception.keypoint_net import KeypointModelConfig, init_keypoint_net
from envisat_pose.perception.train import Task, TrainConfig
from envisat_pose.target import is_default_file, load_target


@dataclass(frozen=True)
class KeypointTrainConfig(TrainConfig):
    """TrainConfig of another target's keypoint network. target: its MJCF file (envisat_pose/target.py; not
    ENVISAT's, whose detector is the corner network); model: KeypointModelConfig, num_keypoints filled in with the
    target's K when not given (and checked against it; filled in again for a config replaced with another
    target); loss: KeypointLossConfig. line_jitter_px is unused.
    Validated when built."""

    target: str = ""
    model: KeypointModelConfig = field(default_factory=KeypointModelConfig)
    loss: KeypointLossConfig = field(default_factory=KeypointLossConfig)

    def __post_init__(self) -> None:
        check(isinstance(self.target, str) and self.target != "", "target", self.target,
              "the target's MJCF file (--target FILE.xml)")
        check(not is_default_file(self.target), "target", self.target,
              "another target than ENVISAT (ENVISAT's detector is the corner network: `envisat train` without "
              "--target)")
        k = load_target(self.target).num_keypoints
        if self.model.num_keypoints is None or filled_for(self.model) not in (UNMARKED, self.target):
            # filled in here (marked: a config replaced with another target counts that target's keypoints)
            object.__setattr__(self, "model", mark_filled(replace(self.model, num_keypoints=k), self.target))
        check(self.model.num_keypoints == k, "model.num_keypoints", self.model.num_keypoints,
              f"the target's {k} keypoints")
        super().__post_init__()


def keypoint_task(target) -> Task:
    """The Task of a Target's keypoint network: init_keypoint_net seeded by cfg.seed recording the target
    (Target.record: name, sha256, keypoint names), keypoint_losses over relabelings(target.symmetries) (the
    identity and each symmetry its materials keep), keypoint_batch for the frames rendered as training goes."""
    record = {k: v for k, v in target.record(target.path).items() if k != "file"}
    perms_cpu = torch.as_tensor(relabelings(target.symmetries, target.num_keypoints))
    on_device: dict = {}

    def build(cfg: KeypointTrainConfig):
        return init_keypoint_net(cfg.model, cfg.seed, record)

    def terms(model, net, batch: dict, cfg: KeypointTrainConfig, step: int, dev: torch.device, bf16: bool) -> dict:
        image = batch["image"]
        if dev.type == "cuda":
            image = image.contiguous(memory_format=torch.channels_last)
        with torch.autocast(device_type=dev.type, dtype=torch.bfloat16, enabled=bf16):
            out = net(image)
        out = {k: v.float() for k, v in out.items()}
        perms = on_device.setdefault(str(dev), perms_cpu.to(dev))
        return keypoint_losses(out, batch, perms, cfg.loss)

    return Task(build, terms, keypoint_batch)
