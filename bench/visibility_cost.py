"""What the exact ray-cast visibility labels cost in the factory: generation time per image with the Target's ray
casts (the labels as shipped) beside the same generation with the visibility taken as given (every keypoint
unoccluded: the ray casts alone left out), in alternating rounds of one process, for each shipped target.

Protocol: the default random config at --resolution px (1024), --images images per round (in one shard, one
worker, the same seeds in both rows), --rounds rounds alternating the two rows after an untimed warm-up (the
process's renderer and scene made once); medians per row and the median paired ratio. Also the ray casts alone per image (Target.visible on the rendered views' poses).
Floor (issue 55): ray-cast visibility adds at most 5 % per image.
Also the filter's visibility table per target (build_visibility_table, appendages off and on: the cost each process
pays once per target file), after the target is loaded; --table-only times that alone (into visibility_table.json).

Run: .venv/bin/python bench/visibility_cost.py [--images N] [--rounds R] [--resolution PX] [--seed 61]
     [--table-only] [--out bench/results/visibility_cost.json]
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import json  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from envisat_pose.config import from_dict  # noqa: E402
from envisat_pose.datagen.factory import run_generate  # noqa: E402
from envisat_pose.datagen.generate_config import GenerateConfig  # noqa: E402
from envisat_pose.io import atomic_write_text  # noqa: E402
from envisat_pose.target import Target, load_target  # noqa: E402
from envisat_pose.target_visibility import build_visibility_table  # noqa: E402

TARGETS = ("models/envisat.xml", "models/upper_stage.xml", "models/cubesat_3u.xml")
FLOOR_RATIO = 1.05


def _generate_s(target: str, images: int, resolution_px: int, seed: int) -> float:
    cfg = from_dict(GenerateConfig, {"target": target, "num_images": images, "shard_size": images,
                                     "resolution_px": resolution_px, "seed": seed})
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        run_generate(cfg, os.path.join(out, "d"), workers=1, progress=False)
        return (time.perf_counter() - t0) / images


def _rays_ms(target: Target, n: int, seed: int) -> float:
    """Target.visible per call on n random poses at 2-5 reaches, ms."""
    rng = np.random.default_rng(seed)
    poses = []
    for _ in range(n):
        q = rng.standard_normal(4)
        q /= np.linalg.norm(q)
        w, x, y, z = q
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        poses.append((R, np.array([0.0, 0.0, rng.uniform(2.0, 5.0) * target.reach_m])))
    t0 = time.perf_counter()
    for R, t in poses:
        target.visible(R, t)
    return 1000.0 * (time.perf_counter() - t0) / n


def _table_s(target: Target) -> dict:
    """build_visibility_table's wall time per `appendages` value, s (not Target.visibility_table's process cache)."""
    out = {}
    for appendages in (False, True):
        t0 = time.perf_counter()
        build_visibility_table(target, appendages)
        out[f"appendages_{'on' if appendages else 'off'}"] = time.perf_counter() - t0
    return out


def main(argv=None) -> int:
    from _common import WholeFlagParser, count, description, out_file, provenance, results_path  # bench/_common.py

    p = WholeFlagParser(description=description(__doc__))
    p.add_argument("--images", type=count(), default=20)
    p.add_argument("--rounds", type=count(), default=3)
    p.add_argument("--resolution", type=count(), default=1024)
    p.add_argument("--seed", type=count(0), default=61)
    p.add_argument("--table-only", action="store_true", help="time the visibility table alone")
    p.add_argument("--out", type=out_file, default=results_path("visibility_cost"),
                   help="results JSON (default visibility_cost.json; with --table-only, visibility_table.json)")
    a = p.parse_args(argv)
    if a.table_only and a.out == results_path("visibility_cost"):  # the table alone: its own file by default
        a.out = results_path("visibility_table")
    rows = {}
    given = Target.visible
    for target in TARGETS:
        t = load_target(target)
        rows[t.name] = {"table_build_s": _table_s(t)}
        if a.table_only:
            continue
        _generate_s(target, 2, a.resolution, a.seed + 1)  # untimed: the renderer and the scene made once
        rounds = []
        for r in range(a.rounds):
            pair = {}
            for name in (("rays", "given") if r % 2 == 0 else ("given", "rays")):
                Target.visible = given if name == "rays" else (lambda self, R, tt, app=False: np.ones(
                    self.num_keypoints, bool))
                try:
                    pair[name] = _generate_s(target, a.images, a.resolution, a.seed)
                finally:
                    Target.visible = given
            rounds.append(pair)
        med = {k: statistics.median(x[k] for x in rounds) for k in ("rays", "given")}
        ratio = statistics.median(x["rays"] / x["given"] for x in rounds)
        rows[t.name].update({"s_per_image_with_rays": med["rays"], "s_per_image_visibility_given": med["given"],
                             "paired_ratio": ratio, "ray_casts_ms_per_image": _rays_ms(t, 200, a.seed),
                             "floor_at_most_5pct_met": ratio <= FLOOR_RATIO, "rounds": rounds})
    print(f"{'target':<14}{'table s (off/on)':>18}" + ("" if a.table_only else
          f"{'with rays s/img':>17}{'given s/img':>13}{'ratio':>8}{'rays ms/img':>13}"))
    for name, row in rows.items():
        table = row["table_build_s"]
        print(f"{name:<14}{table['appendages_off']:>11.2f} / {table['appendages_on']:.2f}" + ("" if a.table_only else
              f"{row['s_per_image_with_rays']:>17.3f}{row['s_per_image_visibility_given']:>13.3f}"
              f"{row['paired_ratio']:>8.3f}{row['ray_casts_ms_per_image']:>13.2f}"))
    result = {"protocol": {"images_per_round": a.images, "rounds": a.rounds, "resolution_px": a.resolution,
                           "seed": a.seed, "workers": 1, "table_only": a.table_only},
              "machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                          "load_avg_end": os.getloadavg()}, "targets": rows}
    result["provenance"] = provenance(a)
    os.makedirs(os.path.dirname(os.path.abspath(a.out)), exist_ok=True)
    atomic_write_text(a.out, json.dumps(result, indent=1) + "\n")
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    from _common import run_main  # bench/_common.py, beside this script

    run_main(main)
