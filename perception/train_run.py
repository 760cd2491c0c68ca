"""What `train()` (perception/train.py) puts around its Trainer: where a run starts (a new folder, or a resumed run
after resume's checks), the clock reading its budget ends at, its batches (the shards epoch by epoch, or frames
rendered as training goes) and how an interrupted run ends (TrainingInterrupted)."""

from __future__ import annotations

import json
import os

from envisat_pose.config import InputError, flatten
from envisat_pose.perception.stream import close_batches, epoch_batches, loader_batches, run_prefetch
from envisat_pose.perception.trainer_hooks import CONFIG_TOML
from envisat_pose.perception.weights import WeightsError, read_header
from envisat_pose.target import resolve_target_path

RESUMABLE_CHANGES = ("steps", "time_budget_s")  # a resumed run may go further or longer, nothing else
# a resume is given a step only with this many times its last leg's min_leg_s left: a leg's start-up (renderers,
# loaders) varies from leg to leg (the one leg after it may start slower), and a leg that starts its batch sources
# for nothing costs their start-up and says nothing to do after it
LEG_START_MARGIN = 2.0


class TrainingInterrupted(KeyboardInterrupt):
    """A run stopped by SIGINT or SIGTERM after its checkpoint was written: step, run_dir and how to go on."""

    def __init__(self, step: int, run_dir: str, signal_name: str):
        self.step, self.run_dir, self.signal_name = step, run_dir, signal_name
        if step > 0:
            text = f"{signal_name} at step {step}: checkpoint written in {run_dir!r}"
        else:
            text = f"{signal_name} before the first step: nothing written"
        super().__init__(text)


def _data_name(records: list[dict]) -> str:
    def one(r):
        sha = (r.get("manifest_sha256") or "none")[:12]
        if r.get("images") is None:  # frames rendered online: its configs' hash
            return f"{r.get('name')} (configs {sha})"
        return f"{r.get('name')} ({r.get('images')} images, manifest {sha})"

    return ", ".join(one(r) for r in records)


