"""`envisat estimate`: the batched UKF over R Monte Carlo runs of one MuJoCo truth, written as est.npz.

The truth comes from `--truth run.npz` (written by `envisat simulate`, read as the core's TruthTrajectory
contract without importing the simulator) or is simulated for `--scenario NAME` by the MuJoCo truth simulator
(datagen.truth.simulate). Measurements are synthesized from the truth's own arrays (MuJoCo's corner sites and
their projection through MuJoCo's camera), never from the filter's model; the filter's model takes the truth's
mu and gravity-gradient switch from its config.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass, field

import numpy as np

from envisat_pose.config import ConfigError, InputError, check, from_dict, resolve_job_config, to_dict, to_toml
from envisat_pose.filtering.estimator import FilterConfig
from envisat_pose.filtering.montecarlo import MeasurementConfig

MAX_OUTPUT_BYTES = 8 * 2**30  # P alone is R * T * 144 * 8 bytes


@dataclass(frozen=True)
class EstimateConfig:
    """One `envisat estimate` job: measurements, filter, number of runs and the root seed.

    Run r draws its initial error and noise from SeedSequence(seed).spawn(runs)[r]; with --scenario the
    truth's random initial attitude comes from the same seed.
    """

    measurement: MeasurementConfig = field(default_factory=MeasurementConfig)
    filter: FilterConfig = field(default_factory=FilterConfig)
    runs: int = 1
    seed: int = 0

    def validate(self, prefix: str = "") -> None:
        check(1 <= self.runs <= 100_000, "runs", self.runs, "a number of runs from 1 to 100000")
        check(0 <= self.seed < 2**63, "seed", self.seed, "a non-negative integer seed")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "estimate",
        help="run the UKF on a truth trajectory (R Monte Carlo runs) and write est.npz",
        description="Estimate the relative pose of the tumbling target with the batched UKF over R Monte Carlo runs "
        "(runs differ in the initial error drawn from P0 and in measurement noise) and write est.npz: t_s, x_true, "
        "x_hat, P, n_meas, nis, nis_dof, diverged, config_json.",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--truth", metavar="RUN.npz", help="truth trajectory written by `envisat simulate`")
    src.add_argument("--scenario", metavar="NAME",
                     help="simulate this named scenario (`envisat scenarios` lists them) with the MuJoCo truth first; "
                     "its [measurement] and [filter] tables are the defaults under --config and the flags")
    p.add_argument("--duration-s", type=float, help="with --scenario: simulated time, s (default: the scenario's)")
    p.add_argument("--config", metavar="FILE.toml", help="estimate config (sections measurement, filter; runs, seed)")
    p.add_argument("--measurements", choices=["markers3d", "pixels", "pixels+range"],
                   help="what is measured of each visible corner (default markers3d)")
    p.add_argument("--sigma-m", type=float, help="3D corner noise per axis, m (default 0.02)")
    p.add_argument("--sigma-px", type=float, help="pixel noise per axis, px (default 1)")
    p.add_argument("--sigma-range-m", type=float, help="range noise for pixels+range, m (default 0.05)")
    p.add_argument("--max-markers", type=int, help="use at most N corners per step, the first visible in A..H order")
    p.add_argument("--failure-prob", type=float, help="probability that a visible corner is lost at a step")
    p.add_argument("--outage", type=float, nargs=2, action="append", metavar=("START_S", "END_S"),
                   help="a window without measurements (repeatable)")
    p.add_argument("--rate-hz", type=float, help="filter/measurement rate, Hz (default 1)")
    p.add_argument("--adaptive-r", action="store_const", const=True, help="innovation-based measurement noise")
    p.add_argument("--adaptive-q", action="store_const", const=True, help="residual-based process noise")
    p.add_argument("--no-gate", action="store_const", const=True, help="switch the chi-square gate off")
    p.add_argument("--runs", type=int, help="number of Monte Carlo runs, filtered as one batch (default 1)")
    p.add_argument("--seed", type=int, help="root seed (default 0)")
    p.add_argument("--out", default="est.npz", help="output .npz (default est.npz); its config goes next to it")
    p.add_argument("--plot", action="store_true", help="also write a PNG of the errors with 3-sigma bounds next to --out")
    p.add_argument("--rrd", metavar="FILE.rrd",
                   help="also write a Rerun recording: truth, run 0's estimate with its 3-sigma ellipsoid, every run's "
                   "errors with +-3 sigma bands (`envisat view FILE`)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run_estimate)


def resolve_config(args: argparse.Namespace) -> EstimateConfig:
    """Defaults, then the named scenario's [measurement] and [filter] tables (with --scenario), then the file,
    then the flags; validated before any work. Unknown scenario names fail here with the known ones."""
    defaults: dict = {}
    if args.scenario is not None:
        from envisat_pose.app.scenarios import job_defaults

        defaults = {k: v for k, v in job_defaults(args.scenario).items() if k in ("measurement", "filter")}
    flags = {
        "measurement.kind": args.measurements,
        "measurement.sigma_m": args.sigma_m,
        "measurement.sigma_px": args.sigma_px,
        "measurement.sigma_range_m": args.sigma_range_m,
        "measurement.max_markers": args.max_markers,
        "measurement.failure_prob": args.failure_prob,
        "measurement.outages_s": [list(w) for w in args.outage] if args.outage else None,
        "measurement.rate_hz": args.rate_hz,
        "filter.adaptive_r": args.adaptive_r,
        "filter.adaptive_q": args.adaptive_q,
        "filter.gate_prob": 0.0 if args.no_gate else None,
        "runs": args.runs,
        "seed": args.seed,
    }
    return resolve_job_config(EstimateConfig, defaults, args.config, flags)


def load_truth(args: argparse.Namespace, cfg: EstimateConfig):
    """The truth trajectory: read from --truth, or simulated by MuJoCo for --scenario. Returns (truth, source).

    A file that is not a truth trajectory (truncated, foreign, another contract) is one InputError line.
    With --scenario the scenario's duration applies unless --duration-s is given.
    """
    if args.truth:
        from envisat_pose.contracts import TruthTrajectory

        if args.duration_s is not None:
            raise InputError("--duration-s applies to --scenario only; the truth file fixes the duration")
        truth = TruthTrajectory.load(args.truth)
        truth_model(truth, args.truth)  # its config must name the physics the filter needs
        return truth, {"truth_file": args.truth}
    from envisat_pose.datagen.scenario import scenario_config, scenario_dict
    from envisat_pose.datagen.truth import simulate

    overrides: dict = {"seed": cfg.seed}
    if args.duration_s is not None:
        overrides["duration_s"] = args.duration_s
    if cfg.measurement.rate_hz > 1.0:
        overrides["dt_s"] = 1.0 / cfg.measurement.rate_hz
    scenario_dict(args.scenario)  # unknown names fail here with the list of known ones
    scfg = scenario_config(args.scenario, **overrides)
    return simulate(scfg, progress=not args.quiet), {"scenario": args.scenario}


def scenario_outages(args: argparse.Namespace, cfg: EstimateConfig, truth) -> EstimateConfig:
    """With --scenario NAME whose file has an [eclipse] table: cfg with the Earth's-shadow windows along the
    simulated truth appended to its outages (app.scenarios.eclipse_outages); cfg otherwise."""
    if not args.scenario:
        return cfg
    import dataclasses

    from envisat_pose.app.scenarios import eclipse_outages, with_outages
    from envisat_pose.datagen.scenario import ScenarioConfig

    windows = eclipse_outages(args.scenario, from_dict(ScenarioConfig, truth.config))
    return dataclasses.replace(cfg, measurement=with_outages(cfg.measurement, windows))


def truth_model(truth, source: str = "the truth") -> tuple[float, bool]:
    """The physics of the truth that the filter's model must share: (mu_m3_s2, gravity_gradient), read from the
    truth's config (orbit.mu_m3_s2, target.gravity_gradient); InputError if the config lacks them."""
    try:
        cfg = truth.config
        mu = float(cfg["orbit"]["mu_m3_s2"])
        gg = cfg["target"]["gravity_gradient"]
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(f"{source}: its config_json does not give orbit.mu_m3_s2 and target.gravity_gradient "
                         f"({type(err).__name__}: {err})") from None
    if not (np.isfinite(mu) and mu > 0) or not isinstance(gg, bool):
        raise InputError(f"{source}: its config_json has orbit.mu_m3_s2 = {mu!r} and target.gravity_gradient = "
                         f"{gg!r}; expected a positive number and true/false")
    return mu, gg


