"""The one reader of the factory's shards (design.md, Shard), for every stage and verb.

A shard is a plain tar; a sample is the run of consecutive members that share a key, the member's path up to
the first dot of its file name, the rest being the member's suffix (webdataset's rule: `000000012.mask.png` is
key `000000012`, suffix `mask.png`). Members come back as bytes: nothing is decoded or unpickled here (the
datagen writer and verifier, the trainer's and the detector's readers decode what they need).

Every reader of a generated dataset first takes its shards from `checked_shards`: each shard the manifest lists is
checked against it (`shard_problem`, the one shard check: its size, its sha256, then its samples counted from the
tar's headers; once per run), and a damaged one is refused in one line naming it, or left out when the reader was
asked to skip damaged shards. A shard that still fails while being read (changed under a running job, or a folder
without a manifest) is the same one line (ShardReadError), never a traceback. A dataset's manifest is read only
through `load_dataset_manifest` (the parsed record, checked), on the core's manifest reader
(resumable.read_manifest).
"""

from __future__ import annotations

import contextlib
import glob
import os
import re
import tarfile
import zlib
from collections.abc import Iterator

from envisat_pose.config import InputError
from envisat_pose.io import sha256_file
from envisat_pose.pools import usable_cores
from envisat_pose.resumable import read_manifest

REQUIRED_MEMBERS = frozenset({"json", "png"})  # what every sample of a shard holds: its label and its image
_TAR_BLOCK = 512  # a tar's record: every header, and every member's data padded up to a multiple of it
_ZERO_BLOCK = bytes(_TAR_BLOCK)
_PLAIN_TYPES = (b"0", b"\0", b"5")  # a regular file (new and old tag) or a folder: the headers the quick walk reads
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


def load_dataset_manifest(data_dir: str, field: str = "dataset", required: bool = True) -> dict | None:
    """The manifest of a dataset folder, parsed and checked: the one reader of a dataset's manifest. None when the
    folder has none and it is not `required`. InputError naming the field and the folder when the folder is
    missing, the manifest is missing (required), unreadable, or not a dataset manifest (which entry and key)."""
    if not os.path.isdir(data_dir):
        raise InputError(f"{field} {data_dir!r}: no such folder")
    manifest = read_manifest(data_dir, field)
    if manifest is None:
        if required:
            raise InputError(f"{field} {data_dir!r}: no manifest.json: not a generated dataset")
        return None
    why = _manifest_problem(manifest)
    if why:
        raise InputError(f"{field} {data_dir!r}: manifest.json is not a dataset manifest ({why})")
    return manifest


def unfinished_dataset(manifest: dict) -> str | None:
    """'an unfinished dataset (n of N shards)' when a dataset's manifest is not marked complete (a generate run
    interrupted and not resumed: only the shards written so far are there), else None."""
    if manifest.get("complete"):
        return None
    expected = manifest.get("num_shards", "?")
    return f"an unfinished dataset ({len(manifest['shards'])} of {expected} shards)"


def _manifest_problem(manifest: dict) -> str | None:
    """What keeps a manifest from being a dataset's (None: nothing): a list 'shards' of entries, each with the
    plain file name of a shard (each name once) and its count of samples and, where given (older datasets have no
    size), its size (non-negative integers) and its sha256 (text); a 'config' and a 'target', where given, are
    tables; 'num_shards' and 'num_images', where given, non-negative integers."""
    entries = manifest.get("shards")
    if not isinstance(entries, list):
        return "expected a list 'shards' of entries with a name and a count"
    first: dict[str, int] = {}  # a shard's name: its entry's place
    for i, e in enumerate(entries):
        if not isinstance(e, dict) or not isinstance(e.get("name"), str) or "count" not in e:
            return f"shards[{i}]: expected an entry with a name and a count"
        if e["name"] in ("", ".", "..") or os.path.basename(e["name"]) != e["name"] or "\\" in e["name"]:
            return f"shards[{i}].name = {e['name']!r}: expected a file name inside the folder"
        if first.setdefault(e["name"], i) != i:  # every reader would read its samples twice
            return (f"shards[{i}].name = {e['name']!r}: listed twice (also shards[{first[e['name']]}]); "
                    "expected each once")
        for key in ("count", "bytes"):
            if key in e and not (type(e[key]) is int and e[key] >= 0):
                return f"shards[{i}].{key} = {e[key]!r}: expected a non-negative integer"
        if "sha256" in e and not isinstance(e["sha256"], str):
            return f"shards[{i}].sha256 = {e['sha256']!r}: expected text"
    for key in ("config", "target"):
        if manifest.get(key) is not None and not isinstance(manifest[key], dict):
            return f"{key}: expected a table, got {type(manifest[key]).__name__}"
    for key in ("num_shards", "num_images"):
        if key in manifest and not (type(manifest[key]) is int and manifest[key] >= 0):
            return f"{key} = {manifest[key]!r}: expected a non-negative integer"
    return None