def _config_changes(saved: list[dict], data: list[dict]) -> str:
    """' (generate.resolution_px 512 -> 256; ...)': the differences of online runs' recorded configs (the
    records' 'configs'; runs written before they were recorded: '')."""
    changed = []
    for was, now in zip(saved, data):
        a, b = flatten(was.get("configs") or {}), flatten(now.get("configs") or {})
        if a and b:
            changed += [f"{k} {a.get(k)!r} -> {b.get(k)!r}" for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
    return f" ({'; '.join(changed[:4])}{'; ...' if len(changed) > 4 else ''})" if changed else ""


def check_same_target(run_dir: str, saved: list[dict], data: list[dict]) -> None:
    """InputError when a run rendering another target's frames is resumed with that target's file changed (its
    data record's target_sha256 differs; records without one, ENVISAT's and older runs', are left to the data
    check)."""
    for was, now in zip(saved, data):
        a, b = was.get("target_sha256"), now.get("target_sha256")
        if a and b and a != b:
            raise InputError(f"resume: {run_dir!r} was trained on a target file that has changed since (sha256 "
                             f"{a[:12]}... then, {b[:12]}... now): restore the file, or start a new run with "
                             "`init` = its checkpoint")


def same_target_file(was, now) -> bool:
    """Whether a resume's `target` names the run's own file in another spelling (an absolute path for the relative
    one it started with, say): both found from here, one file."""
    if not (isinstance(was, str) and isinstance(now, str)):
        return False
    a, b = resolve_target_path(was), resolve_target_path(now)
    return os.path.isfile(a) and os.path.isfile(b) and os.path.samefile(a, b)


def check_resume(run_dir: str, cfg, data: list[dict] | None) -> tuple[dict, dict]:
    """(state.json, the run's config.json) of a run to resume with TrainConfig cfg; InputError when it is not
    one, or when the config (other than steps and the budget) or the data (by manifest hash) differ: each
    difference spelled out."""
    path = os.path.join(run_dir, "config.json")
    missing = [n for n in ("config.json", "state.json") if not os.path.exists(os.path.join(run_dir, n))]
    if missing:
        why = " (it stopped before its first checkpoint: start it again)" if missing == ["state.json"] else ""
        raise InputError(f"resume: {run_dir!r} holds no trained run (no {' and no '.join(missing)}){why}")
    with open(path, encoding="utf-8") as fh:
        saved = json.load(fh)
    old, new = flatten(saved["train"]), flatten(cfg.to_dict())
    changed = [f"{k} {old.get(k)!r} -> {new.get(k)!r}" for k in sorted(set(old) | set(new))
               if k not in RESUMABLE_CHANGES and old.get(k) != new.get(k)
               and not (k == "target" and same_target_file(old.get(k), new.get(k)))]
    if changed:
        raise InputError(f"resume: {run_dir!r} was trained with another config: {'; '.join(changed)} (only `steps` "
                         "and `time_budget_s` may change; start a new run with `init` = its checkpoint instead)")
    if data is not None and "data" in saved:
        check_same_target(run_dir, saved["data"], data)

        def key(records):
            return [r.get("manifest_sha256") or r.get("name") for r in records]

        if key(saved["data"]) != key(data):
            raise InputError(f"resume: {run_dir!r} was trained on {_data_name(saved['data'])}, not on "
                             f"{_data_name(data)}{_config_changes(saved['data'], data)}: resume with the same data, "
                             "or start a new run with `init` = its checkpoint")
    try:
        with open(os.path.join(run_dir, "state.json"), encoding="utf-8") as fh:
            state = json.load(fh)
    except (ValueError, OSError) as err:
        raise InputError(f"resume: {run_dir!r}: its state.json cannot be read ({err})") from None
    check_checkpoint_set(run_dir, state)
    return state, saved


def check_checkpoint_set(run_dir: str, state: dict) -> None:
    """InputError unless the run's weights files hold the step its state.json says (the checkpoint's and the
    moving average's `step` record): a run stopped while it wrote a checkpoint leaves files of two steps (state.json
    is written last), which a resume would mix."""
    for name in ("checkpoint.safetensors", "ema.safetensors"):
        path = os.path.join(run_dir, name)
        if not os.path.exists(path):
            continue  # none to mix (a missing checkpoint is named where it is loaded)
        try:
            step = read_header(path).get("step")
        except WeightsError as err:
            raise InputError(f"resume: {err}") from None
        if step is None or str(step) != str(state.get("step")):
            raise InputError(f"resume: {run_dir!r}: its {name} holds step {step}, its state.json step "
                             f"{state.get('step')}: the run was stopped while it wrote a checkpoint, so its files "
                             "do not belong together; start a new run from the weights with `init` = "
                             f"{os.path.join(run_dir, 'checkpoint.safetensors')}")


# what a run folder holds (perception/train.py)
RUN_FILES = ("config.json", CONFIG_TOML, "metrics.jsonl", "state.json", "checkpoint.safetensors", "optimizer.pt",
             "ema.safetensors", "pre_cooldown.safetensors", "pre_cooldown_optimizer.pt")


def start_state(run_dir: str, cfg, resume: bool, workers: int | None, data: list[dict] | None, world: int = 1
                ) -> tuple[dict, dict | None]:
    """The state to start from (the dict state.json holds) and, on resume, the run's config.json (None: a new
    run). InputError when a new run's folder holds a run, or when resume's checks fail (check_resume, the
    workers and the DDP world: a resumed run keeps their counts, which its batches and steps depend on)."""
    state = {"step": 0, "epoch": 0, "batch": 0, "workers": 0 if workers is None else workers, "time_s": 0.0,
             "world": world}
    if not resume:
        if os.path.exists(os.path.join(run_dir, "state.json")):
            raise InputError(f"run_dir {run_dir!r} already holds a run: resume it, or give another folder")
        others = sorted(n for n in (os.listdir(run_dir) if os.path.isdir(run_dir) else ()) if n not in RUN_FILES
                        and not n.startswith("."))
        if others:
            raise InputError(f"run_dir {run_dir!r} holds files that are not a training run's ({', '.join(others[:3])}"
                             f"{', ...' if len(others) > 3 else ''}): give a new or empty folder")
        return state, None
    saved_state, saved = check_resume(run_dir, cfg, data)
    ran_with = int(saved_state.get("workers", 0))
    if workers is not None and workers != ran_with:
        raise InputError(f"workers = {workers}: {run_dir!r} was trained with {ran_with} (its batches depend "
                         f"on the count); resume it with `workers` {ran_with}")
    ran_by = int(saved_state.get("world", 1))  # a run from before the world was recorded: one process
    if world != ran_by:
        how = f"under torchrun --nproc-per-node {ran_by}" if ran_by > 1 else "in one process (without torchrun)"
        raise InputError(f"resume: {run_dir!r} was trained by {ran_by} DDP process(es), this is {world} (its data "
                         f"split and batches depend on the count); resume it {how}")
    return {**state, **saved_state, "workers": ran_with, "world": ran_by}, saved


def budget_end(cfg, saved: dict | None, state: dict) -> float | None:
    """The run's clock reading at which a budgeted call stops: the config's budget for a new run, or for a
    resumed run given its own budget again (what is left of it); time_s + the new budget for a resumed run given
    another (that many seconds more). None: by steps."""
    if cfg.time_budget_s is None:
        return None
    if saved is None:
        return cfg.time_budget_s
    if state.get("budget_end_s") is not None and saved["train"].get("time_budget_s") == cfg.time_budget_s:
        return float(state["budget_end_s"])
    return float(state["time_s"]) + cfg.time_budget_s


def leg_need_s(state: dict) -> float:
    """The least of its budget a resume of this run is given a step in: LEG_START_MARGIN x state.json's min_leg_s
    (the last leg's wait for its first batch and the reserve before a step, trainer_hooks.Budget)."""
    return LEG_START_MARGIN * float(state.get("min_leg_s", 0.0))


def nothing_to_do(cfg, state: dict, saved: dict) -> dict | None:
    """The end line of a resumed run already at its steps or at its budget's end (it trains nothing), or None.
    The budget counts as spent when less of it is left than leg_need_s, so no batch source is started for nothing;
    a new budget (another time_budget_s than the run's) shorter than that is refused as too short for one step
    (InputError). The end line of a spent budget holds left_s (what was left) and need_s (leg_need_s)."""
    time0, end_s, need_s = float(state["time_s"]), state["budget_end_s"], leg_need_s(state)
    spent = end_s is not None and time0 + need_s >= end_s
    if state["step"] < cfg.steps and not spent:
        return None
    if state["step"] < cfg.steps and saved["train"].get("time_budget_s") != cfg.time_budget_s:
        raise InputError(f"time_budget_s = {cfg.time_budget_s:g}: too short for one step (a resume of this run needs "
                         f"{need_s:.1f} s: {LEG_START_MARGIN:g} x its last leg's {state.get('min_leg_s', 0.0):.1f} s "
                         "for its first batch and a step's reserve): give a longer budget")
    end = {"kind": "end", "step": state["step"], "epoch": state["epoch"], "steps_run": 0,
           "stopped_by": "nothing_to_do", "why": "steps_reached", "time_s": time0, "workers": state["workers"]}
    if state["step"] < cfg.steps:
        end.update(why="budget_spent", left_s=round(end_s - time0, 3), need_s=round(need_s, 3))
    return end


def end_line(tr, stop: str | None) -> dict:
    """Trainer tr's end line; for a resume whose batch sources started but whose budget ran out before a step (its
    start-up slower than leg_need_s allowed for) nothing_to_do's, budget_spent, with left_s (what was left when
    it started) and need_s (leg_need_s after this leg: its checkpoint recorded its own start-up in min_leg_s)."""
    if stop != "time_budget" or tr.steps_run > 0:
        return tr.end_line
    return {**tr.end_line, "stopped_by": "nothing_to_do", "why": "budget_spent",
            "left_s": round(tr.budget_end_s - tr.time0, 3), "need_s": round(leg_need_s(tr.state), 3)}


def _epoch_loader(tr, paths: list[str], epoch: int, prefetch: int):
    return epoch_batches(paths, tr.cfg.data, tr.cfg.seed, epoch, tr.cfg.batch_size, tr.state["workers"], tr.rank,
                         tr.world, pin_memory=tr.dev.type == "cuda", prefetch=prefetch)


def shard_batches(tr, paths: list[str], data_dir):
    """(batch, where the run stands after training it) from the shards for Trainer tr, epoch after epoch; an
    epoch's end is the hooks' after_epoch. A resumed epoch skips the batches it trained on. The next epoch's
    workers start early (no stall at the boundary); the workers of both stop on every way out."""
    state, current, upcoming = tr.state, None, None
    prefetch = run_prefetch(paths, tr.cfg.data, tr.cfg.seed, tr.cfg.batch_size, state["workers"])  # to the /dev/shm
    try:
        while True:
            skip, n = state["batch"], 0  # a resumed epoch: its first batches were trained on before
            current = upcoming if upcoming is not None else _epoch_loader(tr, paths, state["epoch"], prefetch)
            upcoming = _epoch_loader(tr, paths, state["epoch"] + 1, prefetch) if state["workers"] > 0 else None
            for i, cpu_batch in enumerate(loader_batches(current, tr.stop_flag)):
                if i >= skip:
                    n += 1
                    yield cpu_batch, {"batch": i + 1}
            if tr.stop_flag.get("signal"):
                return
            if n == 0 and skip == 0:
                raise InputError(f"data {data_dir!r}: fewer samples than one batch of {tr.cfg.batch_size} per "
                                 f"worker ({state['workers']} workers, {len(paths)} shards, {tr.world} ranks): use "
                                 "fewer workers or a smaller batch")
            close_batches(current)
            tr.call("after_epoch")
            state["epoch"] += 1
            state["batch"] = 0
    finally:
        for batches in (current, upcoming):
            close_batches(batches)


def rendered_batches(online, state: dict):
    """(batch on the device, where the run stands) from frames rendered as training goes: online(start_state)
    yields (batch, the source's state), kept in state.json under 'online' and handed back on resume."""
    for batch, source_state in online(state.get("online")):
        yield batch, {"online": source_state}
