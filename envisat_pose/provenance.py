"""Names of datasets and files that travel: no path of the machine they were made on; the source a result was
made with (git_hash, source_line).

A model card and the weights' metadata name a dataset by its folder's name and the sha256 of its manifest.json
(the manifest holds the full generate config and every shard's size), so the same data regenerated anywhere by
the same command has the same name; a file by its name relative to a scratch or work folder.
"""

from __future__ import annotations

import os
import re
import subprocess

from envisat_pose.io import sha256_file
from envisat_pose.resumable import manifest_path

# an absolute path of a machine: a token starting with "/" and a path component (e.g. /tmp/dcal,
# /work/main/out/leg6/hseq633, /home/me/x.json), not a ratio such as "1/2" or a unit such as "px/s"
ABS_PATH_RE = re.compile(r"(?<![\w.~/-])/(?:[A-Za-z0-9_.~+-]+)(?:/[A-Za-z0-9_.~+=-]*)*")
# scratch and home roots whose prefix says nothing about the data (dropped by relative_name)
_ROOT_RE = re.compile(r"^/(?:tmp|var/tmp|root|home/[^/]+|work/[^/]+|Users/[^/]+|mnt/[^/]+|scratch/[^/]+)(?:/|$)")


def find_absolute_paths(text: str) -> list[str]:
    """The absolute machine paths in `text` (empty when it travels)."""
    out = []
    for m in ABS_PATH_RE.finditer(text):
        token = m.group(0)
        # "/" followed by a word alone (e.g. "and/or" is excluded by the look-behind; "/s" or "/frame" is a
        # unit): a path has a second component or a known root
        if token.count("/") >= 2 or _ROOT_RE.match(token):
            out.append(token)
    return out


def relative_name(path: str) -> str:
    """A path as it travels: relative paths unchanged; an absolute one without its scratch or work root
    (/tmp/drun/checkpoint.safetensors -> drun/checkpoint.safetensors, /work/main/out/leg6/dcal ->
    out/leg6/dcal); any other absolute path -> its last two components."""
    if not path.startswith("/"):
        return path
    if _ROOT_RE.fullmatch(path.rstrip("/") + "/"):
        return "a scratch folder"
    stripped = _ROOT_RE.sub("", path.rstrip("/"), count=1)
    if stripped and stripped != path.rstrip("/"):
        return stripped
    parts = [p for p in path.split("/") if p]
    return "/".join(parts[-2:]) if parts else "."


def scrub_paths(text: str) -> str:
    """`text` with every absolute machine path replaced by its relative_name."""
    return ABS_PATH_RE.sub(lambda m: relative_name(m.group(0)) if find_absolute_paths(m.group(0)) else m.group(0),
                           text)


def manifest_sha256(folder: str) -> str | None:
    """sha256 of a generated dataset's manifest.json (None when it has none)."""
    path = manifest_path(folder)
    return sha256_file(path) if os.path.isfile(path) else None


def dataset_ref(folder: str) -> str:
    """A dataset as a card or a calibration record names it: 'NAME (manifest sha256 0123456789abcdef)'."""
    name = os.path.basename(os.path.normpath(folder)) or "."
    h = manifest_sha256(folder)
    return f"{name} (manifest sha256 {h[:16]})" if h else relative_name(os.path.normpath(folder))


def weights_ref(path: str) -> dict:
    """A weights file named by its file name and sha256 (no path of this machine in a result file)."""
    return {"name": os.path.basename(path), "sha256": sha256_file(path)}


def git_hash() -> str:
    """The source's commit (with '+dirty' when the tree has changes); outside a checkout of this source (a copy
    laid out without .git, as on a borrowed GPU machine; an installed copy, even in a folder another repository
    tracks) the commit the copy was made from, given as ENVISAT_SOURCE_GIT; else 'unknown'."""
    here = os.path.dirname(os.path.abspath(__file__))
    given = os.environ.get("ENVISAT_SOURCE_GIT", "").strip() or "unknown"

    def git(*args: str) -> subprocess.CompletedProcess:
        # --no-optional-locks: `status` reads the index without refreshing it, so git writes nothing in the
        # checkout (a job under `ulimit -f` killed git mid-write, leaving an index.lock that blocks every git
        # command there; a user's own git command beside a job would meet the lock too)
        return subprocess.run(["git", "--no-optional-locks", *args], cwd=here, capture_output=True, text=True,
                              timeout=10)

    try:
        if git("ls-files", "--error-unmatch", os.path.basename(__file__)).returncode != 0:
            return given  # not a checkout, or another project's (a venv inside a user's repository)
        head = git("rev-parse", "HEAD")
        if head.returncode != 0:
            return given
        dirty = git("status", "--porcelain", "--untracked-files=no")
        return head.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return given


def source_line() -> str:
    """The comment a job's written config carries under its first line: the package's version and the source's
    commit (git_hash), what a rerun months later needs beside the config's values to make the same outputs."""
    from importlib import metadata

    try:
        version = metadata.version("envisat-pose")
    except metadata.PackageNotFoundError:
        version = "not installed"
    return f"# source: envisat-pose {version}, commit {git_hash()}\n"
