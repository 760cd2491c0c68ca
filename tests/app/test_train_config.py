"""A training run's folder holds its TrainConfig as train.config.toml beside config.json (which a resume reads), the
source line under its first line, as every verb's written config: `envisat train --config` reads it back to the
same config, ENVISAT's corner network's and another target's keypoint network's (the file's `target` picks the
class, as --target does), and a resumed run's file follows its new steps."""

import dataclasses
from types import SimpleNamespace

import pytest

from envisat_pose.app.cli import build_parser
from envisat_pose.app.train import resolve_config
from envisat_pose.perception import trainer_hooks as th
from envisat_pose.perception.data import DataConfig
from envisat_pose.perception.keypoint_train import KeypointTrainConfig
from envisat_pose.perception.model import ModelConfig
from envisat_pose.perception.train import TrainConfig
from envisat_pose.provenance import source_line


def write_run_folder(cfg, run_dir, saved=None):
    """What RunFolder writes after a run's first step (saved: a resumed run's config.json), on a stand-in trainer."""
    folder = th.RunFolder(saved, {"command": "envisat train", "git": "abc"}, resumed_at=2 if saved else 0)
    folder.trainer = SimpleNamespace(run_dir=str(run_dir), rank=0, cfg=cfg, folder_started=False)
    folder.before_train()
    folder.after_step({})
    return run_dir / "train.config.toml"


def read_back(path, tmp_path):
    return resolve_config(build_parser().parse_args(["train", "--config", str(path), "--out", str(tmp_path / "x")]))


CONFIGS = {
    "envisat": TrainConfig(steps=7, batch_size=4, lr=1e-3, seed=5, time_budget_s=30.5, schedule="constant_cooldown",
                           ema_decay=0.9, model=ModelConfig(input_px=64, width=16, depth=2, stem_width=8),
                           data=DataConfig(input_px=64)),
    "upper_stage": KeypointTrainConfig(target="models/upper_stage.xml", steps=3, seed=2),
}


@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_train_config_toml_reads_back_to_the_runs_config(name, tmp_path):
    cfg = CONFIGS[name]
    path = write_run_folder(cfg, tmp_path / "run")
    lines = path.read_text().splitlines()
    assert lines[0] == "# envisat train: the full validated config of this run"
    assert lines[1] + "\n" == source_line()
    back = read_back(path, tmp_path)
    assert type(back) is type(cfg) and back == cfg
    assert (tmp_path / "run" / "config.json").is_file()  # what a resume reads, as before


def test_a_resumed_runs_train_config_toml_takes_its_new_steps(tmp_path):
    cfg = CONFIGS["envisat"]
    write_run_folder(cfg, tmp_path / "run")
    more = dataclasses.replace(cfg, steps=20, time_budget_s=None)
    path = write_run_folder(more, tmp_path / "run", saved={"train": cfg.to_dict(), "command": "envisat train"})
    assert read_back(path, tmp_path) == more


def test_a_folder_a_run_left_before_its_first_checkpoint_takes_a_new_run(tmp_path):
    """config.json and train.config.toml, written at the first step, are a run's files: a new run may start there
    (no state.json: nothing to resume)."""
    from envisat_pose.perception.train_run import start_state

    write_run_folder(CONFIGS["envisat"], tmp_path / "run")
    state, saved = start_state(str(tmp_path / "run"), CONFIGS["envisat"], False, None, None)
    assert state["step"] == 0 and saved is None


def test_a_target_runs_config_records_the_files_sha256_and_a_rerun_refuses_the_file_changed(tmp_path):
    """Another target's run: train.config.toml records the target file's sha256 beside it (target_sha256), as every
    written config that names a target file does; `envisat train --config` refuses the file once it changed, in
    one line naming it; another --target given over the file's is taken as it is."""
    import shutil
    import tomllib

    from envisat_pose.config import InputError
    from envisat_pose.target import resolve_target_path
    from envisat_pose.target_assets import target_sha256

    target = tmp_path / "upper_stage.xml"
    shutil.copy(resolve_target_path("models/upper_stage.xml"), target)
    cfg = KeypointTrainConfig(target=str(target), steps=3, seed=2)
    path = write_run_folder(cfg, tmp_path / "run")
    recorded = tomllib.loads(path.read_text())["target_sha256"]
    assert recorded == target_sha256(str(target))
    assert read_back(path, tmp_path) == cfg
    target.write_text(target.read_text() + "<!-- edited since -->\n")
    with pytest.raises(InputError, match=f"changed since the config was written.*{recorded[:12]}") as err:
        read_back(path, tmp_path)
    assert str(target) in str(err.value) and "\n" not in str(err.value)
    other = resolve_config(build_parser().parse_args(["train", "--config", str(path), "--target",
                                                      "models/upper_stage.xml", "--out", str(tmp_path / "x")]))
    assert other.target == "models/upper_stage.xml"


def test_a_rerun_from_an_online_runs_train_config_toml_renders_its_looks_again(tmp_path):
    """The file's header says `envisat train --config THIS_FILE` trains the run again, its online looks from
    config.json beside it: a --target run at --resolution 128 (K 3) rerun from it rendered at 512 (K 8), the
    default; another --target typed over the config's renders that target's defaults, --data its shards."""
    from envisat_pose.app.train import online_config
    from envisat_pose.pipelines.detector.train import target_online

    cfg = CONFIGS["upper_stage"]
    online = target_online(cfg.target, resolution_px=128, uses_per_frame=3)
    folder = th.RunFolder(None, {"command": "envisat train", "online": online.record()}, resumed_at=0)
    folder.trainer = SimpleNamespace(run_dir=str(tmp_path / "run"), rank=0, cfg=cfg, folder_started=False)
    folder.before_train()
    folder.after_step({})
    argv = ["train", "--config", str(tmp_path / "run" / "train.config.toml"), "--out", str(tmp_path / "x")]
    args = build_parser().parse_args(argv)
    again = online_config(args, resolve_config(args))
    assert again.looks == online.looks and again.uses_per_frame == 3
    other = build_parser().parse_args([*argv, "--target", "models/cubesat_3u.xml"])
    fresh = online_config(other, resolve_config(other))
    assert fresh.looks[0].generate.resolution_px == 512 and fresh.looks[0].generate.target == "models/cubesat_3u.xml"