def shard_problem(path: str, entry: dict) -> str | None:
    """What makes one shard differ from its manifest entry (None: it matches), the one shard check: missing, its
    size (entry 'bytes', first: a truncated file costs a stat), its sha256 (entry 'sha256'); a shard whose entry
    has no sha256 then has its samples walked from the tar's headers (no member is read): a tar that cannot be
    walked, a sample without its label or image (REQUIRED_MEMBERS), another number of samples than the entry's
    'count'. A matching sha256 says the bytes are those the factory finished, samples and count included (it
    records an entry only once its shard is whole), so the walk would add nothing but time (bench/shard_check.py's
    floor: the check within 2 % of an epoch). An entry without a size or a count skips that step."""
    if not os.path.isfile(path):
        return "missing"
    size = os.path.getsize(path)
    if isinstance(entry.get("bytes"), int) and size != entry["bytes"]:
        return f"size {size} bytes, manifest says {entry['bytes']}"
    digest = sha256_file(path) if entry.get("sha256") else None
    if digest is not None:
        return None if digest == entry["sha256"] else (
            f"sha256 {digest[:12]}..., manifest says {str(entry['sha256'])[:12]}...")
    try:
        samples = sample_suffixes(path)
    except (tarfile.TarError, OSError, EOFError, zlib.error) as err:
        return f"unreadable tar ({type(err).__name__}: {' '.join(str(err).split())})"
    for key, suffixes in samples:
        if not REQUIRED_MEMBERS <= suffixes:
            return f"sample {key} lacks {', '.join(sorted(REQUIRED_MEMBERS - suffixes))}"
    if isinstance(entry.get("count"), int) and len(samples) != entry["count"]:
        return f"{len(samples)} samples, manifest says {entry['count']}"
    return None


def sample_suffixes(path: str) -> list[tuple[str, set[str]]]:
    """(key, {suffix}) of each sample of a shard, in order, from the tar's member names alone (read_shard's
    grouping: consecutive members that share a key). tarfile.TarError when the tar cannot be walked."""
    samples: list[tuple[str, set[str]]] = []
    for name in tar_member_names(path):
        split = split_member(name)
        if split is None:
            continue
        if not samples or samples[-1][0] != split[0]:
            samples.append((split[0], set()))
        samples[-1][1].add(split[1])
    return samples


def tar_member_names(path: str) -> list[str]:
    """The names of a tar's file members, in order, from its headers alone (each member's data is skipped, not
    read: one small read per member). A plain USTAR or old-style tar (what the factory writes) is walked here; any
    other (pax or GNU headers, compressed, or a header that does not check out) by tarfile, whose TarError then
    says what is wrong."""
    names = _plain_member_names(path)
    if names is not None:
        return names
    with tarfile.open(path, "r:*") as tar:
        return [info.name for info in tar if info.isfile()]


