"""UKF speed: microseconds per run-step (one predict + one update of one run) of filterpy's UKF, of our numpy
filter (kernel "reference", filtering/ukf.py) and of our fused numba kernels (kernel "fast", filtering/fast.py,
the default), on one run and batched over 1000 runs, all measured in the same process on the same problem: the
12-state model of the default scenario (MuJoCo truth), 3D corners of all visible corners (up to 8 x 3
measurements, mask-varying). Also the full estimator step (gate, visibility check, monitors, storage:
run_filter) with each kernel, and the arithmetic bound: the floating-point operations of one run-step (counted
below, for the measured mean number of corners) at this core's dgemm rate (a 1024 x 1024 matrix product).

One core: BLAS and OpenMP are held to one thread (set before numpy loads), so every peer gets the same core.
Times are the best of a few repeats of process CPU time (the machine is shared; CPU time is what a run costs).

Run: .venv/bin/python bench/ukf_speed.py [--runs 1000] [--truth-seed 0] [--noise-seed 1]
     [--out bench/results/ukf_speed.json]
Floors: batched over 1000 runs >= 1000x filterpy per run-step (goal: within 10x of the arithmetic
bound); one run >= 50x.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import json  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

REPEATS = 3
TRUTH_SEED, NOISE_SEED = 0, 1  # --truth-seed and --noise-seed's defaults (bench/montecarlo_speed.py's slice too)


def _setup(n_steps: int, n_runs: int, truth_seed: int = TRUTH_SEED, noise_seed: int = NOISE_SEED):
    """The problem every peer solves: the default scenario's truth (truth_seed) and n_runs runs of 3D-corner
    measurements and initial errors drawn from noise_seed."""
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.datagen.truth import simulate_truth
    from envisat_pose.filtering.estimator import FilterConfig, chaser_states
    from envisat_pose.filtering.montecarlo import MeasurementConfig, inputs_from_truth

    tr = simulate_truth(scenario_config("default", duration_s=float(n_steps), seed=truth_seed))
    cfg = FilterConfig(gate_prob=0.0)
    inp = inputs_from_truth(tr, MeasurementConfig(), cfg.P0, seed=noise_seed, n_runs=n_runs)
    chaser = chaser_states(tr.chaser_r_m, tr.chaser_rdot_m_s, tr.chaser_theta_rad, tr.chaser_thetadot_rad_s)
    return tr, cfg, inp, chaser


def _best(fn, repeats: int = REPEATS) -> float:
    """The smallest process CPU time of `repeats` calls of fn(), s."""
    best = np.inf
    for _ in range(repeats):
        t0 = time.process_time()
        fn()
        best = min(best, time.process_time() - t0)
    return best


def time_filterpy(cfg, inp, chaser, steps: int) -> float:
    """us per run-step of filterpy (one run)."""
    from envisat_pose.filtering.reference import make_reference_ukf, reference_predict, reference_update

    def go():
        ukf = make_reference_ukf(inp.x0_hat[0], cfg.P0, cfg.Q(1.0))
        reference_update(ukf, inp.z[0, 0], inp.mask[0, 0], inp.R_c, "markers3d")
        for k in range(1, steps + 1):
            reference_predict(ukf, 1.0, chaser[k - 1])
            reference_update(ukf, inp.z[0, k], inp.mask[0, k], inp.R_c, "markers3d")
    return _best(go, 2) / steps * 1e6


def time_steps(cfg, inp, chaser, steps: int, runs: int, kernel: str) -> float:
    """us per run-step of the pure UKF predict + update (no gate, no visibility check) over `runs` runs at once:
    filtering.ukf's numpy steps ("reference") or filtering.fast's kernels ("fast")."""
    from envisat_pose.filtering import fast, ukf
    from envisat_pose.filtering.estimator import make_setup
    from envisat_pose.filtering.measurements import measure

    setup = make_setup(cfg, "markers3d")
    w, Q = setup.weights, cfg.Q(1.0)
    hx = lambda x: measure(x, "markers3d")  # noqa: E731
    R_c = np.broadcast_to(inp.R_c, (runs, 8, 3, 3))
    ones = np.ones(runs)

    def step(mean, cov, k):
        if kernel == "reference":
            if k > 0:
                mean, cov = ukf.predict(mean, cov, chaser[k - 1], 1.0, Q, w)
            mean, cov, _ = ukf.update(mean, cov, inp.z[:runs, k], inp.mask[:runs, k], inp.R_c, hx, w)
            return mean, cov
        if k > 0:
            mean, cov = fast.predict_fused(mean, cov, chaser[k - 1], 1.0, Q, setup)
        o = fast.update_fused(mean, cov, inp.z[:runs, k], inp.mask[:runs, k], R_c, ones, None, False, setup)
        return o["mean"], o["cov"]

    mean0, cov0 = step(inp.x0_hat[:runs].copy(), np.broadcast_to(cfg.P0, (runs, 12, 12)).copy(), 0)
    step(mean0, cov0, 1)  # warm: numba loads its cache (or compiles) on the first call

    def go():
        mean, cov = mean0, cov0
        for k in range(1, steps + 1):
            mean, cov = step(mean, cov, k)
    return _best(go) / (steps * runs) * 1e6


def time_run_filter(inp, chaser, tr, steps: int, runs: int, kernel: str) -> float:
    """us per run-step of the full estimator loop (gate, visibility check, monitors, storage) over `runs` runs."""
    from envisat_pose.filtering.estimator import FilterConfig, run_filter

    full = FilterConfig(kernel=kernel)
    sl = slice(0, steps + 1)
    go = lambda: run_filter(inp.x0_hat[:runs], full.P0, tr.t_s[sl], chaser[sl], inp.z[:runs, sl],  # noqa: E731
                            inp.mask[:runs, sl], inp.R_c, "markers3d", full)
    return _best(go) / ((steps + 1) * runs) * 1e6


def flops_per_run_step(n_corners: float, n: int = 12, n_sub: int = 1) -> dict:
    """Floating-point operations of one run-step of the fast kernels (markers3d, no gate), counted per part.

    n_corners: measured corners (3 components each). Counts multiply-adds as 2; sqrt and division as 1.
    The model: ~175 operations per evaluation of the 12-state derivative, 4 per RK4 step, 156 for the stage
    sums; the measurement model: 49 for Gamma(p), 21 per corner.
    """
    S, M = 2 * n + 1, 3 * n_corners
    chol_n = n**3 / 3 + n**2
    parts = {
        "predict: Cholesky, sigma points": chol_n + 2 * S * n,
        "predict: RK4 of 25 sigma points": S * n_sub * (4 * 175 + 156),
        "predict: MRP sets, mean, residuals": S * (2 * 25 + 2 * n + n),
        "predict: covariance sum_s Wc r r^T": 2 * S * n * n + S * n,
        "predict: symmetrize, + Q, positive-definite check": 3 * n * n + chol_n,
        "update: Cholesky, sigma points": chol_n + 2 * S * n,
        "update: measurement model of 25 sigma points": S * (49 + 21 * n_corners),
        "update: predicted z, residuals, weights": 2 * S * M + S * M + S * (M + n) + S * (25 + n),
        "update: Pzz and Pxz": 2 * S * M * M + 2 * S * n * M,
        "update: S, Cholesky of S": M * M + M**3 / 3 + M**2,
        "update: gain solves, mean, K S K^T": M * M + n * M * M + 2 * M + 2 * n * M + 2 * n * n * M + n * n,
        "update: symmetrize, positive-definite check": 2 * n * n + chol_n,
    }
    return {k: float(v) for k, v in parts.items()}


def dgemm_flops_per_s(size: int = 1024) -> float:
    """This core's attainable double-precision rate: a size x size matrix product through numpy's BLAS."""
    a = np.random.default_rng(0).standard_normal((size, size))
    a @ a
    return 2.0 * size**3 / _best(lambda: a @ a, 3)


def main() -> None:
    from _common import WholeFlagParser, count, description, out_file, provenance, results_path  # bench/_common.py

    ap = WholeFlagParser(description=description(__doc__))
    ap.add_argument("--runs", type=count(), default=1000)
    ap.add_argument("--truth-seed", type=count(0), default=TRUTH_SEED, help="the default scenario's seed (its truth)")
    ap.add_argument("--noise-seed", type=count(0), default=NOISE_SEED,
                    help="the runs' measurement noise and initial errors")
    ap.add_argument("--out", type=out_file, default=results_path("ukf_speed"))
    args = ap.parse_args()
    load_start = os.getloadavg()[0]
    steps_fp, steps_one, steps_batch = 20, 100, 10
    tr, cfg, inp, chaser = _setup(max(steps_fp, steps_one, steps_batch) + 1, args.runs, args.truth_seed,
                                  args.noise_seed)
    R = args.runs
    us = {
        "filterpy": time_filterpy(cfg, inp, chaser, steps_fp),
        "reference_1_run": time_steps(cfg, inp, chaser, steps_one // 4, 1, "reference"),
        "fast_1_run": time_steps(cfg, inp, chaser, steps_one, 1, "fast"),
        f"reference_batched_{R}": time_steps(cfg, inp, chaser, 3, R, "reference"),
        f"fast_batched_{R}": time_steps(cfg, inp, chaser, steps_batch, R, "fast"),
        "reference_full_loop_1_run": time_run_filter(inp, chaser, tr, steps_one // 4, 1, "reference"),
        "fast_full_loop_1_run": time_run_filter(inp, chaser, tr, steps_one, 1, "fast"),
        f"reference_full_loop_{R}": time_run_filter(inp, chaser, tr, 3, R, "reference"),
        f"fast_full_loop_{R}": time_run_filter(inp, chaser, tr, steps_batch, R, "fast"),
    }
    n_corners = float(inp.mask[:, 1:steps_batch + 1].sum(-1).mean())
    parts = flops_per_run_step(n_corners)
    flops = sum(parts.values())
    rate = dgemm_flops_per_s()
    bound_us = flops / rate * 1e6
    fp = us["filterpy"]
    names = {
        "filterpy": "filterpy 2.0.0 UKF, 1 run",
        "reference_1_run": "ours, numpy (reference), 1 run",
        "fast_1_run": "ours, fast kernels, 1 run",
        f"reference_batched_{R}": f"ours, numpy (reference), batched over {R} runs",
        f"fast_batched_{R}": f"ours, fast kernels, batched over {R} runs",
        "reference_full_loop_1_run": "full estimator step (numpy), 1 run",
        "fast_full_loop_1_run": "full estimator step (fast), 1 run",
        f"reference_full_loop_{R}": f"full estimator step (numpy), {R} runs",
        f"fast_full_loop_{R}": f"full estimator step (fast), {R} runs",
    }
    print(f"{'filter':<52} {'us/run-step':>12} {'x filterpy':>11} {'x bound':>8}")
    for key, name in names.items():
        print(f"{name:<52} {us[key]:12.2f} {fp / us[key]:11.1f} {us[key] / bound_us:8.1f}")
    print(f"{'arithmetic bound':<52} {bound_us:12.2f} {fp / bound_us:11.1f} {1.0:8.1f}")
    print(f"  = {flops:.3g} floating-point operations per run-step ({n_corners:.2f} corners on average) at "
          f"{rate / 1e9:.1f} GFLOP/s (this core's dgemm)")
    ratio_batch, ratio_one = fp / us[f"fast_batched_{R}"], fp / us["fast_full_loop_1_run"]
    result = {
        "problem": "12-state ENVISAT UKF, RK4 at 1 s, 3D corners of all visible corners (markers3d), default scenario",
        "us_per_run_step": us,
        "ratio_vs_filterpy": {k: fp / v for k, v in us.items() if k != "filterpy"},
        "arithmetic_bound": {"us_per_run_step": bound_us, "flops_per_run_step": flops, "flops_parts": parts,
                             "mean_corners": n_corners, "dgemm_gflop_s": rate / 1e9,
                             "fast_batched_over_bound": us[f"fast_batched_{R}"] / bound_us},
        "floors": {"batched_ratio": 1000.0, "one_run_ratio": 50.0, "goal_within_x_of_bound": 10.0},
        "meets_floors": {"batched": bool(ratio_batch >= 1000.0),
                         "one_run (full estimator step)": bool(ratio_one >= 50.0),
                         "goal_within_10x_of_bound": bool(us[f"fast_batched_{R}"] <= 10 * bound_us)},
        "note": "best of a few repeats of process CPU time, one BLAS thread, on a 2-core machine shared with "
                "other work (noisy); every row measured in this same process. 'batched' rows are the pure UKF "
                "steps (no gate); 'full estimator step' is run_filter with the default FilterConfig (gate, "
                "visibility check, monitors, storage). filterpy calls fx and hx once per sigma point.",
        "load_average_1min": {"start": load_start, "end": os.getloadavg()[0]},
        "steps": {"filterpy": steps_fp, "1_run": steps_one, "batched": steps_batch},
        "seeds": {"truth": args.truth_seed, "noise": args.noise_seed},
        "machine": {"python": platform.python_version(), "cpu_count": os.cpu_count(), "numpy": np.__version__,
                    "numba": __import__("numba").__version__},
    }
    result["provenance"] = provenance(args)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    from envisat_pose.io import atomic_write_text

    atomic_write_text(args.out, json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}; fast batched / filterpy = {ratio_batch:.0f}x (floor 1000x), one run (full step) "
          f"{ratio_one:.0f}x (floor 50x), {us[f'fast_batched_{R}'] / bound_us:.1f}x the bound (goal 10x)")


if __name__ == "__main__":
    from _common import run_main  # bench/_common.py, beside this script

    run_main(main)
