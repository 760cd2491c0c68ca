"""Online closed-loop speed and accuracy: `envisat run --warm-start` on the default scenario at 1 Hz, one run, with and
without the region of interest (the filter's predicted corners as the detector's crop).

Measured per frame: the time in each stage (simulation: the MuJoCo truth, per frame; rendering: MuJoCo's render;
camera: the space camera's corruption; detection; filtering: the tracker's filter; recording: JPEG encoding and
logging run 0's frame to the streamed recording),
and the real-time factor, simulated seconds per wall second of the loop. Accuracy: the closed loop's RMSE after
t = 300 s next to the same filter on ideal pixel measurements (the truth's projected corners, every visible
in-frame corner, Gaussian noise of the detector's measured noise: the RMS error of its correctly named corners in
the same run), from the same initial estimate.

One core by default (the floor's protocol): the process pinned to --cores CPUs (sched_setaffinity), torch with
that many threads and llvmpipe with LP_NUM_THREADS = that many.

Run: .venv/bin/python bench/online_speed.py [--duration-s 600] [--cores 1] [--weights W] [--seed 0] [--after-s 300]
     [--out bench/results/online_speed.json]
Floor: 10x real time with the region of interest on one core (goal 20x); RMSE unchanged within noise.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import tempfile
import time

import numpy as np

FLOOR_RTF = 10.0
CORRECT_PX = 10.0  # a detected corner within this of the truth counts as correctly named (noise statistics)


def closed_loop(weights: str, duration_s: float, roi: bool, seed: int, out_dir: str, cores: int) -> tuple[dict, object]:
    """`envisat run --warm-start` (the tracker handed run 0's draw from P0, so the ideal-pixel filter below starts
    from the same estimate)."""
    from envisat_pose.pipelines.jobs import resolve_job
    from envisat_pose.pipelines.runs import closed_loop as loop

    cfg = resolve_job("run", "default", overrides={"duration_s": duration_s, "weights": weights, "seed": seed,
                                                   "workers": 1, "threads": cores, "warm_start": True,
                                                   "tracker.roi.enabled": roi})
    t0 = time.perf_counter()
    summary = loop.run_closed_loop(cfg, out_dir, progress=False)
    summary["bench_wall_s"] = time.perf_counter() - t0
    return summary, cfg


def detector_noise(out_dir: str) -> dict:
    """The detector's pixel error in a run: RMS per axis of its correctly named corners (within CORRECT_PX of
    the truth), the share of found corners that are not, and the mean e^T C^-1 e of the correct ones."""
    from envisat_pose.contracts import TruthTrajectory

    truth = TruthTrajectory.load(os.path.join(out_dir, "truth.npz"))
    with np.load(os.path.join(out_dir, "det.npz"), allow_pickle=False) as z:
        c, vis, cov = z["corners_px"], z["visible"], z["cov_px"]
    e = c - truth.corners_px
    n = np.linalg.norm(e, axis=-1)
    found = vis & np.isfinite(n)
    good = found & (n < CORRECT_PX)
    eg = e[good]
    m = np.einsum("ni,nij,nj->n", eg, np.linalg.inv(cov[good]), eg)
    measurable = truth.visible & truth.in_frame
    return {"sigma_px": float(np.sqrt(np.mean(eg**2))), "sigma_px_xy": np.sqrt(np.mean(eg**2, axis=0)).tolist(),
            "bias_px_xy": eg.mean(axis=0).tolist(), "found_corners": int(found.sum()),
            "measurable_corners": int(measurable.sum()), "wrong_share": float(1 - good.sum() / max(found.sum(), 1)),
            "within_2px": float(np.mean(n[found] < 2.0)), "within_5px": float(np.mean(n[found] < 5.0)),
            "mean_mahalanobis_correct": float(m.mean()), "correct_px": CORRECT_PX}


def ideal_pixels(out_dir: str, cfg, sigma_px: float, seed: int) -> np.ndarray:
    """The filter on the truth's projected corners (visible, in frame) + N(0, sigma_px^2), the closed loop's
    run-0 initial estimate; returns x_hat (T, 12)."""
    from envisat_pose.contracts import TruthTrajectory
    from envisat_pose.filtering.estimator import chaser_states, run_filter
    from envisat_pose.pipelines.tracking.onboard import onboard_physics
    from envisat_pose.state import draw_initial_estimate

    truth = TruthTrajectory.load(os.path.join(out_dir, "truth.npz"))
    mu, gg = onboard_physics(truth)
    rng0 = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(0,)))
    P0 = cfg.filter.P0
    x0 = draw_initial_estimate(truth.x[0], P0, rng0)  # as closed_loop_task draws run 0's warm start
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(10**6,)))
    z = truth.corners_px + rng.normal(0.0, sigma_px, truth.corners_px.shape)
    mask = truth.visible & truth.in_frame
    ch = chaser_states(truth.chaser_r_m, truth.chaser_rdot_m_s, truth.chaser_theta_rad, truth.chaser_thetadot_rad_s)
    res = run_filter(x0[None], P0, truth.t_s, ch, z[None], mask[None], sigma_px**2 * np.eye(2), "pixels", cfg.filter,
                     mu_m3_s2=mu, gravity_gradient=gg)
    return res.x_hat[0]


def rmse(t_s, x_true, x_hat, after_s: float) -> dict:
    """RMSE per block after after_s (envisat_pose.state.error_summary) and the largest position and attitude, over
    the rows that hold an estimate (est.npz's rows are NaN where the tracker was acquiring or lost)."""
    from envisat_pose.state import error_summary

    ok = np.isfinite(x_hat).all(-1)
    e = error_summary(np.asarray(t_s)[ok], x_true[ok][None], x_hat[ok][None], after_s)
    return {"position_m": e["position_m"]["rms_after"], "velocity_m_s": e["velocity_m_s"]["rms_after"],
            "attitude_deg": e["attitude_deg"]["rms_after"], "rate_deg_s": e["rate_deg_s"]["rms_after"],
            "max_position_m": e["position_m"]["max_after"], "max_attitude_deg": e["attitude_deg"]["max_after"]}


def main() -> None:
    # bench/_common.py, beside this script
    from _common import WholeFlagParser, count, description, existing_file, out_file, positive, provenance, results_path

    ap = WholeFlagParser(description=description(__doc__))
    ap.add_argument("--duration-s", type=positive, default=600.0)
    ap.add_argument("--weights", type=existing_file, help="detector weights (default: the shipped ones)")
    ap.add_argument("--seed", type=count(0), default=0)
    ap.add_argument("--cores", type=count(), default=1,
                    help="CPUs the loop may use (affinity, torch and llvmpipe threads)")
    ap.add_argument("--after-s", type=float, default=300.0, help="RMSE from this time on, s")
    ap.add_argument("--out", type=out_file, default=results_path("online_speed"))
    args = ap.parse_args()
    os.sched_setaffinity(0, set(sorted(os.sched_getaffinity(0))[:args.cores]))
    os.environ["LP_NUM_THREADS"] = str(args.cores)
    from envisat_pose.contracts import Estimates
    from envisat_pose.io import atomic_write_text
    from envisat_pose.pipelines.common.job_defaults import default_weights_path
    from envisat_pose.pipelines.runs.rows import STAGES

    weights = args.weights or default_weights_path()
    load_start = os.getloadavg()
    result = {"machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": sys.version.split()[0],
                          "load_avg_start": load_start},
              "protocol": f"envisat run --scenario default --duration-s {args.duration_s:g} at 1 Hz, one run, one "
                          f"process on {args.cores} core(s) (affinity; torch and llvmpipe LP_NUM_THREADS {args.cores} thread(s)); "
                          "stage times per frame; "
                          "real-time factor = simulated s / wall s of the loop's stages",
              "weights": weights, "floor_rtf": FLOOR_RTF, "cases": {}}
    rows = []
    with tempfile.TemporaryDirectory(prefix="online-speed-") as tmp:
        for roi in (True, False):
            name = "roi" if roi else "no_roi"
            out = os.path.join(tmp, name)
            summary, cfg = closed_loop(weights, args.duration_s, roi, args.seed, out, args.cores)
            est = Estimates.load(os.path.join(out, "est.npz"))
            case = {"timing_ms_per_frame": summary["timing_ms_per_frame"],
                    "real_time_factor": summary["real_time_factor_one_run"],
                    "wall_s": summary["wall_s"], "run0": summary["run0"], "scores": summary["scores"],
                    "recording_bytes": summary["recording_bytes"],
                    "rmse_closed_loop": rmse(est.t_s, est.x_true[0], est.x_hat[0], args.after_s),
                    "detector_noise": detector_noise(out)}
            x_ideal = ideal_pixels(out, cfg, case["detector_noise"]["sigma_px"], args.seed)
            case["rmse_ideal_pixels"] = rmse(est.t_s, est.x_true[0], x_ideal, args.after_s)
            case["floor_met"] = case["real_time_factor"] >= FLOOR_RTF if roi else None  # the floor is the ROI's
            result["cases"][name] = case
            rows.append((name, case))
    result["machine"]["load_avg_end"] = os.getloadavg()
    result["after_s"] = args.after_s
    result["provenance"] = provenance(args)
    atomic_write_text(args.out, json.dumps(result, indent=1, sort_keys=True) + "\n")
    print(f"online closed loop, default scenario, {args.duration_s:g} s at 1 Hz (load {load_start[0]:.1f} at start)")
    head = f"{'case':8s} " + " ".join(f"{s[:9]:>9s}" for s in STAGES) + f" {'RTF':>6s} {'pos cm':>8s} {'att deg':>8s}" \
        + f" {'ideal cm':>9s} {'ideal deg':>9s}"
    print(head + "   (ms per frame; RMSE after %g s)" % args.after_s)
    for name, c in rows:
        t = c["timing_ms_per_frame"]
        print(f"{name:8s} " + " ".join(f"{t[s]:9.1f}" for s in STAGES)
              + f" {c['real_time_factor']:6.2f} {100 * c['rmse_closed_loop']['position_m']:8.2f}"
              f" {c['rmse_closed_loop']['attitude_deg']:8.3f} {100 * c['rmse_ideal_pixels']['position_m']:9.2f}"
              f" {c['rmse_ideal_pixels']['attitude_deg']:9.3f}")
    n = result["cases"]["roi"]["detector_noise"]
    print(f"detector noise (correct corners): {n['sigma_px']:.2f} px RMS per axis, wrong {100 * n['wrong_share']:.1f} % "
          f"of found corners; floor {FLOOR_RTF:g}x real time on {args.cores} core(s): "
          + ("met" if result["cases"]["roi"]["floor_met"] else "NOT met") + " with the region of interest")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    from _common import run_main  # bench/_common.py, beside this script

    run_main(main)