def output_paths(out: str) -> tuple[str, str]:
    """est.npz -> (est.npz, est.config.toml)."""
    stem = out[:-4] if out.endswith(".npz") else out
    return out, stem + ".config.toml"


def estimate(truth, cfg: EstimateConfig, progress: bool = False) -> dict:
    """Filter cfg.runs runs of a truth trajectory; returns the arrays of est.npz (without config_json).

    Arrays: t_s (T,), x_true (R, T, 12), x_hat (R, T, 12), P (R, T, 12, 12), n_meas (R, T), nis (R, T), nis_dof (R, T),
    diverged (R,) (NIS window or NEES window against the truth).
    """
    from envisat_pose.filtering.estimator import chaser_states, nees_divergence, run_filter
    from envisat_pose.filtering.montecarlo import filter_stride, make_run_inputs, truth_measurements

    mu_m3_s2, gravity_gradient = truth_model(truth)

    try:
        stride = filter_stride(truth.t_s, cfg.measurement.rate_hz)
    except ValueError as err:
        raise ConfigError("measurement.rate_hz", cfg.measurement.rate_hz, str(err)) from None
    sel = slice(0, None, stride)
    t_s, x_true = truth.t_s[sel], truth.x[sel]
    chaser = chaser_states(truth.chaser_r_m, truth.chaser_rdot_m_s, truth.chaser_theta_rad,
                           truth.chaser_thetadot_rad_s)[sel]
    R, T = cfg.runs, len(t_s)
    need = R * T * (144 + 30) * 8
    if need > MAX_OUTPUT_BYTES:
        raise ConfigError("runs", R, f"fewer runs or a shorter truth: {R} runs x {T} steps need "
                          f"{need / 2**30:.1f} GiB (limit {MAX_OUTPUT_BYTES / 2**30:.0f} GiB)")
    fcfg = cfg.filter
    kind = cfg.measurement.kind
    z_true, base = truth_measurements(kind, truth.corners_C_m[sel], truth.visible[sel], truth.corners_px[sel],
                                      truth.in_frame[sel])
    inp = make_run_inputs(x_true[0], t_s, z_true, base, cfg.measurement, fcfg.P0, cfg.seed, R)
    res = run_filter(inp.x0_hat, fcfg.P0, t_s, chaser, inp.z, inp.mask, inp.R_c, kind, fcfg, progress=progress,
                     mu_m3_s2=mu_m3_s2, gravity_gradient=gravity_gradient)
    diverged = res.diverged | nees_divergence(x_true[None], res.x_hat, res.P, fcfg)
    return {
        "t_s": t_s,
        "x_true": np.broadcast_to(x_true, (R, T, 12)).copy(),
        "x_hat": res.x_hat,
        "P": res.P,
        "n_meas": res.n_meas,
        "nis": res.nis,
        "nis_dof": res.dof,
        "diverged": diverged,
    }


