"""The one reader of the factory's shards (design.md, Shard), for every stage and verb.

A shard is a plain tar; a sample is the run of consecutive members that share a key, the member's path up to
the first dot of its file name, the rest being the member's suffix (webdataset's rule: `000000012.mask.png` is
key `000000012`, suffix `mask.png`). Members come back as bytes: nothing is decoded or unpickled here (the
datagen writer and verifier, the trainer's and the detector's readers decode what they need).

Every reader of a generated dataset first takes its shards from `checked_shards`: each shard the manifest lists is
checked against it (its size, then its sha256; once per run), and a damaged one is refused in one line naming it, or
left out when the reader was asked to skip damaged shards. A shard that still fails while being read (changed under
a running job, or a folder without a manifest) is the same one line (ShardReadError), never a traceback.
"""

from __future__ import annotations

import glob
import json
import os
import re
import tarfile
import zlib
from collections.abc import Iterator

from envisat_pose.config import InputError
from envisat_pose.io import sha256_file

MANIFEST = "manifest.json"

_KEY = re.compile(r"^((?:.*/|)[^./]+)[.]([^/]*)$")  # (key, suffix): the path up to the first dot of the name


def split_member(name: str) -> tuple[str, str] | None:
    """(key, suffix) of a member name, or None for a name without a suffix (not part of any sample)."""
    m = _KEY.match(name)
    return (m.group(1), m.group(2)) if m else None


class ShardReadError(InputError, tarfile.TarError):
    """A shard that cannot be read to its end: one line naming the file (an InputError for the verbs, still a
    TarError for the verifier, which lists it among a dataset's problems)."""


class DamagedShardError(InputError):
    """A shard that does not match its dataset's manifest. name: the shard's file name; why: what differs."""

    def __init__(self, message: str, name: str, why: str):
        super().__init__(message)
        self.name, self.why = name, why


def read_shard(path: str) -> Iterator[tuple[str, dict[str, bytes]]]:
    """The samples of one shard, in order: (key, {suffix: bytes}). Streams the tar (one pass, no seeking).
    ShardReadError naming the file when it cannot be read to its end (truncated, a damaged header)."""
    try:
        yield from _tar_samples(path)
    except (tarfile.TarError, OSError, EOFError, zlib.error) as err:
        raise ShardReadError(f"shard {path!r} cannot be read ({type(err).__name__}: {err}); the file is damaged "
                             "or was changed while being read") from None


def _tar_samples(path: str) -> Iterator[tuple[str, dict[str, bytes]]]:
    with tarfile.open(path, "r|*") as tar:
        key, members = None, {}
        for info in tar:
            split = split_member(info.name) if info.isfile() else None
            if split is None:
                continue
            k, suffix = split
            if k != key and key is not None:
                yield key, members
                members = {}
            key = k
            members[suffix] = tar.extractfile(info).read()
        if key is not None:
            yield key, members


def read_shards(paths: list[str]) -> Iterator[tuple[str, str, dict[str, bytes]]]:
    """The samples of several shards in the given order: (where, key, members), where = 'shard file name:key'
    (for messages that name the sample)."""
    for path in paths:
        name = os.path.basename(path)
        for key, members in read_shard(path):
            yield f"{name}:{key}", key, members


# ---------------------------------------------------------------------------------------------------------
# The check every reader of a generated dataset makes before it reads


def load_dataset_manifest(data_dir: str, field: str = "data_dir") -> dict | None:
    """The manifest of a dataset folder (None: the folder has none); InputError naming the field when the folder
    is missing or the manifest is not a dataset manifest."""
    if not os.path.isdir(data_dir):
        raise InputError(f"{field} {data_dir!r}: no such folder")
    path = os.path.join(data_dir, MANIFEST)
    if not os.path.exists(path):
        return None
    try:
        with open(path, encoding="utf-8") as fh:
            manifest = json.load(fh)
    except (OSError, ValueError) as err:
        raise InputError(f"{field} {data_dir!r}: unreadable {MANIFEST} ({err})") from None
    entries = manifest.get("shards") if isinstance(manifest, dict) else None
    if not isinstance(entries, list) or not all(isinstance(e, dict) and isinstance(e.get("name"), str)
                                                 for e in entries):
        raise InputError(f"{field} {data_dir!r}: {MANIFEST} is not a dataset manifest (expected a list 'shards' "
                         "of entries with a name)")
    return manifest


def shard_problem(path: str, entry: dict) -> str | None:
    """What makes one shard differ from its manifest entry (None: it matches): missing, its size (entry 'bytes',
    read first: a truncated file costs a stat), then its sha256 (entry 'sha256')."""
    if not os.path.isfile(path):
        return "missing"
    size = os.path.getsize(path)
    if isinstance(entry.get("bytes"), int) and size != entry["bytes"]:
        return f"size {size} bytes, manifest says {entry['bytes']}"
    digest = sha256_file(path) if entry.get("sha256") else None
    if digest is not None and digest != entry["sha256"]:
        return f"sha256 {digest[:12]}..., manifest says {str(entry['sha256'])[:12]}..."
    return None


def shard_problems(data_dir: str, entries: list[dict], threads: int | None = None) -> list[str | None]:
    """shard_problem of every manifest entry, in order, the shards hashed on `threads` threads at once (default:
    one per core; hashlib and file reads release the GIL, so the check takes the wall time of the cores)."""
    from concurrent.futures import ThreadPoolExecutor

    threads = max(1, min(len(entries), threads or os.cpu_count() or 1))
    if threads == 1:
        return [shard_problem(os.path.join(data_dir, e["name"]), e) for e in entries]
    with ThreadPoolExecutor(threads, thread_name_prefix="shard-check") as pool:
        return list(pool.map(lambda e: shard_problem(os.path.join(data_dir, e["name"]), e), entries))


def checked_shards(data_dir: str, skip_damaged: bool = False, field: str = "data_dir"
                   ) -> tuple[list[str], list[str]]:
    """The shard files of a dataset folder to read, each checked against the folder's manifest.json (size, then
    sha256), and the names of the damaged ones left out: (paths, skipped).

    Shards the manifest lists with no samples are left out; shards it does not list (an interrupted run's) are
    not read. A damaged shard (missing, another size, another sha256) is a DamagedShardError naming the field,
    the folder and the shard, unless skip_damaged: then it is left out and named in `skipped`. A folder without
    a manifest (shards made elsewhere) has nothing to check against: every *.tar in it, in name order, is read
    as it is (read_shard still stops in one line at a damaged one). InputError when nothing is left to read."""
    manifest = load_dataset_manifest(data_dir, field)
    if manifest is None:
        paths, skipped = sorted(glob.glob(os.path.join(glob.escape(data_dir), "*.tar"))), []
    else:
        paths, skipped = [], []
        entries = [e for e in manifest["shards"] if e.get("count", 1)]
        for entry, why in zip(entries, shard_problems(data_dir, entries)):
            if why is None:
                paths.append(os.path.join(data_dir, entry["name"]))
            elif skip_damaged:
                skipped.append(entry["name"])
            else:
                raise DamagedShardError(f"{field} {data_dir!r}: shard {entry['name']} is damaged ({why})",
                                        entry["name"], why)
    if not paths:
        left = f" ({len(skipped)} damaged shard(s) skipped: {', '.join(skipped)})" if skipped else ""
        raise InputError(f"{field} {data_dir!r}: empty dataset (no shards with samples){left}")
    return paths, skipped
