"""WebDataset shards: deterministic tar writing and atomic publication (reading, the manifest's reader and the one
shard check: the core's envisat_pose/shard_reader.py).

A shard is a plain tar of samples, each sample's members `<key>.depth.png`, `<key>.json`, `<key>.mask.png`,
`<key>.png` consecutive (design.md, Shard contract). Members carry a fixed mtime, owner and mode, so the same
samples give the same bytes in any process, on any backend.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import tarfile

import cv2
import numpy as np

from envisat_pose.io import atomic_path

MEMBER_SUFFIXES = ("depth.png", "json", "mask.png", "png")  # sorted: the order inside a sample
# zlib level 1 with the PNG filter and zlib strategy that measured fastest per kind of image (1024 px, one core):
# noisy images and masks without filtering and with run-length matching, smooth 16-bit depth with the Sub filter.
PNG_PARAMS = {
    "image": [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE,
              cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE],
    # depth is zero off the target: run-length coding without a filter is both faster and smaller here
    "depth": [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE,
              cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE],
}


SHARD_GLOB = "shard-*.tar"  # every shard's name matches it (a file matching it that the manifest lacks is a stray)


def shard_name(index: int) -> str:
    """File name of shard `index`: shard-000000.tar."""
    return f"shard-{index:06d}.tar"


def sample_key(global_index: int) -> str:
    """WebDataset key of the dataset's sample `global_index` (no dots: the key ends at the first dot)."""
    return f"{global_index:09d}"


def encode_png(image: np.ndarray, kind: str = "image") -> bytes:
    """PNG bytes of an 8- or 16-bit single-channel image; kind 'image' (also masks) or 'depth' picks the
    encoder settings. Deterministic: the same pixels give the same bytes."""
    ok, buf = cv2.imencode(".png", image, PNG_PARAMS[kind])
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def decode_png(data: bytes) -> np.ndarray:
    """An image from PNG bytes, keeping its bit depth. (H, W) uint8 or uint16."""
    return cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)


def label_bytes(label: dict) -> bytes:
    """The label as compact, key-sorted JSON (stable bytes)."""
    return json.dumps(label, sort_keys=True, separators=(",", ":")).encode("utf-8")


def _tar_member(name: str, size: int) -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.size = size
    info.mtime = 0
    info.mode = 0o644
    info.uid = info.gid = 0
    info.uname = info.gname = ""
    return info


class ShardWriter:
    """Writes one shard to a temporary file next to its final path; the `with` block's end renames it into place.

    Use as a context manager: an exception leaves no file (the temporary removed), a kill none under the final
    name (the job removes a stopped worker's temporary: resumable.ResumableJob.run).
    """

    def __init__(self, path: str):
        self.path = path
        self.count = 0
        self._ctx = atomic_path(path, suffix=".tar")
        self._tmp = self._ctx.__enter__()
        self._tar = tarfile.open(self._tmp, "w", format=tarfile.USTAR_FORMAT)

    def write(self, key: str, members: dict[str, bytes]) -> None:
        """Add one sample: members maps a suffix of MEMBER_SUFFIXES to its bytes (absent ones are skipped)."""
        for suffix in MEMBER_SUFFIXES:
            if suffix in members:
                data = members[suffix]
                self._tar.addfile(_tar_member(f"{key}.{suffix}", len(data)), io.BytesIO(data))
        self.count += 1

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        try:
            if exc_type is None:
                self._tar.close()
                with open(self._tmp, "rb+") as fh:
                    os.fsync(fh.fileno())
            else:  # TarFile's own exit: no end-of-archive written after a failed write (a full disk: a 2nd error)
                with contextlib.suppress(OSError):
                    self._tar.__exit__(exc_type, exc, tb)
                raise exc
        except BaseException as err:  # the temporary file goes, whatever stopped the shard
            self._ctx.__exit__(type(err), err, err.__traceback__)
            if isinstance(err, OSError) and err.filename is None:  # tarfile's writes name no file: the shard's
                raise OSError(err.errno, err.strerror, self.path) from err
            raise
        return self._ctx.__exit__(None, None, None)