def _plain_member_names(path: str) -> list[str] | None:
    """tar_member_names of a plain tar; None when the file is anything else (then tarfile reads it)."""
    end, pos, names = os.path.getsize(path), 0, []
    with open(path, "rb") as fh:
        while pos + _TAR_BLOCK <= end:
            fh.seek(pos)
            header = fh.read(_TAR_BLOCK)
            if header == _ZERO_BLOCK:
                return names
            kind = header[156:157]
            try:
                # the header's checksum: its bytes summed, the checksum field's own 8 counted as spaces
                plain = kind in _PLAIN_TYPES and tarfile.nti(header[148:156]) == sum(header) - sum(header[148:156]) + 256
                size = tarfile.nti(header[124:136])
            except tarfile.TarError:
                return None
            if not plain or size < 0:
                return None
            name = tarfile.nts(header[:100], "utf-8", "surrogateescape")
            if header[257:263] == b"ustar\0" and header[345] != 0:  # USTAR: a long name's leading folders
                name = tarfile.nts(header[345:500], "utf-8", "surrogateescape") + "/" + name
            if kind != b"5":
                names.append(name)
            pos += _TAR_BLOCK + -(-size // _TAR_BLOCK) * _TAR_BLOCK
    return names if pos == end else None  # a file that ends inside a member: tarfile says where


def shard_problems(data_dir: str, entries: list[dict], threads: int | None = None) -> list[str | None]:
    """shard_problem of every manifest entry, in order, the shards hashed on `threads` threads at once (default:
    one per usable core; hashlib and file reads release the GIL, so the check takes the wall time of the cores)."""
    from concurrent.futures import ThreadPoolExecutor

    threads = max(1, min(len(entries), threads or usable_cores()))
    if threads == 1:
        return [shard_problem(os.path.join(data_dir, e["name"]), e) for e in entries]
    with ThreadPoolExecutor(threads, thread_name_prefix="shard-check") as pool:
        return list(pool.map(lambda e: shard_problem(os.path.join(data_dir, e["name"]), e), entries))


def checked_shards(data_dir: str, skip_damaged: bool = False, field: str = "data_dir"
                   ) -> tuple[list[str], list[str]]:
    """The shard files of a dataset folder to read, each checked against the folder's manifest.json (shard_problem:
    size, sha256, samples), and the names of the damaged ones left out: (paths, skipped).

    Shards the manifest lists with no samples are left out; shards it does not list (an interrupted run's) are
    not read. A damaged shard (shard_problem says why) is a DamagedShardError naming the field,
    the folder and the shard, unless skip_damaged: then it is left out and named in `skipped`. A folder without
    a manifest (shards made elsewhere) has nothing to check against: every *.tar in it, in name order, is read
    as it is (read_shard still stops in one line at a damaged one). InputError when nothing is left to read."""
    manifest = load_dataset_manifest(data_dir, field, required=False)
    if manifest is None:
        paths, skipped = sorted(glob.glob(os.path.join(glob.escape(data_dir), "*.tar"))), []
    else:
        paths, skipped = [], []
        entries = [e for e in manifest["shards"] if e["count"]]
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


def sample_total(paths: list[str], limit: int | None = None) -> int | None:
    """How many samples the shard files hold, from their folders' manifests (a progress bar's total; at most
    `limit`); None when a shard is not listed in one (shards made elsewhere: unknown without reading them)."""
    counts = {}
    for folder in {os.path.dirname(os.path.abspath(p)) for p in paths}:
        manifest = load_dataset_manifest(folder, required=False)
        for e in (manifest or {}).get("shards", []):
            counts[os.path.join(folder, e["name"])] = e["count"]
    try:
        n = sum(counts[os.path.abspath(p)] for p in paths)
    except KeyError:
        return None
    return n if limit is None else min(n, limit)


@contextlib.contextmanager
def skip_hint():
    """A damaged shard found under this block (DamagedShardError: one line naming the field, the folder and the
    shard) also says how to go on without it: `skip_damaged` (a verb shows its --skip-damaged flag)."""
    try:
        yield
    except DamagedShardError as err:
        raise InputError(f"{err}; `skip_damaged` goes on without it, `envisat dataset verify` lists every "
                         "problem") from None
