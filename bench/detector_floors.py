"""The detector's floors (PCK@5, swaps, ambiguity, visibility) against `envisat evaluate` JSONs: which hold,
which do not, with the figures.

    .venv/bin/python bench/detector_floors.py --random EVAL.json [EVAL.json ...] [--earth EVAL.json ...]
        [--sequence EVAL.json ...] [--speed bench/results/detector_speed.json]
        [--out bench/results/detector_floors.json]

--random: held-out random views (full 1024 px frames, default generate config); --earth: the same with the Earth
behind the target in every view; --sequence: sequences whose apparent scale is checked (evaluate's bias, per
method present: detector = coarse pass, detector_roi = the labels' region of interest). Every figure is the
detector's over the group 'all' of each file, except 'better than Shi-Tomasi', checked per corruption level
(the groups noise=... and blur=... with frames in both methods) on PCK@2 and PCK@5. Writes a small JSON (--out,
default bench/results/detector_floors.json).
"""

from __future__ import annotations

import json
import os

RANDOM = {  # metric: (floor, direction)
    "median_px": (0.45, "<="), "pck_2px": (0.85, ">="), "pck_5px": (0.95, ">="), "swap_rate_strict": (0.015, "<="),
    "ambiguous_share": (0.10, "<="), "visibility_precision": (0.96, ">="), "visibility_recall": (0.96, ">="),
}
EARTH_PCK5 = 0.92
SCALE_TOL = 3e-4
SPEED_MS = {"detector_full_frame": 60.0, "detector_roi": 40.0}


def meets(value: float, floor: float, direction: str) -> bool:
    return value <= floor if direction == "<=" else value >= floor


def detector_figures(s: dict) -> dict:
    return {"frames": s["frames"], "usable_corners": s.get("usable_corners"), "median_px": s["errors"]["all"]["median_px"],
            "p95_px": s["errors"]["all"]["p95_px"], "pck_2px": s["pck_2px"], "pck_5px": s["pck_5px"],
            "swap_rate_strict": s["swap_rate_strict"], "ambiguous_share": s["ambiguous_share"],
            "visibility_precision": s["visibility"]["precision"], "visibility_recall": s["visibility"]["recall"],
            "mean_nees": s.get("calibration", {}).get("mean_nees"), "bias": s.get("bias")}


def read(path: str, flag: str, *keys: str) -> dict:
    """The JSON file given to `flag`, checked to hold the nested keys its figures come from: InputError (one line)
    for another file."""
    from envisat_pose.config import InputError

    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
        inner = data
        for key in keys:
            inner = inner[key]
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise InputError(f"{flag} {path}: no {'.'.join(keys)} ({type(err).__name__}: {err})") from None
    return data


def corruption_levels(e: dict) -> list[dict]:
    """Detector against Shi-Tomasi (oracle names) per corruption level, PCK@2 and PCK@5."""
    out = []
    for group, per in e["groups"].items():
        if not (group.startswith("noise=") or group.startswith("blur=")):
            continue
        d, st = per.get("detector", {}), per.get("shi_tomasi", {})
        if not d.get("frames") or not st.get("frames"):
            continue
        out.append({"group": group, "frames": d["frames"], "detector_pck_2px": d["pck_2px"],
                    "shi_tomasi_pck_2px": st["pck_2px"], "detector_pck_5px": d["pck_5px"],
                    "shi_tomasi_pck_5px": st["pck_5px"],
                    "better": d["pck_2px"] > st["pck_2px"] and d["pck_5px"] > st["pck_5px"]})
    return out


def main() -> int:
    from _common import (  # bench/_common.py
        WholeFlagParser,
        description,
        existing_file,
        out_file,
        provenance,
        write_json,
    )

    p = WholeFlagParser(description=description(__doc__))
    p.add_argument("--random", nargs="+", type=existing_file, default=[])
    p.add_argument("--earth", nargs="*", type=existing_file, default=[])
    p.add_argument("--sequence", nargs="*", type=existing_file, default=[])
    p.add_argument("--speed", type=existing_file)
    p.add_argument("--out", type=out_file, default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results",
                                                 "detector_floors.json"))
    a = p.parse_args()
    result = {"random": [], "earth": [], "sequences": [], "speed": None, "floors": {}}
    rows = []
    for path in a.random:
        e = read(path, "--random", "groups", "all", "detector")
        fig = detector_figures(e["groups"]["all"]["detector"])
        levels = corruption_levels(e)
        checks = {k: {"value": fig[k], "floor": f, "op": op, "met": meets(fig[k], f, op)} for k, (f, op) in RANDOM.items()}
        checks["better_than_shi_tomasi_every_level"] = {"met": all(r["better"] for r in levels),
                                                       "levels": levels}
        result["random"].append({"file": os.path.basename(path), "data": e.get("data"), **fig, "checks": checks})
        rows += [(os.path.basename(path), k, c.get("value"), c.get("floor"), c["met"]) for k, c in checks.items()]
    for path in a.earth:
        e = read(path, "--earth", "groups", "all", "detector")
        fig = detector_figures(e["groups"]["all"]["detector"])
        met = fig["pck_5px"] >= EARTH_PCK5
        result["earth"].append({"file": os.path.basename(path), "data": e.get("data"), **fig,
                                "checks": {"pck_5px": {"value": fig["pck_5px"], "floor": EARTH_PCK5, "met": met}}})
        rows.append((os.path.basename(path), "earth pck_5px", fig["pck_5px"], EARTH_PCK5, met))
    for path in a.sequence:
        e = read(path, "--sequence", "groups", "all")
        for method, s in e["groups"]["all"].items():
            if not method.startswith("detector") or not s.get("frames") or "bias" not in s:
                continue
            b = s["bias"]
            met = abs(b["scale_mean"] - 1.0) <= SCALE_TOL
            result["sequences"].append({"file": os.path.basename(path), "data": e.get("data"), "method": method,
                                        **b, "met": met})
            rows.append((os.path.basename(path), f"{method} |scale-1|", b["scale_mean"] - 1.0, SCALE_TOL, met))
    if a.speed:
        sp = read(a.speed, "--speed", "full_frame", "ms_per_frame")["full_frame"]["ms_per_frame"]
        result["speed"] = {k: {"median_ms": sp[k]["median"], "floor_ms": v, "met": sp[k]["median"] <= v}
                           for k, v in SPEED_MS.items()}
        rows += [("speed", k, c["median_ms"], c["floor_ms"], c["met"]) for k, c in result["speed"].items()]
    for name, metric, value, floor, met in rows:
        v = "-" if value is None else f"{value:.4g}"
        f = "-" if floor is None else f"{floor:.4g}"
        print(f"{name:28s} {metric:36s} {v:>10s} {f:>8s}  {'met' if met else 'NOT met'}")
    result["provenance"] = provenance(a)
    write_json(a.out, result, indent=1, sort_keys=True)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    from _common import run_main  # bench/_common.py, beside this script

    run_main(main)
