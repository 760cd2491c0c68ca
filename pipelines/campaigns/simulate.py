"""The pipeline of `envisat simulate`: the MuJoCo truth of a scenario, written as the design's truth trajectory
(run.npz) with its config next to it, and optionally a PNG of the 12 states and a Rerun recording."""

from __future__ import annotations

import dataclasses
import os

from envisat_pose.config import InputError, config_arg, path_arg, rrd_arg, to_dict, to_toml
from envisat_pose.datagen.scenario import ScenarioConfig
from envisat_pose.io import atomic_write_text, staged_folder
from envisat_pose.named_scenarios import known, names
from envisat_pose.out_dirs import check_out_file, make_out_file_dirs, own_side_files
from envisat_pose.out_lock import locks_output
from envisat_pose.provenance import source_line
from envisat_pose.target import load_target
from envisat_pose.written_target import with_target_sha256


def output_paths(out: str) -> tuple[str, str, str]:
    """run.npz -> (run.npz, run.config.toml, run.png)."""
    stem = out[:-4] if out.endswith(".npz") else out
    return out, stem + ".config.toml", stem + ".png"


@locks_output("rrd", "simulate", folder=False)
@locks_output("out", "simulate", folder=False)
def run_simulate(cfg, out: str, plot: bool = False, rrd: str | None = None, progress: bool = False,
                 label: str = "") -> dict:
    """Simulate the truth of cfg (a validated datagen ScenarioConfig) with MuJoCo and write out (the
    TruthTrajectory contract) and its config; label: the named scenario cfg was made from where cfg does not say
    (cfg.scenario: scenario_config and resolve_job set it; another name there is refused; recorded in the truth,
    and its plot's title); with plot the states' PNG next to out, with rrd a Rerun recording of the truth. The
    output paths (str or pathlib.Path) are checked before any work (InputError naming `out` or `rrd`), their
    folders made then.

    Returns {"truth": the TruthTrajectory, "truth_file": out, "config_toml": its path, "plot": the PNG or None,
    "rrd": rrd}.
    """
    from envisat_pose.datagen.truth import simulate_truth

    cfg = config_arg(cfg, ScenarioConfig)
    if label and label != cfg.scenario:
        if cfg.scenario:  # the truth records one scenario: estimate takes its tables
            raise InputError(f"label {label!r}: cfg was made from scenario {cfg.scenario!r} (cfg.scenario, which "
                             "its truth records); give no label, or that one")
        if not known(label):
            raise InputError(f"label {label!r}: expected a named scenario ({', '.join(names())}) or a scenario "
                             "file that exists")
        cfg = dataclasses.replace(cfg, scenario=label)
    label = cfg.scenario
    out, rrd = path_arg(out, "out"), rrd_arg(rrd)
    if not out.endswith(".npz"):
        raise InputError(f"out {out!r}: expected a path ending in .npz")
    paths = {**{p: "out" for p in output_paths(out)}, **({rrd: "rrd"} if rrd else {})}
    for path, field in paths.items():
        check_out_file(path, field)
    out, cfg_path, png = output_paths(out)
    stale = own_side_files(out, cfg_path, png, "simulate", plot)  # a user's run.config.toml or run.png: refused
    make_out_file_dirs(paths)
    traj = simulate_truth(cfg, progress=progress)
    origin = (f"# made from scenario {label!r} (recorded in the truth: `envisat estimate --truth` takes its filter and "
              f"measurement tables); `envisat simulate --scenario {label} --config THIS_FILE` remakes it\n"
              if label else "")
    # all written into a staging folder beside out, then moved into place together: an interrupt (Ctrl-C during
    # the plot) leaves an earlier run's files as they were, not a new run.npz beside the old run.png
    # a rerun without plot removes an earlier run's PNG (it shows another truth; a user's PNG stays: stale)
    # the config records the target file's sha256 as the truth does (target.sha256): a rerun from it refuses a
    # file that changed since (written_target.recorded_target_checked)
    written = with_target_sha256(to_dict(cfg), "simulate", traj.config["target"]["sha256"])
    with staged_folder(os.path.dirname(os.path.abspath(out)), stale) as stage:
        traj.save(os.path.join(stage, os.path.basename(out)))
        atomic_write_text(os.path.join(stage, os.path.basename(cfg_path)),
                          "# envisat simulate: the full validated config of this run\n" + source_line() + origin
                          + to_toml(written))
        if plot:
            from envisat_pose.analysis.plots import plot_states

            target = load_target(cfg.target.file)
            plot_states(traj.t_s, traj.x, os.path.join(stage, os.path.basename(png)), visible=traj.visible,
                        title=f"{target.name} truth, scenario {label!r}, seed {cfg.seed}",
                        points="keypoints" if target.labels_name_keypoints else "corners", job="simulate")
        if rrd:
            from envisat_pose.analysis.recording import write_truth_recording

            write_truth_recording(rrd, traj, load_target(cfg.target.file))
    return {"truth": traj, "truth_file": out, "config_toml": cfg_path, "plot": png if plot else None, "rrd": rrd}
