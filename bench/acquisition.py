"""Acquisition benchmark: cold starts of the closed loop (MuJoCo renders, the space camera, the shipped detector,
the Tracker with no prior) over random attitudes, tumble axes and lit suns, per bin of range x tumble rate.

A trial holds the chaser range_m ahead on V-bar in a named scenario's orbit (the rate's scenario: slow-tumble
226 s, default = ENVISAT's 134.74 s, stress-tumble 72 s spin period), with the target's initial attitude uniform on
SO(3), its tumble axis uniform on the sphere (in the body frame T) and a sun uniform over those lighting every frame
within a 90 deg phase angle out of the Earth's shadow (pipelines/runs/trials.py); the run config is resolved as `envisat
run --scenario RATE_SCENARIO` resolves it (pipelines.jobs.resolve_job) with the trial's seed,
duration and sun; the truth is the scenario's with the trial's range, axis and attitude (trials.trial_truth_config,
the keep-out checked when it is simulated); the loop is the closed loop's own run task (closed_loop.closed_loop_task)
from a cold start for --duration-s of frames (all lit: time counts from the first frame). Scored with
pipelines/runs/scoring.py: a trial succeeds when its first frame declared "tracking" is correct (attitude within 5 deg,
position within 2 % of the range); it false-locks when it claims an estimate (tracking or coasting) while wrong on
any frame; time to the first correct track from the first lit frame.

Per bin it prints and writes to bench/results/acquisition.json: trials, trials refused by the keep-out check,
success rate, success within 60 s, false-lock rate, time to the first correct track (median, max) and the trials
that never tracked; per trial its seeds and draws. Every draw comes from SeedSequence(seed, spawn_key=(range in cm,
rate index)).spawn(trials) (one child per trial, the same trials whatever other bins are run).

The solar array reaches 22.1 m from the target's centre of mass and the keep-out margin is 2 m, so a 20 m hold is
legal only while the array does not sweep toward the chaser: the truth's keep-out check (datagen/clearance.py)
refuses those draws (seed 0, 90 s: 1 of 30 draws at 20 m, 1 of 30 at 22 m and 24 m, none of 30 at 25 m, the nearest
hold legal whatever the attitude). A refused trial is not flown and not redrawn: it is counted per bin
(refused_keepout) and the rates are over the flown trials.

Run: .venv/bin/python bench/acquisition.py [--trials-per-bin 10] [--seed 0] [--ranges-m 20 30 40 50]
     [--rates slow envisat stress] [--duration-s 90] [--workers N]
Floors: 0 false locks in at least 300 acquisitions; success >= 99 % within 60 s of the first lit frame
in every range bin and tumble rate.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# tumble rates: name -> the named scenario whose spin period it is (its index is part of a bin's seed key)
RATES = {"slow": "slow-tumble", "envisat": "default", "stress": "stress-tumble"}
RANGES_M = (20.0, 30.0, 40.0, 50.0)
DURATION_S = 90.0
SUCCESS_WITHIN_S = 60.0
FLOORS = {"false_locks": 0, "min_acquisitions": 300, "success_within_60_s": 0.99}


def bin_seeds(seed: int, range_m: float, rate: str, trials: int) -> list[np.random.SeedSequence]:
    """One SeedSequence per trial of the bin (range_m, rate), from the root seed."""
    key = (int(round(100 * range_m)), list(RATES).index(rate))
    return np.random.SeedSequence(seed, spawn_key=key).spawn(trials)


def draw_trial(ss: np.random.SeedSequence, range_m: float, rate: str, duration_s: float, weights: str,
               phase_max_deg: float, config_path: str | None = None) -> dict:
    """A trial's draws and its run config (JSON) from its SeedSequence (two children: the run seed, i.e. the camera
    noise; then attitude, axis and sun from one generator); config_path: a run-config TOML over the scenario's
    (`envisat run --config`)."""
    from envisat_pose.config import to_dict
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.pipelines.jobs import resolve_job
    from envisat_pose.pipelines.runs.trials import draw_lit_sun_N, random_attitude_mrp, unit_vector

    scenario = RATES[rate]
    noise_ss, draw_ss = ss.spawn(2)
    run_seed = int(noise_ss.generate_state(1, np.uint32)[0])  # the closed loop's seed: its camera noise
    rng = np.random.default_rng(draw_ss)
    p0 = random_attitude_mrp(rng)
    axis = unit_vector(rng)
    flags = {"seed": run_seed, "runs": 1, "workers": 1, "weights": weights, "duration_s": duration_s}
    cfg = resolve_job("run", scenario, config_path, flags)
    t_s = np.arange(int(np.floor(cfg.duration_s * cfg.rate_hz + 1e-9)) + 1) / cfg.rate_hz
    sun = draw_lit_sun_N(scenario_config(scenario).orbit, t_s, (0.0, range_m, 0.0), rng, phase_max_deg)
    flags["image.sun_dir"] = list(sun)
    cfg = resolve_job("run", scenario, config_path, flags)
    return {"scenario": scenario, "range_m": range_m, "rate": rate, "run_seed": run_seed,
            "p0_mrp": [float(v) for v in p0], "spin_axis_T": [float(v) for v in axis], "sun_dir_N": list(sun),
            "cfg_json": json.dumps(to_dict(cfg), sort_keys=True)}


def run_trial(trial: dict) -> dict:
    """One cold start (a runner task): the truth with the trial's range, axis and attitude (None and the keep-out's
    message when it is refused), the closed loop's run task on it, scored per frame (scoring.run_record)."""
    from envisat_pose.config import ConfigError
    from envisat_pose.datagen.truth import simulate_truth
    from envisat_pose.pipelines.runs import closed_loop as loop
    from envisat_pose.pipelines.runs.run_config import run_config_from_json
    from envisat_pose.pipelines.runs.scoring import frame_errors, run_record
    from envisat_pose.pipelines.runs.trials import trial_truth_config

    cfg = run_config_from_json(trial["cfg_json"])
    truth_cfg = trial_truth_config(trial["scenario"], cfg.duration_s, cfg.rate_hz, cfg.seed, trial["range_m"],
                                   trial["spin_axis_T"], trial["p0_mrp"])
    out = {k: v for k, v in trial.items() if k != "cfg_json"}
    t0 = time.perf_counter()
    try:
        truth = simulate_truth(truth_cfg)
    except ConfigError as err:
        return out | {"refused": str(err), "error": None}
    with tempfile.TemporaryDirectory(prefix="acquisition-") as tmp:
        truth_path, run_dir = os.path.join(tmp, "truth.npz"), os.path.join(tmp, "run")
        truth.save(truth_path)
        try:
            loop.closed_loop_task(trial["cfg_json"], 0, truth_path, None, False, 0.0, run_dir)
        except Exception as err:  # noqa: BLE001 - a trial that crashes is recorded, the others still run
            return out | {"refused": None, "error": f"{type(err).__name__}: {err}"[:500]}
        rows = {k: np.load(os.path.join(run_dir, f"{k}.npy")) for k in ("x_hat", "P", "status", "skipped")}
    errors = frame_errors(truth.x, rows["x_hat"], rows["P"])
    rec = run_record(truth.t_s, errors, rows["status"], ~rows["skipped"].astype(bool))
    return out | {"refused": None, "error": None, "record": rec, "frames": len(truth.t_s),
                  "wall_s": time.perf_counter() - t0, "statuses": np.asarray(rows["status"]).tolist()}


