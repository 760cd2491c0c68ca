"""The pipeline of `envisat train`: the corner detector trained on the factory's shards into a run directory, or
(a perception.keypoint_train.KeypointTrainConfig, `envisat train --target FILE.xml`) another target's keypoint
detector trained on frames of that target rendered as training goes (TargetOnlineConfig; run_task picks the Task).

Around the stage's loop (perception/train.py, its batches from worker processes, perception/stream.py): the
inputs checked before any work, torch.distributed started and ended under torchrun (gloo on CPU, nccl on CUDA),
the CUDA speed settings, and the run's provenance (the command, the git hash, the datasets by name and manifest
hash, the initial weights by name and hash; no path of the machine it ran on).
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass

from envisat_pose.config import InputError, check, from_dict, load_toml, path_arg, paths_arg, resolve_job_config
from envisat_pose.datagen.generate_config import GenerateConfig
from envisat_pose.datagen.gl_check import check_gl_platform
from envisat_pose.io import sha256_file
from envisat_pose.out_dirs import check_makeable
from envisat_pose.out_lock import output_lock
from envisat_pose.perception.weights_keys import MODEL_CONFIG_KEY
from envisat_pose.pipelines.common.threads import default_torch_threads
from envisat_pose.pipelines.detector.look_mix import WeightedLook, as_looks, look_shares
from envisat_pose.pipelines.detector.online import MAX_USES_PER_FRAME, online_batches, run_configs, run_identity
from envisat_pose.pipelines.detector.render_pool import RENDERER_BYTES, looks_keypoints
from envisat_pose.pipelines.detector.train_records import online_record, read_run_record, saved_online
from envisat_pose.pools import MAX_WORKERS, default_processes, torchrun_int, usable_cores, warn_oversubscribed
from envisat_pose.provenance import git_hash, manifest_sha256
from envisat_pose.shard_reader import checked_shards, load_dataset_manifest
from envisat_pose.target import (
    DEFAULT_TARGET,
    is_default_file,
    load_target,
    other_target,
    require_envisat,
    require_envisat_dataset,
)
from envisat_pose.written_target import recorded_target_checked

TARGET_RESOLUTION_PX = 512  # another target's renders when none is given (its keypoint network's crops)


@dataclass(frozen=True)
class OnlineConfig:
    """Training on frames as they are rendered (pipelines/detector/online.py) instead of shards. looks: what is rendered,
    a GenerateConfig (frame f is sample f of the dataset it would generate; its seed, resolution, appearance and
    corruption) or a sequence of online.WeightedLook (a mix by weight: resolutions, cameras, scenarios), kept as a tuple
    of Looks; workers: renderer processes; uses_per_frame: K, the most crops any frame gives (1-8). Validated
    when built."""

    looks: object
    workers: int = 1
    uses_per_frame: int = 8

    def __post_init__(self) -> None:
        object.__setattr__(self, "looks", as_looks(self.looks))
        self.check_target()
        check(isinstance(self.workers, int) and 1 <= self.workers <= MAX_WORKERS, "online.workers", self.workers,
              f"1 to {MAX_WORKERS} renderer processes")  # each holds a renderer (RENDERER_BYTES)
        check(isinstance(self.uses_per_frame, int) and 1 <= self.uses_per_frame <= MAX_USES_PER_FRAME,
              "online.uses_per_frame", self.uses_per_frame, f"an integer in [1, {MAX_USES_PER_FRAME}]")

    def check_target(self) -> None:
        """Every look shows ENVISAT (the corner network's target); ConfigError naming the look otherwise."""
        for look in self.looks:
            require_envisat(look.generate.target, f"looks.{look.name}.generate.target", "train")

    def record(self) -> dict:
        """What config.json keeps of it (a resumed run rebuilds it from this): the looks with their shares of the
        period, the renderer processes and K."""

        looks = [dict(look.record(), share=int(n)) for look, n in zip(self.looks, look_shares(self.looks))]
        return {"looks": looks, "workers": self.workers, "uses_per_frame": self.uses_per_frame}

    @classmethod
    def from_record(cls, record: dict, workers: int | None = None, uses_per_frame: int | None = None
                    ) -> "OnlineConfig":
        """From record()'s dict, or an earlier run's with one 'generate' config; workers, uses_per_frame: the
        record's unless given (a resume given another K is refused by its run's identity, naming K)."""

        if "looks" in record:
            looks = tuple(WeightedLook.from_record({k: v for k, v in r.items() if k != "share"}, "online.looks")
                          for r in record["looks"])
        else:
            looks = from_dict(GenerateConfig, record["generate"], "online.generate")
        return cls(looks, workers or int(record.get("workers", 1)), int(uses_per_frame or record["uses_per_frame"]))


class TargetOnlineConfig(OnlineConfig):
    """The OnlineConfig of another target's keypoint network (perception/keypoint_train.py): every look shows one
    target file, not ENVISAT's (ConfigError naming the look otherwise)."""

    def check_target(self) -> None:
        looks_keypoints(self.looks)  # one target file (by its sha256) for every look
        for look in self.looks:
            check(not is_default_file(look.generate.target), f"looks.{look.name}.generate.target",
                  look.generate.target, "another target than ENVISAT (`envisat train --target FILE.xml`)")


def target_online(target: str, resolution_px: int = TARGET_RESOLUTION_PX, workers: int = 1,
                  uses_per_frame: int = 8, **generate) -> TargetOnlineConfig:
    """The default source of a keypoint run: random views of `target` (its sized ranges and its own materials,
    varied) at resolution_px, generate's other GenerateConfig fields as given."""
    gen = GenerateConfig(mode="random", target=target, resolution_px=resolution_px, **generate)
    return TargetOnlineConfig(gen, workers, uses_per_frame)


def train_config_class(given: str | None, saved: dict, config_path: str | None = None) -> type:
    """The config class `envisat train` resolves: perception.keypoint_train.KeypointTrainConfig for another
    target (given, the resumed run's saved config holds one, or the TOML file at config_path names one, as a run's
    train.config.toml does), else perception.train.TrainConfig."""
    from envisat_pose.perception.keypoint_train import KeypointTrainConfig
    from envisat_pose.perception.train import TrainConfig

    in_file = load_toml(config_path) if config_path else {}
    return KeypointTrainConfig if other_target(given) or "target" in saved or "target" in in_file else TrainConfig


def layered_train(given: str | None, base: dict, config_path: str | None, flags: dict):
    """The config `envisat train` resolves (of train_config_class's class; given: --target as typed): `base` (a
    resumed run's own config), the TOML file at config_path and the flags, each over the last
    (config.resolve_job_config); a written train.config.toml's record of its target file set aside, the file
    checked against it (written_target.recorded_target_checked: a rerun refuses the file once it changed)."""
    return resolve_job_config(train_config_class(given, base, config_path), base, config_path, flags,
                              recorded_target_checked(config_path, "train"))


def online_kind(cfg) -> tuple[type, dict]:
    """(the OnlineConfig class of a training config, the GenerateConfig defaults of its renders): another
    target's keypoint run renders that target at TARGET_RESOLUTION_PX (TargetOnlineConfig), ENVISAT's corner run
    takes GenerateConfig's own (OnlineConfig); random mode both."""
    target = getattr(cfg, "target", None)  # a KeypointTrainConfig's
    if target is None:
        return OnlineConfig, {"mode": "random"}
    return TargetOnlineConfig, {"mode": "random", "target": target, "resolution_px": TARGET_RESOLUTION_PX}


def missing_data(run_dir: str, resume: bool) -> InputError:
    """The error of a run given neither shards nor online frames; a resumed run on shards is told to give its data
    again (the run records each folder by name and manifest hash, not by path)."""
    if resume and not os.path.isdir(run_dir):
        return InputError(f"run_dir {run_dir!r}: nothing to resume (no such folder)")
    if resume:
        names = ", ".join(d.get("name", "?") for d in read_run_record(run_dir).get("data") or [])
        return InputError(f"run_dir {run_dir!r} trained on shards ({names or 'its data'}): give them again with "
                          "`data_dirs` (the run records each folder by name and manifest hash, not by path)")
    return InputError("give `data_dirs` (shards) or `online` (frames rendered as training goes)")


def run_threads(run_dir: str) -> int | None:
    """The torch CPU threads the run in run_dir trained with (its config.json's `threads`; None: not recorded, a
    run from before it was, or no run: resume's own checks say so): a resumed run takes them again, since its
    floats depend on them."""
    try:
        threads = read_run_record(run_dir).get("threads")
    except InputError:
        return None
    return threads if type(threads) is int and threads >= 1 else None


def _ranks(variable: str) -> int:
    return max(1, torchrun_int(variable, 1))


def default_workers(shards: int | None = None, images: int | None = None, batch_size: int = 1) -> int:
    """DataLoader workers when none are asked for: the usable cores (shared among the node's torchrun ranks) less
    one for the training process itself; 0 (in-process) on one core; and no more workers than a rank's `shards`
    (each worker reads its own) or its `images` make batches of batch_size (each worker batches its own, its
    partial last batch dropped: more workers than that left an epoch without a batch on a machine with more
    cores, where a smaller one trained); where given."""
    n = max(0, usable_cores() // _ranks("LOCAL_WORLD_SIZE") - 1)
    world = _ranks("WORLD_SIZE")
    for units in (shards, None if images is None else images // max(1, batch_size)):
        if units is not None:
            n = min(n, max(1, units // world))
    return n


def default_render_workers() -> int:
    """Renderer processes of an online run when none are asked for: default_workers() (at least 1), no more than
    the usable memory holds at RENDERER_BYTES each for the node's ranks (63 renderers, a 64-core machine's default
    count, take ~67 GB)."""
    return default_processes(max(1, default_workers()), RENDERER_BYTES * _ranks("LOCAL_WORLD_SIZE"))


def dataset_provenance(data_dir: str, skipped: list[str] = ()) -> dict:
    """A dataset by its folder's name, its manifest's sha256 and image count (None where it has no manifest): the
    images trained on, the shards `skipped` (damaged, --skip-damaged) left out."""
    manifest = load_dataset_manifest(data_dir, "data_dirs", required=False)
    record = {"name": os.path.basename(os.path.normpath(data_dir)), "manifest_sha256": manifest_sha256(data_dir),
              "images": None}
    if manifest is not None and isinstance(manifest.get("num_images"), int) and manifest["num_images"]:
        left_out = sum(sh.get("count", 0) for sh in manifest["shards"] if sh["name"] in skipped)
        record["images"] = manifest["num_images"] - left_out
    return record


def dataset_images(data: list[dict]) -> int | None:
    """The images of the datasets' records (dataset_provenance's), None where one has no manifest to count them."""
    images = [d["images"] for d in data]
    return None if None in images else sum(images)


def check_inputs(data_dirs: list[str], run_dir: str, resume: bool, init: str | None, workers: int | None,
                 threads: int | None, online: bool = False, target: str = DEFAULT_TARGET,
                 backbone: str | None = None, device: str = "cpu") -> None:
    """Every input of a training run but the shards checked before any work; InputError naming the argument (init:
    weights of another target than `target`, the one trained, are refused in one line; backbone: any detector's
    weights, a new run's alone; device: 'cpu', 'cuda' or 'cuda:N', as the verb's --device)."""
    if not (isinstance(device, str) and re.fullmatch(r"cpu|cuda(:\d+)?", device)):
        raise InputError(f"device {device!r}: expected 'cpu' or 'cuda' (or 'cuda:N')")

    if not data_dirs and not online:
        raise InputError("data_dirs: no dataset folder given")
    if online:
        check_gl_platform()  # its renderer processes' platform, refused here rather than in each of them
    for folder in data_dirs:
        require_envisat_dataset(folder, "data_dirs", "train")
    if init is not None and resume:
        raise InputError("init and resume: a resumed run goes on from its own checkpoint; give one of them")
    if init is not None and not os.path.isfile(init):
        raise InputError(f"init {init!r}: no such weights file")
    if init is not None:
        from envisat_pose.perception.weights import check_weights_target  # torch

        check_weights_target(init, target, "init")
    if backbone is not None and (init is not None or resume):
        raise InputError("backbone and " + ("init" if init is not None else "resume") + ": the backbone starts a new "
                         "run's network; " + ("init gives the whole network" if init is not None else
                                              "a resumed run goes on from its own checkpoint"))
    if backbone is not None and not os.path.isfile(backbone):
        raise InputError(f"backbone {backbone!r}: no such weights file")
    if backbone is not None:
        from envisat_pose.perception.weights import read_header  # torch

        read_header(backbone)  # a file that is not safetensors: refused here; a backbone of another shape when built
    if resume and not os.path.isdir(run_dir):
        raise InputError(f"run_dir {run_dir!r} does not exist: nothing to resume")
    check_makeable(run_dir, field="run_dir")  # a file, a path under one, or a place that takes no folder
    if workers is not None and not 0 <= workers <= MAX_WORKERS:  # 2^63 - 1: a DataLoader forking without end
        raise InputError(f"workers = {workers}: expected 0 (in-process) to {MAX_WORKERS} worker processes")
    if threads is not None and not 1 <= threads <= MAX_WORKERS:  # 2^31 or more: a ValueError from torch
        raise InputError(f"threads = {threads}: expected 1 to {MAX_WORKERS} threads")


def warn_processes(workers: int | None, online) -> None:
    """pools.warn_oversubscribed for the processes a run was given: its renderers (RENDERER_BYTES each) online,
    else its DataLoader workers, each of the machine's torchrun ranks (LOCAL_WORLD_SIZE) starting its own."""
    if online is not None:
        warn_oversubscribed(online.workers, "online.workers", RENDERER_BYTES, ranks=_ranks("LOCAL_WORLD_SIZE"))
    elif workers:
        warn_oversubscribed(workers, ranks=_ranks("LOCAL_WORLD_SIZE"))


def ddp_rank() -> int:
    """This process's rank under torchrun (its RANK where WORLD_SIZE > 1), else 0."""
    return torchrun_int("RANK", 0) if torchrun_int("WORLD_SIZE", 1) > 1 else 0


def init_distributed(device: str) -> str:
    """torchrun sets WORLD_SIZE/RANK/MASTER_ADDR: start the process group (gloo on CPU, nccl on CUDA). Returns
    this rank's device."""
    import torch
    import torch.distributed as dist

    if torchrun_int("WORLD_SIZE", 1) <= 1 or dist.is_initialized():
        return device
    dist.init_process_group("nccl" if device == "cuda" else "gloo")
    if device == "cuda":
        local = torchrun_int("LOCAL_RANK", 0)
        torch.cuda.set_device(local)
        return f"cuda:{local}"
    return device


def end_distributed() -> None:
    """Tear the process group down before the interpreter exits: a rank that leaves with gloo's threads still
    running can abort ('terminate called without an active exception'; about 1 run in 30 of a 2-rank run on a
    2-core machine, and in CI). torch imports parts of itself lazily inside the first training call, and one of
    them (torch.fx's wrap) keeps its own frame in a local: a reference cycle whose frames' f_back chain holds
    train()'s locals, the DistributedDataParallel (whose reducer holds the group) among them, until a garbage
    collection. Collected first, here, the group is really freed by destroy_process_group rather than during the
    interpreter's finalization."""
    import gc

    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        gc.collect()
        try:
            dist.barrier()
        finally:
            dist.destroy_process_group()


def default_online(cfg, run_dir: str, resume: bool) -> OnlineConfig | None:
    """The online source `envisat train` takes where none is given and no shards: a resumed online run's own (its
    config.json), else another target's default renders (online_kind: at TARGET_RESOLUTION_PX), else None."""
    kind, defaults = online_kind(cfg)
    saved = saved_online(run_dir, resume, None, cfg, None) if os.path.isfile(os.path.join(run_dir, "config.json")) \
        else None
    if saved is not None:
        return kind.from_record(saved)
    return kind(GenerateConfig(**defaults), default_render_workers()) if "target" in defaults else None


def run_task(cfg, online: OnlineConfig | None) -> tuple:
    """(perception's Task, the Target or None) of a training config: a KeypointTrainConfig's target's keypoint
    network (perception/keypoint_train.py; InputError unless online renders that target's file), else ENVISAT's
    corner network (perception.train.CORNERS, None)."""
    from envisat_pose.perception.keypoint_train import KeypointTrainConfig, keypoint_task
    from envisat_pose.perception.train import CORNERS

    if not isinstance(cfg, KeypointTrainConfig):
        return CORNERS, None
    target = load_target(cfg.target, "target")
    if online is None:
        raise InputError(f"online: target {target.name!r}'s keypoint detector trains on frames of it rendered as "
                         "training goes (TargetOnlineConfig), not on shards")
    shown = load_target(online.looks[0].generate.target, "online.looks")
    if shown.sha256 != target.sha256:
        raise InputError(f"online: its looks show target {shown.name!r} ({online.looks[0].generate.target}), the "
                         f"config trains {target.name!r} ({cfg.target}): one target file for both")
    return keypoint_task(target), target


def online_source(online: OnlineConfig, cfg, device: str, task, target) -> tuple[list[dict], object]:
    """(the data record of config.json, the batch source train() takes) of an online run: the record's hash is
    the run's identity (online.run_identity), with the target file's sha256 folded in for a keypoint run (a
    resumed run refuses a changed target file as it refuses other data)."""
    import hashlib

    identity = run_identity(online.looks, cfg.data, cfg.seed, cfg.batch_size, online.uses_per_frame)
    sha = identity["config_sha256"]
    if target is not None:
        sha = hashlib.sha256(f"{sha} {target.sha256}".encode()).hexdigest()
    mix = ", ".join(f"{look.name} {n} %" for look, n in zip(online.looks, look_shares(online.looks)))
    what = "" if target is None else f"target {target.name}, "
    data = [{"name": f"online ({what}{mix}, K = {online.uses_per_frame})", "manifest_sha256": sha, "images": None,
             "configs": json.loads(json.dumps(run_configs(online.looks, cfg.data), sort_keys=True))}]
    if target is not None:
        data[0]["target_sha256"] = target.sha256  # named apart, so a resume can say the target file changed

    def source(start_state):
        return online_batches(online.looks, cfg.data, cfg.seed, cfg.batch_size, online.workers, device,
                              online.uses_per_frame, start_state, task.online_batch, stream=ddp_rank())
    return data, source


SHARED_SHAPE = ("width", "depth", "stem_width")  # the backbone's shape (perception/model.py check_backbone)


def resolve_backbone(backbone: str | None, cfg, new_target_run: bool) -> str | None:
    """The weights file a run's backbone starts from. backbone: a weights file; 'shipped': ENVISAT's shipped corner
    network; 'none': none (from scratch); None, the default: ENVISAT's shipped network for a new run of another
    target's keypoint detector (new_target_run: no init, not resumed) whose model has its backbone's shape
    (SHARED_SHAPE; at the same training time it starts far ahead of scratch: docs/usage.md), else none."""
    if backbone == "none":
        return None
    if backbone is None and not new_target_run:
        return None
    from envisat_pose.perception.weights import read_header, shipped_weights_path  # torch

    if backbone not in (None, "shipped"):
        return backbone
    shipped = shipped_weights_path()
    if backbone is None:
        theirs = json.loads(read_header(shipped).get(MODEL_CONFIG_KEY, "{}"))
        ours = cfg.model.to_dict()
        if any(theirs.get(k) != ours.get(k) for k in SHARED_SHAPE):
            return None
    return shipped


def train_config_arg(cfg):
    """cfg when it is a TrainConfig (ENVISAT's corner detector) or a KeypointTrainConfig (another target's), else
    InputError naming `cfg`: anything else reached the data's check (None) or failed once training began (a dict)."""
    from envisat_pose.perception.keypoint_train import KeypointTrainConfig
    from envisat_pose.perception.train import TrainConfig

    if not isinstance(cfg, (TrainConfig, KeypointTrainConfig)):
        raise InputError(f"cfg: expected a TrainConfig or a KeypointTrainConfig, got {type(cfg).__name__} "
                         f"({cfg!r:.60})")
    return cfg


def train_detector(cfg, data_dirs: str | list[str], run_dir: str, *, resume: bool = False,
                   init: str | None = None, device: str = "cpu", workers: int | None = None, bf16: bool = False,
                   threads: int | None = None, progress: bool = False, command: str = "",
                   skip_damaged: bool = False, online: OnlineConfig | None = None,
                   backbone: str | None = None) -> dict:
    """Train the detector (cfg: a perception TrainConfig, validated when built) on the shards of data_dirs (one
    folder or several) into run_dir (locked: out_lock; its files written once the first step is trained). cfg a
    perception.keypoint_train.KeypointTrainConfig: another target's keypoint detector, online only (online a
    TargetOnlineConfig of that target file; none given: target_online's at TARGET_RESOLUTION_PX, or on resume the
    run's own, as the verb), the target recorded in
    config.json ('target') and in every weights file.

    resume: go on from run_dir's last checkpoint (exclusive with init: a safetensors file to start from); the
    config may differ from the run's in steps and time_budget_s only, the data not at all (InputError spelling
    out the difference). backbone: any detector's weights (another target's keypoint network; 'shipped': ENVISAT's
    shipped corner network) whose stem, hourglass and neck start a new run's network, its heads seeded (transfer;
    exclusive with init and resume), recorded by name and sha256 in config.json; None (the default): ENVISAT's for
    a new run of another target of the same backbone shape, none otherwise; 'none': none (resolve_backbone). workers: DataLoader worker
    processes (None: the run's own on resume, else default_workers()); bf16: bfloat16 autocast; threads: torch's CPU threads in this process; command: the
    command line as typed, for the record. Every shard is checked against its dataset's manifest first (size,
    then sha256: envisat_pose.shard_reader.checked_shards); a damaged one stops the run before anything is
    written (DamagedShardError naming it) unless skip_damaged, which leaves it out and records it in config.json
    (skipped_damaged_shards) and the end line. online: train on frames rendered as training goes instead
    (data_dirs then empty; OnlineConfig), recorded in config.json under 'online'; the end line then holds
    uses_per_frame, max_uses (the most crops any frame gave) and frame_ms (a frame's cost in its worker).
    Returns the run's last metrics line (perception/train.py); raises
    perception.train.TrainingInterrupted after a checkpoint when SIGINT or SIGTERM stopped it. Callable from a
    plain script: its workers never import the script. run_dir is locked while it trains (out_lock: a second job
    on it is refused), after the checks of the arguments."""
    cfg = train_config_arg(cfg)
    data_dirs, run_dir = paths_arg(data_dirs, "data_dirs") if data_dirs else [], path_arg(run_dir, "run_dir")
    if online is not None and data_dirs:
        raise InputError("data_dirs and online: train on shards or on frames rendered as training goes, not both")
    if online is None and not data_dirs:  # as the verb: a resumed online run's own looks, a target's default renders
        online = default_online(cfg, run_dir, resume)
    if online is not None and workers is not None:  # as the verb's --workers on an online run; it was dropped
        raise InputError(f"workers = {workers}: the DataLoader processes reading data_dirs' shards; an online run's "
                         "frames come from its renderer processes (online.workers)")
    task, target = run_task(cfg, online)
    backbone = resolve_backbone(backbone, cfg, target is not None and init is None and not resume)
    check_inputs(data_dirs, run_dir, resume, init, workers, threads, online is not None,
                 DEFAULT_TARGET if target is None else cfg.target, backbone, device)
    if ddp_rank() == 0:  # said once, not by every rank
        warn_processes(workers, online)
    with output_lock(run_dir, "train", field="run_dir"):
        return _train_locked(cfg, data_dirs, run_dir, resume, init, device, workers, bf16, threads, progress,
                             command, skip_damaged, online, backbone, task, target)


def _train_locked(cfg, data_dirs: list[str], run_dir: str, resume: bool, init: str | None, device: str,
                  workers: int | None, bf16: bool, threads: int | None, progress: bool, command: str,
                  skip_damaged: bool, online, backbone: str | None, task, target) -> dict:
    """train_detector's run, its arguments checked and run_dir locked."""
    import torch

    from envisat_pose.perception.data import warn_shuffle_buffer
    from envisat_pose.perception.train import train

    if online is not None:
        workers = 0  # no DataLoader: the renderer processes are online.workers
    rank_device = init_distributed(device)
    if device == "cuda":  # speed over the last bits: TF32 matrix products, cuDNN's autotuned convolutions
        # (not online: its crops are resampling matrix products, which TF32 would round to ~0.1 gray level)
        torch.backends.cuda.matmul.allow_tf32 = online is None
        torch.backends.cudnn.allow_tf32 = torch.backends.cudnn.benchmark = True

    paths, skipped, data = [], [], []
    for d in data_dirs:
        mine, left_out = checked_shards(d, skip_damaged, "data_dirs")
        paths += mine
        skipped += [f"{os.path.basename(os.path.normpath(d))}/{name}" for name in left_out]
        data.append(dataset_provenance(d, left_out))
    if workers is None and not resume:  # as many as the shards and their batches keep busy
        workers = default_workers(len(paths), dataset_images(data), cfg.batch_size)
    if online is None and ddp_rank() == 0:  # once a run, not once a rank
        warn_shuffle_buffer(cfg.data, dataset_images(data))
    source = None
    if online is not None:
        data, source = online_source(online, cfg, rank_device, task, target)
    caller_threads = torch.get_num_threads()  # given back on the way out: a library call leaves torch as it was
    threads = threads or (run_threads(run_dir) if resume else None) or default_torch_threads()  # resumed: its own
    provenance = {"command": command, "git": git_hash(), "data": data, "torch": torch.__version__,
                  "device": device, "bf16": bf16, "threads": threads, "skipped_damaged_shards": skipped}
    if online is not None:
        provenance["online"] = online.record()
    if target is not None:
        provenance["target"] = {k: v for k, v in target.record(cfg.target).items() if k != "file"}
    for field, path in (("init", init), ("backbone", backbone)):  # the weights a new run starts from
        if path is not None:
            provenance[field] = {"name": os.path.basename(path), "sha256": sha256_file(path)}
    torch.set_num_threads(threads)  # the batches' floats depend on it: recorded, and a resumed run takes it again
    try:
        end = train(cfg, data_dirs, run_dir, resume=resume, device=rank_device, progress=progress,
                    provenance=provenance, init_weights=init, workers=workers, bf16=bf16, paths=paths,
                    online=source, task=task, backbone_weights=backbone)
        if online is not None:
            end = {**end, "uses_per_frame": online.uses_per_frame, **online_record(run_dir),
                   "render_workers": online.workers}
        return {**end, "skipped_damaged_shards": skipped}
    finally:
        torch.set_num_threads(caller_threads)
        end_distributed()