def summary(arrays: dict) -> str:
    """Errors over the second half of the run: RMS position (cm) and attitude angle (deg), ANEES."""
    from envisat_pose.filtering.estimator import nees
    from envisat_pose.state import error_summary

    t_s = arrays["t_s"]
    T = t_s.shape[0]
    late = slice(T // 2, None)
    e = error_summary(t_s, arrays["x_true"], arrays["x_hat"], after_s=float(t_s[T // 2]) if T else 0.0)
    anees = nees(arrays["x_true"][:, late], arrays["x_hat"][:, late], arrays["P"][:, late]).mean()
    return (f"after t = {e['after_s']:.0f} s: RMS position error {100 * e['position_m']['rms_after']:.3f} cm, RMS "
            f"attitude error {e['attitude_deg']['rms_after']:.4f} deg, mean NEES {anees:.2f} (12 expected); "
            f"diverged runs {int(arrays['diverged'].sum())}/{len(arrays['diverged'])}")


def run_estimate(args: argparse.Namespace) -> int:
    from envisat_pose.contracts import Estimates
    from envisat_pose.io import atomic_write_text, check_writable_output

    if not args.out.endswith(".npz"):
        raise InputError(f"--out {args.out!r}: expected a path ending in .npz")
    cfg = resolve_config(args)
    out, cfg_path = output_paths(args.out)
    check_writable_output(out)
    if args.rrd:
        from envisat_pose.app.view import check_rrd_output

        check_rrd_output(args.rrd)
    truth, source = load_truth(args, cfg)
    cfg = scenario_outages(args, cfg, truth)
    if len(truth.t_s) < 2:
        raise InputError("the truth trajectory has fewer than 2 samples")
    arrays = estimate(truth, cfg, progress=not args.quiet)
    config_json = json.dumps({"estimate": to_dict(cfg), "truth_source": source, "truth_config": truth.config},
                             sort_keys=True)
    est = Estimates(**arrays, config_json=config_json)
    est.save(out)
    atomic_write_text(cfg_path, "# envisat estimate: the full validated config of this job\n" + to_toml(to_dict(cfg)))
    print(f"wrote {out} ({cfg.runs} runs x {len(arrays['t_s'])} steps), config {cfg_path}")
    print(summary(arrays))
    if args.plot:
        from envisat_pose.analysis.plots import plot_estimate

        png = out[:-4] + ".png"
        plot_estimate(arrays["t_s"], arrays["x_true"], arrays["x_hat"], arrays["P"], png,
                      title=f"UKF errors, {cfg.measurement.kind}, {cfg.runs} runs, seed {cfg.seed}")
        print(f"wrote {png}")
    if args.rrd:
        from envisat_pose.analysis.recording import write_estimates_recording

        write_estimates_recording(args.rrd, est, truth)
        print(f"wrote {args.rrd} (Rerun recording; open it with `envisat view {args.rrd}`)")
    return 0