def bin_summary(trials: list[dict]) -> dict:
    """A bin's figures over its trials (refused ones and crashed ones counted apart; a trial that never tracks is a
    failure)."""
    flown = [t for t in trials if t["refused"] is None and t.get("error") is None]
    recs = [t["record"] for t in flown]
    n = len(recs)
    ok = [bool(r["first_track_correct"]) for r in recs]
    t1 = [r["time_to_first_correct_track_s"] for r in recs]
    within = [o and r["time_to_first_correct_track_s"] is not None
              and r["time_to_first_correct_track_s"] <= SUCCESS_WITHIN_S for o, r in zip(ok, recs)]
    fl = [r["false_lock_frames"] > 0 for r in recs]
    done = [v for v in t1 if v is not None]
    refused = sum(t["refused"] is not None for t in trials)
    return {"trials": len(trials), "refused_keepout": refused, "errors": len(trials) - n - refused, "flown": n,
            "success": int(sum(ok)), "success_rate": sum(ok) / n if n else None,
            "success_within_60_s": int(sum(within)), "success_within_60_s_rate": sum(within) / n if n else None,
            "false_locks": int(sum(fl)), "false_lock_rate": sum(fl) / n if n else None,
            "false_lock_s": float(sum(r["false_lock_s"] for r in recs)),
            "never_tracked": int(sum(not r["tracked"] for r in recs)),
            "time_to_first_correct_track_median_s": float(np.median(done)) if done else None,
            "time_to_first_correct_track_max_s": float(np.max(done)) if done else None,
            "without_correct_track": n - len(done)}


