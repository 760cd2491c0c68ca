"""Held-out sequences in the closed loop's own regime, for the detector's error model (`envisat calibrate
--held-out`): for each (scenario, seed), the frames `envisat run` would render for that scenario and seed with the
seed's lit sun (the image table of bench/tracking.py's run config: pipelines.runs.trials.scenario_sun_N, within a 90 deg
phase angle), cut to --frames, written by `envisat generate` as DIR/SCENARIO-SEED. Each dataset keeps its
generate.config.toml, so `envisat generate --config DIR/SCENARIO-SEED/generate.config.toml --out ...` makes it again.

    python scripts/loop_sequences.py --scenarios default slow-tumble stress-tumble close-25m \
        --seeds 9001 9002 9003 --frames 150 --out held_out
"""

from __future__ import annotations

import os
import sys

from envisat_pose.whole_flags import WholeFlagParser


def sequence_config(scenario: str, seed: int, frames: int, phase_max_deg: float = 90.0):
    """The GenerateConfig of the closed loop's frames of (scenario, seed) over its first `frames` frames, lit."""
    from envisat_pose.pipelines.jobs import resolve_job
    from envisat_pose.pipelines.runs.run_config import RunConfig
    from envisat_pose.pipelines.runs.trials import scenario_sun_N

    flags = {"seed": seed, "runs": 1, "workers": 1}
    rate_hz = RunConfig(scenario=scenario, **flags).rate_hz
    flags["duration_s"] = (frames - 1) / rate_hz
    sun = scenario_sun_N(scenario, flags["duration_s"], rate_hz, seed, phase_max_deg)
    if sun is not None:
        flags["image.sun_dir"] = list(sun)
    return resolve_job("run", scenario, overrides=flags).image


def main(argv: list[str] | None = None) -> int:
    p = WholeFlagParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenarios", nargs="+", default=["default", "slow-tumble", "stress-tumble", "close-25m"])
    p.add_argument("--seeds", nargs="+", type=int, required=True)
    p.add_argument("--frames", type=int, default=150)
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    from envisat_pose.datagen.factory import run_generate

    os.makedirs(args.out, exist_ok=True)
    for scenario in args.scenarios:
        for seed in args.seeds:
            out = os.path.join(args.out, f"{scenario}-{seed}")
            manifest = run_generate(sequence_config(scenario, seed, args.frames), out, workers=args.workers,
                                    progress=False)
            print(f"{out}: {sum(e['count'] for e in manifest['shards'])} frames", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
