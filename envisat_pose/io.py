"""Atomic file writing: a temp file in the destination's folder, then os.replace, so a killed job never
leaves a partial output under the final name."""

from __future__ import annotations

import contextlib
import os
import tempfile


@contextlib.contextmanager
def atomic_path(path: str, suffix: str = ""):
    """Yield a temporary path next to `path`; on success it is renamed to `path`, on error removed."""
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=suffix or os.path.splitext(path)[1], dir=folder)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    mode = 0o666 & ~umask
    os.chmod(tmp, mode)  # mkstemp makes 0600 files; outputs get the user's usual mode
    try:
        yield tmp
        os.chmod(tmp, mode)  # again: a writer may have replaced the file (safetensors' save_file makes it 0600)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.remove(tmp)
        raise


def atomic_write_text(path: str, text: str) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)


def check_writable_output(path: str, field: str = "out") -> None:
    """Fail early (InputError) when `path` cannot be written: its folder is missing or read-only."""
    from envisat_pose.config import InputError

    folder = os.path.dirname(os.path.abspath(path)) or "."
    if os.path.isdir(path):
        raise InputError(f"--{field} {path!r} is a directory, expected a file path")
    if not os.path.isdir(folder):
        raise InputError(f"--{field} {path!r}: folder {folder!r} does not exist")
    if not os.access(folder, os.W_OK):
        raise InputError(f"--{field} {path!r}: folder {folder!r} is not writable")


def save_npz(path: str, arrays: dict) -> None:
    """Write arrays to an .npz atomically and byte-reproducibly (fixed zip timestamps, sorted keys).

    numpy.savez stamps every member with the current time, so the same data would give different bytes.
    """
    import zipfile

    import numpy as np

    with atomic_path(path, suffix=".npz") as tmp:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
            for key in sorted(arrays):
                info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.external_attr = 0o644 << 16
                with zf.open(info, "w", force_zip64=True) as fh:
                    np.lib.format.write_array(fh, np.asanyarray(arrays[key]), allow_pickle=False)


def sha256_file(path: str) -> str:
    """Hex sha256 of a file, read in 1 MiB blocks (how resumable jobs check what an earlier run wrote)."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def json_safe(x):
    """Plain data for strict JSON: NaN and infinities become null (in dicts, lists and tuples, recursively)."""
    import math

    if isinstance(x, dict):
        return {k: json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x