def _f(v, fmt: str, scale: float = 1.0) -> str:
    """v formatted (times scale), or '-' as wide when None."""
    width = int(fmt.split(".")[0]) if fmt[0].isdigit() else 0
    return "-".rjust(width) if v is None else format(scale * v, fmt)


HEAD = (f"{'range m':>7s} {'rate':8s} {'flown':>5s} {'refused':>7s} {'crash':>5s} {'succ %':>6s} {'<=60s %':>7s} "
        f"{'FL %':>5s} "
        f"{'never':>5s} {'t50 s':>6s} {'tmax s':>6s}")


def table_row(range_m: float, rate: str, b: dict) -> str:
    return (f"{range_m:7g} {rate:8s} {b['flown']:5d} {b['refused_keepout']:7d} {b['errors']:5d} "
            f"{_f(b['success_rate'], '6.1f', 100)} "
            f"{_f(b['success_within_60_s_rate'], '7.1f', 100)} {_f(b['false_lock_rate'], '5.1f', 100)} "
            f"{b['never_tracked']:5d} {_f(b['time_to_first_correct_track_median_s'], '6.0f')} "
            f"{_f(b['time_to_first_correct_track_max_s'], '6.0f')}")


def main() -> None:
    # bench/_common.py, beside this script
    from _common import WholeFlagParser, count, description, existing_file, out_file, positive, provenance, results_path

    ap = WholeFlagParser(description=description(__doc__))
    ap.add_argument("--trials-per-bin", type=count(), default=10)
    ap.add_argument("--seed", type=count(0), default=0, help="root seed of every draw")
    ap.add_argument("--ranges-m", type=positive, nargs="+", default=list(RANGES_M))
    ap.add_argument("--rates", nargs="+", choices=list(RATES), default=list(RATES))
    ap.add_argument("--duration-s", type=positive, default=DURATION_S, help="frames per trial from the cold start, s")
    ap.add_argument("--workers", type=count(), default=os.cpu_count() or 1)
    ap.add_argument("--weights", type=existing_file, help="detector weights (default: the shipped ones)")
    ap.add_argument("--sun-phase-max-deg", type=positive, help="a lit sun's largest phase angle (default: trials')")
    ap.add_argument("--config", type=existing_file,
                    help="a run-config TOML applied to every trial, as `envisat run --config` takes it "
                         "(an ablation: [tracker.acquire] frames = 12, say); its text goes into the result")
    ap.add_argument("--out", type=out_file, default=results_path("acquisition"))
    args = ap.parse_args()
    from envisat_pose.io import atomic_write_text
    from envisat_pose.pipelines.common.job_defaults import default_weights_path
    from envisat_pose.pipelines.runs.trials import SUN_PHASE_MAX_DEG
    from envisat_pose.pools import RunnerConfig, run_tasks, thread_env
    from envisat_pose.provenance import weights_ref
    from envisat_pose.status import legend

    weights = args.weights or default_weights_path()
    phase = args.sun_phase_max_deg if args.sun_phase_max_deg is not None else SUN_PHASE_MAX_DEG
    load_start = os.getloadavg()
    bins = [(r, rate) for rate in args.rates for r in args.ranges_m]
    trials = [draw_trial(ss, r, rate, args.duration_s, weights, phase, args.config)
              for r, rate in bins for ss in bin_seeds(args.seed, r, rate, args.trials_per_bin)]
    print(f"acquisition: {len(bins)} bins x {args.trials_per_bin} trials, seed {args.seed}, {args.duration_s:g} s "
          f"each, {args.workers} workers (load {os.getloadavg()[0]:.1f} at start)")
    runner = RunnerConfig("local", args.workers, env=thread_env(args.workers))
    results: list[dict | None] = [None] * len(trials)
    t0 = time.perf_counter()
    for i, res in run_tasks(run_trial, [(t,) for t in trials], runner):
        results[i] = res
        rec = res.get("record")
        print(f"  trial {i + 1}/{len(trials)}: {res['range_m']:g} m {res['rate']}: "
              + ("refused by the keep-out" if res["refused"] else f"error: {res['error']}" if rec is None else
                 f"first track {rec['first_tracking_s']} s, correct {rec['first_track_correct']}, false lock "
                 f"{rec['false_lock_s']:g} s"), flush=True)
    wall_s = time.perf_counter() - t0
    out = {"machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": sys.version.split()[0],
                       "load_avg_start": load_start, "load_avg_end": os.getloadavg()},
           "protocol": f"cold starts, {args.trials_per_bin} trials per bin, root seed {args.seed} "
                       f"(SeedSequence(seed, spawn_key=(range cm, rate index)).spawn(trials)), {args.duration_s:g} s "
                       f"at the scenario's rate, random attitude (uniform SO(3)), tumble axis (uniform sphere, in T) "
                       f"and lit sun (phase <= {phase:g} deg all run, no shadow); V-bar hold; the tracker gets the "
                       f"exact chaser orbit and the render camera",
           "config": None if args.config is None else Path(args.config).read_text(),
           "weights": weights_ref(weights), "status_legend": legend(), "floors": FLOORS, "rates": RATES, "wall_s": wall_s,
           "bins": [], "trials": results}
    print(HEAD)
    for r, rate in bins:
        b = bin_summary([t for t in results if t["range_m"] == r and t["rate"] == rate])
        out["bins"].append({"range_m": r, "rate": rate, "scenario": RATES[rate]} | b)
        print(table_row(r, rate, b))
    allb = bin_summary(results)
    out["all"] = allb
    out["floors_met"] = {
        "false_locks": allb["false_locks"] == FLOORS["false_locks"] and allb["flown"] >= FLOORS["min_acquisitions"],
        "success_within_60_s": all(b["success_within_60_s_rate"] is not None
                                   and b["success_within_60_s_rate"] >= FLOORS["success_within_60_s"]
                                   for b in out["bins"])}
    print(f"all: {allb['flown']} flown ({allb['refused_keepout']} refused, {allb['errors']} crashed), success "
          f"{allb['success']}, within 60 s "
          f"{allb['success_within_60_s']}, false locks {allb['false_locks']}, never tracked {allb['never_tracked']}; "
          f"wall {wall_s:.0f} s")
    out["provenance"] = provenance(args)
    atomic_write_text(args.out, json.dumps(out, indent=1, sort_keys=True) + "\n")
    print(f"floors: 0 false locks in >= {FLOORS['min_acquisitions']} acquisitions, success >= "
          f"{100 * FLOORS['success_within_60_s']:g} % within {SUCCESS_WITHIN_S:g} s in every bin; wrote {args.out}")


if __name__ == "__main__":
    from _common import run_main  # bench/_common.py, beside this script

    run_main(main)
