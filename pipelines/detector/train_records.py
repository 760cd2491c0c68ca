"""A training run folder's records as the verb reads them back: config.json (its TrainConfig, command, data and online
looks) for a resume and for a rerun from its train.config.toml, state.json's online figures."""

from __future__ import annotations

import os

from envisat_pose.config import InputError
from envisat_pose.target import resolve_target_path


def resolved(target: str) -> str:
    """A target file as typed, as the one file it names from here."""
    return os.path.realpath(resolve_target_path(target))


def read_run_config(run_dir: str) -> dict:
    """The TrainConfig (as a dict) a run folder was trained with: the base a resumed run starts from. InputError
    when its target file, kept as typed (relative to the folder the run started in), is not found from here (its
    renders' record holds the same path: the run goes on only where it names the file)."""
    train = read_run_record(run_dir)["train"]
    kept = train.get("target")
    if isinstance(kept, str) and not os.path.isfile(resolve_target_path(kept)):
        raise InputError(f"resume: {run_dir!r} renders the target file {kept!r}, kept as it was typed when the "
                         "run started, and it is not found from here: resume from the folder the run started in")
    return train


def read_run_record(run_dir: str) -> dict:
    """A run folder's config.json: the TrainConfig ('train'), the command, the data, 'online' where it has it."""
    import json

    path = os.path.join(run_dir, "config.json")
    try:
        with open(path, encoding="utf-8") as fh:
            record = json.load(fh)
        if not isinstance(record, dict) or not isinstance(record.get("train"), dict):
            raise KeyError("train")
        return record
    except FileNotFoundError:
        raise InputError(f"resume: {run_dir!r} holds no config.json (not a run folder)") from None
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise InputError(f"resume: {path!r} is unreadable ({err})") from None


def saved_online(run_dir: str, resume: bool, config_path: str | None, cfg, data) -> dict | None:
    """The online record (config.json's 'online') a run renders again: a resumed run's own, or that of the run whose
    train.config.toml `config_path` is (its header names config.json beside it for the looks: resolution, looks,
    K) where the config trains that run's target and no --data is given; None otherwise (the flags' looks)."""
    if resume and os.path.isdir(run_dir):
        return read_run_record(run_dir).get("online")
    beside = os.path.dirname(os.path.abspath(config_path or ""))
    if data or not config_path or os.path.basename(config_path) != "train.config.toml" or \
            not os.path.isfile(os.path.join(beside, "config.json")):
        return None
    record = read_run_record(beside)
    kept, given = record["train"].get("target"), getattr(cfg, "target", None)
    same = kept == given or (kept and given and resolved(kept) == resolved(given))
    return record.get("online") if same else None  # another --target typed over the config's: its own renders


def online_record(run_dir: str) -> dict:
    """An online run's figures from its state.json: max_uses (the most crops any rendered frame gave so far) and
    frame_ms (the last session's mean cost of a frame in its render worker, online.RenderPool.stage_ms); None
    where the file does not say."""
    import json

    try:
        with open(os.path.join(run_dir, "state.json"), encoding="utf-8") as fh:
            online = json.load(fh)["online"]
        return {"max_uses": int(online["max_uses"]), "frame_ms": online.get("frame_ms")}
    except (OSError, ValueError, KeyError, TypeError):
        return {"max_uses": None, "frame_ms": None}


def nothing_to_do_line(run_dir: str, end: dict, time_budget_s: float | None) -> str:
    """The verb's one line for a run that trained nothing (end: train()'s end line, stopped_by 'nothing_to_do';
    time_budget_s: the budget the run was resumed under): at its steps, or with less of its budget left than a
    step needs (what was left, what is needed, the flag that gives more)."""
    step = end.get("step")
    if end.get("why") != "budget_spent":
        return f"nothing to do: {run_dir} is at step {step}, its steps reached; give --steps above {step} to go further"
    left, need = end.get("left_s", 0.0), end.get("need_s", 0.0)
    other = "" if time_budget_s is None else f", other than its {time_budget_s:g}"
    return (f"nothing to do: {run_dir} is at step {step}, its budget spent ({left:.1f} s of it left, a resume needs "
            f"{need:.1f} s: its last leg's start-up and a step's reserve, with a margin); give --time-budget-s S "
            f"(S above {need:.1f}{other}) to train S seconds more")


def rate_text(end: dict) -> str:
    """The end line's training speed as the verb says it: samples a second over this call's steps (end:
    train()'s end line, samples_s and steps_run), whole above 10, two significant digits below (a slow leg of one
    step trained 0.49 samples/s, once printed as '0 samples/s'); '' when this call trained no step."""
    rate = end.get("samples_s")
    if not end.get("steps_run") or rate is None:
        return ""
    if rate < 0.01:  # samples_s is kept to 2 decimals: a step trained, slower than that
        return "under 0.01 samples/s"
    return f"{rate:.0f} samples/s" if rate >= 10 else f"{rate:.2g} samples/s"


def loss_text(loss) -> str:
    """The end line's loss as what it is: the mean over the steps since the last epoch's line (metrics.jsonl),
    where the progress bar shows one step's loss every few steps (a 2-minute run's bar ended at 2.643 beside an
    end line's 3.8464, read as a contradiction)."""
    if loss is None:
        return "no loss recorded"
    return f"mean loss {loss:.4f} over the last epoch's steps"


def trained_line(run_dir: str, end: dict) -> str:
    """The verb's one line for a run that trained (end: train_detector's end line): the step reached and this
    call's steps, the loss, the speed (rate_text), the workers, why it stopped, the weights, and an online run's
    reuse of its frames."""
    workers = f"{end['render_workers']} render" if "render_workers" in end else f"{end.get('workers')}"
    rate = rate_text(end)
    return (f"trained to step {end.get('step')} ({end.get('steps_run')} this run): "
            f"{loss_text(end.get('loss'))}, {rate + ' ' if rate else ''}with {workers} workers "
            f"({end.get('stopped_by')}); weights {os.path.join(run_dir, 'checkpoint.safetensors')}"
            + (f"; each rendered frame cropped at most {end.get('max_uses')} times "
               f"(K = {end.get('uses_per_frame')})" if end.get("uses_per_frame") else ""))
