"""Two trees of the project side by side: has a change slowed the filter or the closed loop?

Runs each tree's own bench/ukf_speed.py (the batched UKF, microseconds per run-step) and bench/online_speed.py
(`envisat run --warm-start`, default scenario, 1 Hz, one core: the real-time factor with and without the region
of interest, and each stage's ms per frame) in fresh processes, alternating the trees round by round so the machine's load drifts alike for
both; medians over the rounds, and the median of the rounds' paired ratios (current / baseline). The baseline is a `git archive` of an earlier commit with the compiled plugin
copied in (`cp datagen/plugin/*.so DIR/datagen/plugin/`); its package is put first on PYTHONPATH.

Floor of a change that must not slow anything: every figure within 5 % of the baseline's (ukf: at most 1.05x the
time; closed loop: at least 0.95x the real-time factor).

Run: .venv/bin/python bench/tree_speed.py --baseline DIR [--current DIR] [--rounds 2] [--duration-s 300]
     [--only ukf|loop] [--cores 1] [--warm-up-s 30] [--out bench/results/tree_speed.json]  (each run appended to
     the file's runs; an untimed warm-up of each tree first, so a fresh tree's numba compile is not timed)
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
UKF_KEYS = ("fast_1_run", "fast_batched_1000", "fast_full_loop_1_run", "fast_full_loop_1000")
FLOOR = 0.05


def run_bench(tree: str, script: str, args: list[str]) -> dict:
    """The tree's own bench script in a fresh process with the tree's package first on the path; its JSON."""
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "result.json")
        env = {**os.environ, "PYTHONPATH": tree}
        subprocess.run([sys.executable, os.path.join(tree, "bench", script), *args, "--out", out], cwd=tree, env=env,
                       check=True, stdout=subprocess.DEVNULL)
        with open(out, encoding="utf-8") as fh:
            return json.load(fh)


def figures(tree: str, duration_s: float, only: str | None, cores: int = 1) -> dict:
    """{figure name: value} of one round of one tree (only: 'ukf' or 'loop', else both; the loop on `cores`)."""
    out = {}
    if only in (None, "ukf"):
        ukf = run_bench(tree, "ukf_speed.py", [])["us_per_run_step"]
        out.update({f"ukf_{k}_us": ukf[k] for k in UKF_KEYS})
    if only in (None, "loop"):
        loop = run_bench(tree, "online_speed.py", ["--duration-s", str(duration_s), "--after-s", str(duration_s / 2),
                                                   "--cores", str(cores)])
        for case in sorted(loop["cases"]):
            out[f"rtf_{case}"] = loop["cases"][case]["real_time_factor"]
            out.update({f"ms_{case}_{stage}": ms for stage, ms in loop["cases"][case]["timing_ms_per_frame"].items()})
    return out


def main() -> None:
    # bench/_common.py, beside this script
    from _common import (
        WholeFlagParser,
        count,
        description,
        existing_dir,
        existing_results,
        out_file,
        positive,
        provenance,
        write_json,
    )

    ap = WholeFlagParser(description=description(__doc__))
    ap.add_argument("--baseline", required=True, type=existing_dir,
                    help="the earlier tree (a git archive, its plugin .so copied in)")
    ap.add_argument("--current", default=ROOT, type=existing_dir, help="the tree measured (default: this one)")
    ap.add_argument("--rounds", type=count(), default=2)
    ap.add_argument("--duration-s", type=positive, default=300.0, help="closed-loop simulated seconds per run")
    ap.add_argument("--only", choices=("ukf", "loop"), help="one of the two benches (default: both)")
    ap.add_argument("--cores", type=count(), default=1,
                    help="the closed loop's CPUs (online_speed.py --cores; default 1)")
    ap.add_argument("--warm-up-s", type=float, default=30.0,
                    help="an untimed run of each tree first, this many simulated seconds (0: none): a fresh tree "
                         "compiles its numba kernels into its cache on its first run, which would land in round 1")
    ap.add_argument("--out", type=out_file, default=os.path.join(HERE, "results", "tree_speed.json"))
    args = ap.parse_args()
    has_runs = lambda data: isinstance(data.get("runs"), list)  # noqa: E731
    existing_results(args.out, has_runs)  # a wrong --out refused before the benchmark runs
    for tree in (args.baseline, args.current):
        if not os.path.isfile(os.path.join(tree, "bench", "online_speed.py")):
            ap.error(f"{tree}: not a tree of this project (no bench/online_speed.py)")
    trees = {"baseline": os.path.abspath(args.baseline), "current": os.path.abspath(args.current)}
    for name in trees if args.warm_up_s > 0 else ():
        figures(trees[name], args.warm_up_s, args.only, args.cores)
        print(f"warmed up {name} ({args.warm_up_s:g} s, untimed)", flush=True)
    rounds: dict[str, list[dict]] = {name: [] for name in trees}
    for r in range(args.rounds):
        for name in (trees if r % 2 == 0 else reversed(list(trees))):
            rounds[name].append(figures(trees[name], args.duration_s, args.only, args.cores))
            print(f"round {r + 1} {name}: " + ", ".join(f"{k} {v:.2f}" for k, v in rounds[name][-1].items()),
                  flush=True)
    median = {name: {k: statistics.median(row[k] for row in rows) for k in rows[0]} for name, rows in rounds.items()}
    # each round's pair ran back to back: the median of the rounds' ratios cancels most of the load's drift
    ratio = {k: statistics.median(c[k] / b[k] for b, c in zip(rounds["baseline"], rounds["current"]))
             for k in median["baseline"]}
    # the floors: the UKF's time and the loop's real-time factor; a stage's ms per frame says where time went
    met = {k: (v <= 1 + FLOOR) if k.startswith("ukf_") else (v >= 1 - FLOOR) for k, v in ratio.items()
           if not k.startswith("ms_")}
    print(f"{'figure':<30} {'baseline':>10} {'current':>10} {'ratio':>7}  floor (5 %; ratio: median of the rounds')")
    for k in ratio:
        print(f"{k:<30} {median['baseline'][k]:>10.2f} {median['current'][k]:>10.2f} {ratio[k]:>7.3f}  "
              f"{'' if k not in met else 'met' if met[k] else 'MISSED'}")
    result = {"machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "load_avg_end": os.getloadavg()},
              "protocol": f"each tree's own bench/ukf_speed.py (default) and bench/online_speed.py "
                          f"(--duration-s {args.duration_s} --cores {args.cores}; only: {args.only or 'both'}), an untimed "
                          f"{args.warm_up_s:g} s warm-up of each tree, {args.rounds} alternating rounds; "
                          f"medians, and the ratio as the median of the rounds' paired ratios",
              "trees": {name: os.path.basename(path.rstrip("/")) for name, path in trees.items()},
              "rounds": rounds, "median": median, "ratio_current_to_baseline": ratio, "floor_met": met}
    # one file, every run appended (runs of one pair of trees side by side, each with its protocol)
    result["provenance"] = provenance(args)
    runs = existing_results(args.out, has_runs).get("runs", [])
    write_json(args.out, {"runs": runs + [result]}, indent=1, sort_keys=True)
    print(f"wrote {args.out} (run {len(runs) + 1})")


if __name__ == "__main__":
    from _common import run_main  # bench/_common.py, beside this script

    run_main(main)
