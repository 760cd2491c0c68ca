"""`envisat scenarios`: the named scenarios with their one-line descriptions (scenarios/NAME.toml, read by
envisat_pose.named_scenarios). What a job takes from one is the library's: pipelines/jobs.py (resolve_job),
pipelines/common/job_defaults.py (scenario_defaults; each job config's constructor fills itself from it)."""

from __future__ import annotations

import argparse

from envisat_pose import named_scenarios
from envisat_pose.config import to_toml


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
    if args.show is not None:
        data = named_scenarios.scenario_tables(args.show)
        print(f"# scenario {args.show}: {' '.join(data.pop('description').split())}\n" + to_toml(data), end="")
        return 0
    rows = named_scenarios.descriptions()
    width = max(len(n) for n, _ in rows)
    for name, text in rows:
        print(f"{name:<{width}}  {text}")
    return 0
