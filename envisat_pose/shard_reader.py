"""The one reader of the factory's shards (design.md, Shard), for every stage and verb.

A shard is a plain tar; a sample is the run of consecutive members that share a key, the member's path up to
the first dot of its file name, the rest being the member's suffix (webdataset's rule: `000000012.mask.png` is
key `000000012`, suffix `mask.png`). Members come back as bytes: nothing is decoded or unpickled here (the
datagen writer and verifier, the trainer's and the detector's readers decode what they need).
"""

from __future__ import annotations

import os
import re
import tarfile
from collections.abc import Iterator

_KEY = re.compile(r"^((?:.*/|)[^./]+)[.]([^/]*)$")  # (key, suffix): the path up to the first dot of the name


def split_member(name: str) -> tuple[str, str] | None:
    """(key, suffix) of a member name, or None for a name without a suffix (not part of any sample)."""
    m = _KEY.match(name)
    return (m.group(1), m.group(2)) if m else None


def read_shard(path: str) -> Iterator[tuple[str, dict[str, bytes]]]:
    """The samples of one shard, in order: (key, {suffix: bytes}). Streams the tar (one pass, no seeking)."""
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
