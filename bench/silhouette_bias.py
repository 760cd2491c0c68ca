"""Where the target's silhouette sits in the image itself, before any detector (the bias's causes).

For freshly rendered frames (1024 px, stored clean; the space camera applied on read, as a detector sees them)
it measures the silhouette edges of the box against the labelled corners' projection: along every edge of the
convex hull of the visible corners at least MIN_EDGE_PX long, at stations every 2 px from 20 px in from its
ends, the image is sampled across the edge (bicubic, 0.25 px steps, +-6 px) and the edge located by the area
method (inside plateau 4-6 px in, outside 4-6 px out: edge = -4 + integral from -4 to 4 of the normalized
profile; exact for a straight step blurred by any symmetric PSF in a linear image). Offsets are signed,
positive outward, px. A station counts where the mask shows one face of the body from 1 to 6 px inside (no thin
strip of another face at the rim) and background 3 px outside, the contrast exceeds 20 grey levels, and the
inside is uniform (its samples 1-6 px in within 10 % of the contrast: textures, shadow-map acne on a face lit
at grazing incidence and slivers would bias the plateau, not the edge). Rows:
per look (random views with the MJCF's plain materials; random views with the appearance on; the default
scenario's sequence), clean and through the space camera, all stations and split by whether the profile
reaches the 8-bit ceiling (>= 250: clipped, bloomed). The segmentation mask's own edge is checked the same way
(the render's geometry against the labels). The station and area-method math is the library's
(pipelines/adaptation/edge_range.py, which `envisat adapt` uses without a mask); this bench passes the render's mask.

Run: .venv/bin/python bench/silhouette_bias.py [--images 40] [--seed 4242]  (writes bench/results/silhouette_bias.json)
"""

from __future__ import annotations

import json
import os
import platform
import sys
import tempfile

os.environ.setdefault("MUJOCO_GL", "osmesa")

import numpy as np

MIN_EDGE_PX, END_PX = 60.0, 20.0  # at 1024 px (the library's defaults reach the box's short edges at 512 px)

LOOKS = {
    "random_plain": {"appearance": {"enabled": False}, "appendages": False},
    "random_appearance": {"appendages": False},
    "sequence_default": {"mode": "sequence", "sequence": {"scenario": "default"}},
}


def edge_offsets(image: np.ndarray, mask: np.ndarray, corners_px: np.ndarray, visible: np.ndarray
                 ) -> list[tuple[float, bool]]:
    """(offset px, clipped) of every usable station of the hull's edges (module doc): the library's
    pipelines/adaptation/edge_range.edge_stations with the render's mask and this bench's 60 px edges, 20 px from their ends."""
    from envisat_pose.pipelines.adaptation.edge_range import edge_stations

    st = edge_stations(image, corners_px, visible, mask=mask, min_edge_px=MIN_EDGE_PX, end_px=END_PX)
    return [(float(o), bool(c)) for o, c in zip(st.offset_px, st.clipped)]


def summary(rows: list[tuple[float, bool]]) -> dict:
    def stats(v: np.ndarray) -> dict:
        if len(v) == 0:
            return {"n": 0, "mean_px": None, "median_px": None, "se_px": None}
        return {"n": int(len(v)), "mean_px": float(v.mean()), "median_px": float(np.median(v)),
                "se_px": float(v.std() / np.sqrt(len(v)))}

    e = np.array([r[0] for r in rows])
    c = np.array([r[1] for r in rows], dtype=bool)
    return {"all": stats(e), "clipped": stats(e[c]) if len(e) else stats(e), "unclipped": stats(e[~c]) if len(e) else stats(e)}


def measure_look(name: str, extra: dict, images: int, seed: int, tmp: str) -> dict:
    from envisat_pose.config import from_dict
    from envisat_pose.datagen.corrupt import apply_corruption
    from envisat_pose.datagen.factory import run_generate
    from envisat_pose.datagen.generate_config import GenerateConfig
    from envisat_pose.datagen.shards import decode_png
    from envisat_pose.shard_reader import read_shard

    cfg = from_dict(GenerateConfig, {"num_images": images, "shard_size": images, "resolution_px": 1024,
                                     "seed": seed, "storage": "clean", **extra})
    out = os.path.join(tmp, name)
    manifest = run_generate(cfg, out)
    rows = {"clean": [], "space_camera": [], "mask": []}
    for entry in manifest["shards"]:
        for _, members in read_shard(os.path.join(out, entry["name"])):
            label = json.loads(members["json"])
            clean = decode_png(members["png"])
            mask = decode_png(members["mask.png"])
            q = np.asarray(label["corners_px"], dtype=np.float64)
            vis = np.asarray(label["visible"], bool) & np.asarray(label["in_frame"], bool)
            rows["clean"] += edge_offsets(clean, mask, q, vis)
            rows["space_camera"] += edge_offsets(apply_corruption(clean, label["corruption"]), mask, q, vis)
            body = np.where((mask >= 1) & (mask <= 6), 200, 0).astype(np.uint8)
            rows["mask"] += edge_offsets(body, mask, q, vis)
    return {k: summary(v) for k, v in rows.items()}


def main() -> None:
    from _common import WholeFlagParser, count, description, out_file, provenance, results_path  # bench/_common.py

    ap = WholeFlagParser(description=description(__doc__))
    ap.add_argument("--images", type=count(), default=40, help="frames per look")
    ap.add_argument("--seed", type=count(0), default=4242)
    ap.add_argument("--out", type=out_file, default=results_path("silhouette_bias"))
    args = ap.parse_args()
    from envisat_pose.io import atomic_write_text

    result = {"machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": sys.version.split()[0]},
              "protocol": f"{args.images} frames per look at 1024 px, seed {args.seed}; offsets px, + outward",
              "looks": {}}
    print(f"{'look':18s} {'image':12s} {'stations':>8s} {'mean':>7s} {'median':>7s} {'se':>6s} "
          f"{'clipped n':>9s} {'mean':>7s} {'unclipped n':>11s} {'mean':>7s}")
    with tempfile.TemporaryDirectory(prefix="silhouette-") as tmp:
        for name, extra in LOOKS.items():
            res = measure_look(name, extra, args.images, args.seed, tmp)
            result["looks"][name] = res
            for kind, s in res.items():
                a, c, u = s["all"], s["clipped"], s["unclipped"]

                def f(v):
                    return "      -" if v is None else f"{v:+7.3f}"
                print(f"{name:18s} {kind:12s} {a['n']:8d} {f(a['mean_px'])} {f(a['median_px'])} "
                      f"{'' if a['se_px'] is None else format(a['se_px'], '6.3f'):>6s} {c['n']:9d} {f(c['mean_px'])} "
                      f"{u['n']:11d} {f(u['mean_px'])}", flush=True)
    result["provenance"] = provenance(args)
    atomic_write_text(args.out, json.dumps(result, indent=1, sort_keys=True) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    from _common import run_main  # bench/_common.py, beside this script

    run_main(main)
