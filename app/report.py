"""`envisat report DIR [DIR...] --out report.html`: one self-contained HTML page over Monte Carlo campaigns and
rate sweeps (the report is pipelines/campaigns/report.py's: write_report)."""

from __future__ import annotations

import argparse

from envisat_pose.app.common import add_common


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report",
        help="one self-contained HTML report over Monte Carlo campaign folders",
        description="Write one HTML file (figures embedded, no external links) comparing campaign folders written by "
        "`envisat montecarlo`: scenario, config, figures and a table of RMSE, 3-sigma share, NEES, RMSE/PCRLB, "
        "wall time.")
    p.add_argument("dirs", nargs="+", metavar="DIR", help="campaign folders (envisat montecarlo --out)")
    add_common(p, out="output HTML file (default report.html)", out_default="report.html", out_metavar="FILE.html",
               quiet=False)
    p.set_defaults(func=run_report)


def run_report(args: argparse.Namespace) -> int:
    from envisat_pose.pipelines.campaigns.report import write_report

    n = write_report(args.dirs, args.out)
    print(f"wrote {args.out} ({n['campaigns']} campaign{'s' if n['campaigns'] != 1 else ''}"
          + (f", {n['sweeps']} rate sweep{'s' if n['sweeps'] > 1 else ''}" if n["sweeps"] else "") + ")")
    return 0
