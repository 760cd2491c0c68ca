"""`envisat scenarios`: the named scenarios with their one-line descriptions; and what a job takes from one.

A named scenario (scenarios/NAME.toml, read by envisat_pose.named_scenarios) gives `estimate` and `montecarlo`
their defaults under the user's --config and flags: its [measurement] and [filter] tables, its duration, and,
for a scenario with an [eclipse] table, the measurement outages of the Earth's shadow computed from the truth's
orbit (datagen.scenario.eclipse_windows), appended to any configured outages (the pipelines' job:
pipelines.estimate.eclipse_outages and with_outages).
"""

from __future__ import annotations

import argparse

from envisat_pose import named_scenarios


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "scenarios",
        help="list the named scenarios (--scenario NAME) with their descriptions",
        description="List the named scenarios shipped with the package (scenarios/*.toml) with their one-line "
        "descriptions; --show NAME prints one scenario's resolved tables.",
    )
    p.add_argument("--show", metavar="NAME", help="print this scenario's tables (its base resolved) as TOML")
    p.set_defaults(func=run_scenarios)


def run_scenarios(args: argparse.Namespace) -> int:
    from envisat_pose.config import to_toml

    if args.show is not None:
        data = named_scenarios.load(args.show)
        print(f"# scenario {args.show}: {' '.join(data.pop('description').split())}\n" + to_toml(data), end="")
        return 0
    rows = named_scenarios.descriptions()
    width = max(len(n) for n, _ in rows)
    for name, text in rows:
        print(f"{name:<{width}}  {text}")
    return 0


def job_defaults(name: str) -> dict:
    """What a named scenario sets of an estimate or montecarlo config: measurement, filter, duration_s.
    Unknown names raise ConfigError listing the known ones."""
    data = named_scenarios.load(name)
    out = {k: dict(data[k]) for k in ("measurement", "filter") if k in data}
    if "duration_s" in data:
        out["duration_s"] = data["duration_s"]
    return out
