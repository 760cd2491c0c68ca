"""The Trainer's hooks one at a time, on a stand-in trainer (no model trained): the budget's stop rule, the
step timing it reads, the signal handlers, the metrics' averages and where they go, the pre-cooldown weights
kept once, the run folder's record of a resume."""

import json
import os
import signal
from types import SimpleNamespace

import pytest
import torch

from envisat_pose.config import InputError
from envisat_pose.perception import trainer_hooks as th
from envisat_pose.perception.model import CornerNet, ModelConfig


class Clock:
    """Readings given in advance, one per call."""

    def __init__(self, *readings):
        self.readings = list(readings)

    def __call__(self):
        return self.readings.pop(0)


def stand_in(**kw):
    base = dict(dist=None, dev=torch.device("cpu"), steps_run=0, time0=0.0, rank=0, state={"step": 0, "epoch": 0},
                lr=1e-3, cfg=SimpleNamespace(time_budget_s=10.0, to_dict=lambda: {"steps": 3}), t_start=0.0)
    return SimpleNamespace(**{**base, **kw})


def test_timing_leaves_the_first_steps_data_wait_out():
    timing = th.Timing()
    timing.trainer = stand_in(clock=Clock(1.0, 5.0, 6.0, 7.0, 7.5, 8.5, 9.0), t_start=0.5)
    timing.ask()  # 1.0
    timing.got()  # 5.0: the loaders' start-up
    timing.trainer.steps_run = 1
    timing.after_step({})  # 6.0 - 5.0, then asks at 7.0
    timing.got()  # 7.5
    timing.trainer.steps_run = 2
    timing.after_step({})  # 8.5 - 7.0, then asks at 9.0
    assert timing.iter_s == [1.0, 1.5]
    assert timing.first_batch_s == 4.5 and timing.data_wait_s == 4.0 + 0.5


def test_the_budget_stops_before_a_step_that_would_leave_too_little():
    timing, checkpoints = th.Timing(), SimpleNamespace(checkpoint_s=0.5)
    timing.iter_s = [9.0] + [1.0] * 10  # only the last 10 steps count
    budget = th.Budget(10.0, timing, checkpoints)
    budget.trainer = stand_in(steps_run=11)
    reserve = 1.5 * 1.0 + 0.5 + th.SHUTDOWN_RESERVE_S
    assert budget.share_clock(7.0 - 1e-9) == 7.0 - 1e-9 and budget.reserve == reserve
    assert budget.before_step(10.0 - reserve - 1e-9) is None
    assert budget.before_step(10.0 - reserve) == "time_budget"
    budget.trainer.steps_run = 0
    with pytest.raises(InputError, match="too short for one step"):
        budget.before_step(10.0 - reserve)


def test_signals_set_a_flag_then_a_second_ctrl_c_stops_at_once_and_handlers_come_back():
    before = signal.getsignal(signal.SIGINT)
    with th.StopOnSignals() as signals:
        assert signals.caught is None
        signal.raise_signal(signal.SIGTERM)
        assert signals.caught == "SIGTERM" and signals.flag == {"signal": "SIGTERM"}
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)
    assert signal.getsignal(signal.SIGINT) is before


def test_metrics_average_since_the_last_line_and_write_only_once_the_folder_exists(tmp_path):
    folder = SimpleNamespace(started=False)
    metrics = th.Metrics(folder)
    metrics.trainer = stand_in(run_dir=str(tmp_path), elapsed=Clock(2.0, 3.0))
    for loss in (1.0, 2.0, 4.5):
        metrics.after_step({"loss": torch.tensor(loss)})
    assert metrics.log("epoch")["loss"] == pytest.approx(2.5)
    assert not (tmp_path / "metrics.jsonl").exists()  # no folder yet
    folder.started = True
    again = metrics.log("end", {"steps_run": 3})
    assert again["loss"] == pytest.approx(2.5) and again["steps_run"] == 3 and again["time_s"] == 3.0
    lines = [json.loads(x) for x in open(tmp_path / "metrics.jsonl")]
    assert [x["kind"] for x in lines] == ["end"]


def test_pre_cooldown_weights_are_kept_once_and_at_a_budgets_stop_only(tmp_path):
    model = CornerNet(ModelConfig(input_px=64, width=16, depth=2, stem_width=8))
    opt = torch.optim.AdamW(model.parameters())
    folder = SimpleNamespace(started=False, start=lambda: setattr(folder, "started", True))
    hook = th.PreCooldown(folder)
    cooling = {"now": False}
    hook.trainer = stand_in(run_dir=str(tmp_path), model=model, opt=opt, state={"step": 4},
                            in_cooldown=lambda now_s: cooling["now"])
    assert hook.before_step(1.0) is None and "pre_cooldown_step" not in hook.trainer.state
    hook.on_stop("SIGINT")
    assert not (tmp_path / "pre_cooldown.safetensors").exists()
    cooling["now"] = True
    hook.before_step(2.0)
    assert folder.started and hook.trainer.state["pre_cooldown_step"] == 4
    assert (tmp_path / "pre_cooldown.safetensors").exists() and (tmp_path / "pre_cooldown_optimizer.pt").exists()
    hook.trainer.state["step"] = 7
    hook.before_step(3.0)
    hook.on_stop("time_budget")
    assert hook.trainer.state["pre_cooldown_step"] == 4  # kept once


def test_a_resumed_run_records_its_command_and_the_step_it_resumed_from_once(tmp_path):
    saved = {"train": {"steps": 2}, "command": "first", "resumes": []}
    folder = th.RunFolder(saved, {"command": "again", "git": "abc"}, resumed_at=2)
    folder.trainer = stand_in(run_dir=str(tmp_path), state={"step": 3})
    folder.after_step({})
    folder.trainer.state["step"] = 4
    folder.after_step({})
    record = json.load(open(os.path.join(tmp_path, "config.json")))
    assert record["train"] == {"steps": 3} and record["command"] == "first"
    assert record["resumes"] == [{"command": "again", "git": "abc", "step": 2}]


def test_checkpoints_wait_for_the_folder_then_write_every_n_steps_with_the_other_hooks_files(tmp_path):
    model = CornerNet(ModelConfig(input_px=64, width=16, depth=2, stem_width=8))
    folder = SimpleNamespace(started=False)
    checkpoints = th.Checkpoints(folder, every=2)
    saved = []
    other = SimpleNamespace(on_checkpoint=lambda: saved.append(json.loads(
        open(tmp_path / "state.json").read())["step"] if (tmp_path / "state.json").exists() else None))
    checkpoints.trainer = stand_in(run_dir=str(tmp_path), model=model, opt=torch.optim.AdamW(model.parameters()),
                                   state={"step": 2}, clock=Clock(1.0, 1.25), elapsed=lambda: 3.14159,
                                   hooks=[other, checkpoints])
    checkpoints.write()
    assert not os.listdir(tmp_path) and saved == []  # no folder yet: nothing
    folder.started = True
    checkpoints.after_step({})  # step 2: due
    assert saved == [None]  # the other hooks' files before state.json (written last)
    assert json.load(open(tmp_path / "state.json")) == {"step": 2, "time_s": 3.142}
    assert {"checkpoint.safetensors", "optimizer.pt"} <= set(os.listdir(tmp_path)) and checkpoints.checkpoint_s == 0.25
    checkpoints.trainer.state["step"] = 3
    checkpoints.after_step({})  # not due
    assert json.load(open(tmp_path / "state.json"))["step"] == 2
