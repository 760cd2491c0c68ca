"""Cold-start tracking benchmark: `envisat run` (MuJoCo renders, the space camera, the shipped detector, the
Tracker started with no prior) on several scenarios, R runs each (each its own camera noise), scored against the
truth.

Per scenario it prints and writes to bench/results/tracking.json: runs converged (position error < 10 cm and
attitude error < 1 deg on every lit frame to the end), time to converge from the first lit frame (median, max),
RMSE / PCRLB per block over the lit frames after convergence (the project's posterior Cramer-Rao bound,
analysis/pcrlb.py, along the same truth with the truth's measurable corners at the detector's measured pixel noise
in this run: the RMS per axis of its correctly named corners), mean NEES (12 expected), range bias (m), the
real-time factor of one run, and the detector's error model the tracker used.

Run: .venv/bin/python bench/tracking.py [--runs 8] [--duration-s 600] [--scenarios default slow-tumble ...]
     [--seed 11] [--correlation-in time|rotation]
Floors (issue 16): every run converges within 120 s of its first lit frame; RMSE/PCRLB <= 2 per block; mean
NEES in [6, 20]; |range bias| <= 1 cm at 50 m.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time

import numpy as np

SCENARIOS = ("default", "slow-tumble", "stress-tumble", "close-25m", "eclipse")
ECLIPSE_DURATION_S = 3000.0  # the eclipse scenario's shadow is ~600..2710 s: through it and out
CORRECT_PX = 10.0  # a detected corner within this of the truth counts as correctly named (noise statistics)
FLOORS = {"converge_s": 120.0, "rmse_over_pcrlb": 2.0, "nees": (6.0, 20.0), "range_bias_m": 0.01}


def run_scenario(scenario: str, runs: int, duration_s: float, workers: int, seed: int, weights: str, out: str,
                 correlation_in: str | None = None) -> dict:
    from envisat_pose.app.scenarios import job_defaults
    from envisat_pose.config import from_dict
    from envisat_pose.pipelines import closed_loop as loop
    from envisat_pose.pipelines.tracker import TRACKER_FILTER

    loop.stage_types()
    data = {"scenario": scenario, "duration_s": duration_s, "runs": runs, "workers": workers, "seed": seed,
            "weights": weights, "filter": {**TRACKER_FILTER, **job_defaults(scenario).get("filter", {})}}
    if correlation_in is not None:  # else the tracker's default
        data["tracker"] = {"correlation_in": correlation_in}
    cfg = loop.finish_config(from_dict(loop.RunConfig, data))
    t0 = time.perf_counter()
    summary = loop.run_closed_loop(cfg, out, progress=False, sink=f"save:{os.path.join(out, 'recording.rrd')}")
    summary["bench_wall_s"] = time.perf_counter() - t0
    return summary


def pixel_noise(out: str) -> float:
    """RMS per axis (px) of run 0's correctly named corners (within CORRECT_PX of the truth's)."""
    from envisat_pose.contracts import TruthTrajectory

    truth = TruthTrajectory.load(os.path.join(out, "truth.npz"))
    with np.load(os.path.join(out, "det.npz"), allow_pickle=False) as z:
        e = z["corners_px"] - truth.corners_px
        vis = z["visible"]
    n = np.linalg.norm(e, axis=-1)
    good = vis & np.isfinite(n) & (n < CORRECT_PX)
    return float(np.sqrt(np.mean(e[good] ** 2))) if good.any() else float("nan")


def bound_blocks(out: str, sigma_px: float) -> np.ndarray:
    """PCRLB per block (T, 4) (m, m/s, rad, rad/s) along the run's truth with the measurable corners of the lit
    frames at sigma_px, from an uninformative prior (the tracker starts cold)."""
    from envisat_pose.analysis.pcrlb import block_bounds, pcrlb_along_truth
    from envisat_pose.contracts import TruthTrajectory
    from envisat_pose.filtering.dynamics import load_inertia_T_kg_m2, propagate
    from envisat_pose.filtering.estimator import chaser_states
    from envisat_pose.filtering.measurements import measure
    from envisat_pose.geometry import load_camera
    from envisat_pose.pipelines.closed_loop import truth_dynamics
    from envisat_pose.pipelines.tracker import ACQUIRING_SIGMA

    truth = TruthTrajectory.load(os.path.join(out, "truth.npz"))
    with np.load(os.path.join(out, "det.npz"), allow_pickle=False) as z:
        lit = ~z["skipped"]
    mu, gg = truth_dynamics(truth)
    J, cam = load_inertia_T_kg_m2(), load_camera()
    ch = chaser_states(truth.chaser_r_m, truth.chaser_rdot_m_s, truth.chaser_theta_rad, truth.chaser_thetadot_rad_s)
    dt = float(truth.t_s[1] - truth.t_s[0])

    def fx(X):
        return propagate(X, ch[:-1, None, :], dt, J, mu, gravity_gradient=gg)

    measured = truth.visible & truth.in_frame & lit[:, None]
    P0 = np.diag(np.repeat(np.square(ACQUIRING_SIGMA), 3)) * 100.0
    B = pcrlb_along_truth(fx, lambda X: measure(X, "pixels", cam), truth.x, measured, sigma_px**2 * np.eye(2), P0,
                          np.zeros((12, 12)))
    return block_bounds(B, truth.x)


def ratios(out: str, summary: dict, bound: np.ndarray) -> dict:
    """RMSE / PCRLB per block over every run's lit frames after its convergence."""
    from envisat_pose.contracts import Estimates
    from envisat_pose.pipelines.scoring import after_convergence_masks
    from envisat_pose.state import BLOCKS, error_magnitudes

    est = Estimates.load(os.path.join(out, "est.npz"))
    with np.load(os.path.join(out, "det.npz"), allow_pickle=False) as z:
        skipped = z["skipped"]
    mask = after_convergence_masks(est.t_s, summary["scores"], skipped)
    if not mask.any():
        return {b: None for b in BLOCKS}
    err = error_magnitudes(est.x_true, est.x_hat)
    units = (1.0, 1.0, np.pi / 180.0, np.pi / 180.0)  # deg -> rad for the bound's units
    out_r = {}
    for i, (b, key) in enumerate(zip(BLOCKS, ("position_m", "velocity_m_s", "attitude_deg", "rate_deg_s"))):
        e2 = (err[key] * units[i])[mask] ** 2
        b2 = np.broadcast_to(bound[:, i], mask.shape)[mask] ** 2
        out_r[b] = float(np.sqrt(e2.mean() / b2.mean()))
    return out_r


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=8)
    ap.add_argument("--duration-s", type=float, default=600.0, help="per scenario (eclipse: at least 3000 s)")
    ap.add_argument("--scenarios", nargs="+", default=list(SCENARIOS))
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--weights", help="detector weights (default: the shipped ones)")
    ap.add_argument("--correlation-in", choices=("time", "rotation"),
                    help="the tracker's correlation_in (default: TrackerConfig's, pipelines/tracker.py)")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "tracking.json"))
    args = ap.parse_args()
    from envisat_pose.app.run import default_weights_path
    from envisat_pose.io import atomic_write_text
    from envisat_pose.perception.detect import load_detector

    weights = args.weights or default_weights_path()
    em = getattr(load_detector(weights), "error_model", None)
    result = {"machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": sys.version.split()[0],
                          "load_avg_start": os.getloadavg()},
              "protocol": f"envisat run (cold start), {args.runs} runs per scenario, seed {args.seed}, "
                          f"{args.duration_s:g} s ({ECLIPSE_DURATION_S:g} s for eclipse), 1 Hz, {args.workers} workers, "
                          f"tracker.correlation_in {args.correlation_in or 'default'}",
              "weights": weights, "error_model": None if em is None else {k: getattr(em, k) for k in vars(em)},
              "floors": FLOORS, "scenarios": {}}
    print(f"cold-start tracking, {args.runs} runs per scenario (load {os.getloadavg()[0]:.1f} at start)")
    head = (f"{'scenario':14s} {'conv':>5s} {'t50 s':>6s} {'tmax s':>6s} {'pos':>5s} {'vel':>5s} {'att':>5s} "
            f"{'rate':>5s} {'NEES':>6s} {'bias cm':>8s} {'RTF':>5s} {'px':>5s}   (RMSE/PCRLB per block)")
    print(head)
    for scen in args.scenarios:
        dur = max(args.duration_s, ECLIPSE_DURATION_S) if scen == "eclipse" else args.duration_s
        with tempfile.TemporaryDirectory(prefix=f"tracking-{scen}-") as out:
            summary = run_scenario(scen, args.runs, dur, args.workers, args.seed, weights, out, args.correlation_in)
            sigma = pixel_noise(out)
            ratio = ratios(out, summary, bound_blocks(out, sigma))
        s = summary["scores"]
        row = {"scores": s, "rmse_over_pcrlb": ratio, "pixel_noise_px": sigma, "duration_s": dur,
               "real_time_factor_one_run": summary["real_time_factor_one_run"],
               "timing_ms_per_frame": summary["timing_ms_per_frame"], "wall_s": summary["bench_wall_s"]}
        conv_ok = s["converged"] == s["runs"] and (s["time_to_converge_max_s"] or 1e9) <= FLOORS["converge_s"]
        vals = [v for v in ratio.values() if v is not None]
        nees = s["mean_nees_after_convergence"]
        row["floors_met"] = {
            "converge": bool(conv_ok),
            "rmse_over_pcrlb": bool(vals and len(vals) == 4 and max(vals) <= FLOORS["rmse_over_pcrlb"]),
            "nees": bool(nees is not None and FLOORS["nees"][0] <= nees <= FLOORS["nees"][1]),
            "range_bias": bool(s["range_bias_m"] is not None and abs(s["range_bias_m"]) <= FLOORS["range_bias_m"])}
        result["scenarios"][scen] = row

        def f(v, fmt):
            return "-" if v is None else format(v, fmt)

        print(f"{scen:14s} {s['converged']:2d}/{s['runs']:<2d} {f(s['time_to_converge_median_s'], '6.0f')} "
              f"{f(s['time_to_converge_max_s'], '6.0f')} "
              + " ".join(f(ratio[b], "5.2f") for b in ratio)
              + f" {f(nees, '6.1f')} {f(None if s['range_bias_m'] is None else 100 * s['range_bias_m'], '8.2f')}"
              f" {row['real_time_factor_one_run']:5.1f} {sigma:5.2f}", flush=True)
    result["machine"]["load_avg_end"] = os.getloadavg()
    atomic_write_text(args.out, json.dumps(result, indent=1, sort_keys=True) + "\n")
    print(f"floors: converge within {FLOORS['converge_s']:g} s, RMSE/PCRLB <= {FLOORS['rmse_over_pcrlb']:g}, NEES in "
          f"{list(FLOORS['nees'])}, |range bias| <= {100 * FLOORS['range_bias_m']:g} cm; wrote {args.out}")


if __name__ == "__main__":
    main()
