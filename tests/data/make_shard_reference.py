"""Write tests/data/envisat_shards_reference.npz: two small ENVISAT datasets (128 px, seed 48: 6 random views in
shards of 3, 4 sequence frames in shards of 2), decoded: each sample's image, depth and mask as arrays and its label
as JSON text, read by tests/datagen/test_targets.py (ENVISAT's datasets unchanged by the work on other targets).

History: the shards of commit 60424e2 (before any target work) were pinned by SHA-256, which the code after the
target work reproduced on the machine that recorded them; bytes of rendered images and printed floats differ
between machines, so the same code's output was recorded decoded on 2026-12-02 (an AMD EPYC with AVX-512) and is
compared within the tolerances of tests/data/compare.py. Re-recorded the same day when the sun's shadow map was
sized to the target (datagen/render.py, SHADOW_MAP_PX): only shadow edges moved (the 128-px random views' blurred
images up to 3.7 DN apart, against the 3 DN the comparison allows for machines).

Run: .venv/bin/python tests/data/make_shard_reference.py [--out tests/data/envisat_shards_reference.npz]
"""

from __future__ import annotations

import os
import sys
import tempfile

import cv2
import numpy as np

from envisat_pose.whole_flags import WholeFlagParser

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "envisat_shards_reference.npz")
DATASETS = {"random": (6, 3), "sequence": (4, 2)}  # mode: (images, shard size)


def generate(mode: str, out_dir: str) -> dict:
    """One of the two datasets, written to out_dir; its manifest."""
    from envisat_pose.config import from_dict
    from envisat_pose.datagen.factory import run_generate
    from envisat_pose.datagen.generate_config import GenerateConfig

    n, size = DATASETS[mode]
    cfg = from_dict(GenerateConfig, {"mode": mode, "num_images": n, "shard_size": size, "resolution_px": 128,
                                     "seed": 48})
    return run_generate(cfg, out_dir)


def decode(out_dir: str, manifest: dict, mode: str) -> dict[str, np.ndarray]:
    """{mode/key/member: array} of a dataset's samples: images decoded as stored (uint8, uint16), the label as
    its JSON text."""
    from envisat_pose.shard_reader import read_shard

    found = {}
    for entry in manifest["shards"]:
        for key, members in read_shard(os.path.join(out_dir, entry["name"])):
            for suffix, data in members.items():
                name = f"{mode}/{key}/{suffix}"
                if suffix.endswith("png"):
                    found[name] = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
                else:
                    found[name] = np.array(data.decode())
    return found


def reference(work: str) -> dict[str, np.ndarray]:
    """Both datasets, generated in the folder work, decoded."""
    found = {}
    for mode in DATASETS:
        out = os.path.join(work, mode)
        found.update(decode(out, generate(mode, out), mode))
    return found


def main(argv=None) -> int:
    p = WholeFlagParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default=OUT)
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as work:
        arrays = reference(work)
    np.savez_compressed(args.out, **arrays)
    print(f"wrote {args.out}: {len(arrays)} arrays, {os.path.getsize(args.out)} bytes", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
