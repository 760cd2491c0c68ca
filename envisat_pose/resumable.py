"""Resumable jobs (`ResumableJob`): the one protocol for outputs written unit by unit into a folder (the image
factory's shards, a Monte Carlo campaign's blocks), run as tasks of the pools (envisat_pose/pools.py): units
with sha256 in manifest.json, rewritten atomically after each unit (or a few, where a rewrite costs much); a
folder of another config refused; unvouched unit files and partial files removed and redone, a file named as a unit
but beyond the job's units refused. The manifest's file
name and its one reader (`read_manifest`) are here; a generated dataset's manifest is checked on top of it by envisat_pose/shard_reader.py
(`load_dataset_manifest`).
"""

from __future__ import annotations

import contextlib
import glob
import json
import os
import time
from dataclasses import dataclass, field
from typing import Callable

from envisat_pose.config import InputError, flatten
from envisat_pose.io import atomic_write_text, partial_owner_alive, sha256_file
from envisat_pose.out_dirs import PARTIAL_PREFIX, make_out_dir
from envisat_pose.out_lock import is_lock_file
from envisat_pose.pools import RunnerConfig, run_tasks

MANIFEST = "manifest.json"
# A finished unit's manifest rewrite waits while the time since the last rewrite is under this many times what that
# rewrite took: a manifest of a few hundred units (ms to write) is rewritten after every unit, one of 100 000 (17 MB,
# ~1 s) every ~20 s, so rewriting it costs at most ~1/20 of the job's time instead of growing with the square of
# its units (a job of 100 000 one-image shards spent hours writing its manifest). A kill loses at most the units
# of that wait (redone on the resume); an error, Ctrl-C or SIGTERM and the job's end write every one.
MANIFEST_REWRITE_WAIT = 20.0


def manifest_path(folder: str) -> str:
    """The path of folder's manifest (what to hash or test for; read it with read_manifest)."""
    return os.path.join(folder, MANIFEST)


def read_manifest(folder: str, field: str) -> dict | None:
    """The JSON object in folder's manifest.json (None: the folder has none): the one place a manifest is opened
    for reading. InputError naming the field, the folder and the file when it is unreadable or not an object."""
    path = manifest_path(folder)
    if not os.path.isfile(path):
        return None
    try:
        with open(path, encoding="utf-8") as fh:
            manifest = json.load(fh)
    except (OSError, ValueError) as err:
        raise InputError(f"{field} {folder!r}: unreadable {MANIFEST} ({err})") from None
    if not isinstance(manifest, dict):
        raise InputError(f"{field} {folder!r}: {MANIFEST} holds a JSON {type(manifest).__name__}, not an object")
    return manifest


def remove_partial_files(folder: str) -> None:
    """Remove the temporary files (and io.staged_folder's folders) a killed writer left in folder; a running
    process's stay (a second run of the job on the same folder must not pull the first's files from under it)."""
    import shutil

    for name in os.listdir(folder):
        if name.startswith(PARTIAL_PREFIX) and not partial_owner_alive(name):
            path = os.path.join(folder, name)
            shutil.rmtree(path) if os.path.isdir(path) else os.remove(path)


@dataclass
class ResumableJob:
    """A job whose output is `n_units` files in one folder, each written atomically by one task (a shard, a
    block of Monte Carlo runs) and vouched for by the folder's manifest.json, rewritten atomically after every
    unit, so a killed job resumes where it stopped with the same bytes.

    The protocol: a folder holds one job (`identity`: the full config, the root seed); a rerun with another is
    refused before anything is written. A rerun keeps a unit the manifest lists only when its file still has the
    recorded sha256 (and passes `verify_unit`); every other unit file, and every partial file of a killed
    writer, is removed and redone. A file named as a unit (`unit_glob`) that is none of the job's units (a shard
    beyond the dataset's last, copied in) is not the job's to remove: the run is refused naming it.

    format: the manifest's format string. what: the job's output in messages ('dataset', 'campaign').
    units_key: the manifest's list of unit entries ('shards', 'blocks'). unit_file(i): unit i's path relative
    to out_dir. header: further manifest fields (counts, a prerequisite's sha256). verify_unit(entry, path):
    checks beyond the sha256. A unit's entry (its task's result) holds at least 'index' and 'sha256'.
    added_defaults: identity fields (flattened, 'config.x') added to the job after folders were written without
    them, each with the value such a folder had implicitly (a field's default that reproduces the older bytes).
    own_entries: what the job may have written into its folder before the first manifest (its unit subfolders
    are among them, empty: no unit is written before it); a folder without a manifest that holds anything else
    is not this job's and is refused.
    compared_by: identity fields (flattened) compared by a header field instead ({'config.target':
    'target.sha256'}: a target file given by another path, from another folder, is the same file), where the
    earlier manifest records that header field. unit_glob: the glob of a unit file's path relative to out_dir
    ('shard-*.tar'; None: not checked), whose matches must all be units of the job (a reader that globs the folder
    would take a stray one in).
    """

    out_dir: str
    format: str
    what: str
    identity: dict
    units_key: str
    n_units: int
    unit_file: Callable[[int], str]
    header: dict = field(default_factory=dict)
    verify_unit: Callable[[dict, str], bool] | None = None
    added_defaults: dict = field(default_factory=dict)
    own_entries: tuple = ()
    compared_by: dict = field(default_factory=dict)
    unit_glob: str | None = None
    clock: Callable[[], float] = time.monotonic
    done: dict[int, dict] = field(default_factory=dict, init=False)
    _unwritten: int = field(default=0, init=False)  # units recorded since the manifest's last rewrite
    _next_write: float = field(default=float("-inf"), init=False)  # the clock's time of the next rewrite

    def unit_path(self, index: int) -> str:
        return os.path.join(self.out_dir, self.unit_file(index))

    def previous(self) -> dict | None:
        """The manifest of an earlier run in out_dir (None: none yet). InputError when it is unreadable, of
        another kind of job, or of another identity (the message names the first differences)."""
        try:
            manifest = read_manifest(self.out_dir, "out_dir")
        except InputError as err:
            raise InputError(f"{err}; remove it or use another folder") from None
        if manifest is None:
            self._refuse_foreign_entries()
            return None
        if manifest.get("format") != self.format:
            raise InputError(f"out_dir {self.out_dir!r}: {MANIFEST} is not a {self.what} manifest (format "
                             f"{self.format!r} expected); use another folder")
        units = manifest.get(self.units_key, [])
        if not isinstance(units, list) or not all(isinstance(e, dict) for e in units):
            raise InputError(f"out_dir {self.out_dir!r}: {MANIFEST}'s {self.units_key!r} is not a list of entries; "
                             "remove it or use another folder")
        theirs = {**self.added_defaults, **flatten({k: manifest.get(k) for k in self.identity})}
        ours = flatten(self.identity)
        recorded = flatten({k: manifest.get(k) for k in self.header})
        as_given = {}  # a field compared by its record: its text there and here, to name the file in a refusal
        for k, by in self.compared_by.items():  # a path's text stands for its file: compared by its record
            if recorded.get(by) is not None:
                as_given[k] = (theirs.get(k), ours.get(k))
                theirs[k], ours[k] = recorded[by], flatten(self.header).get(by)
        # a compared file first: another target scales fields of its own (a range, a margin) that sort before it
        diff = sorted((k for k in set(theirs) | set(ours) if theirs.get(k) != ours.get(k)),
                      key=lambda k: (k not in as_given, k))
        if diff:
            def shown(k: str) -> str:
                if k in as_given:
                    (there, here), by = as_given[k], self.compared_by[k].replace("_", ".").rsplit(".", 1)[-1]
                    return (f"{k.removeprefix('config.')} = {there!r} ({by} {str(theirs.get(k))[:12]}) there, "
                            f"{here!r} ({by} {str(ours.get(k))[:12]}) here")
                return f"{k.removeprefix('config.')} = {theirs.get(k)!r} there, {ours.get(k)!r} here"

            raise InputError(f"out_dir {self.out_dir!r} holds a {self.what} of another config or seed ("
                             + ", ".join(shown(k) for k in diff[:3]) + (", ..." if len(diff) > 3 else "")
                             + "); rerun with the same settings or use another folder")
        self._refuse_stray_units()
        return manifest

    def _refuse_foreign_entries(self) -> None:
        """InputError in one line when out_dir holds entries but no manifest beyond the job's own (own_entries, its
        unit subfolders, empty: the job writes no unit before its first manifest), a killed writer's partial files
        and a lock file (out_lock): another job's folder, whose files this job would mix in with its own or
        overwrite (a unit file there was written by none of this job's runs: removing it would lose it)."""
        own = set(self.own_entries) | set(self.subdirs())
        names = sorted(n for n in os.listdir(self.out_dir) if not n.startswith(PARTIAL_PREFIX) and n not in own
                       and not is_lock_file(n))
        for sub in self.subdirs():  # a unit subfolder's entries: files this job never wrote (blocks/ of a copy)
            if os.path.isdir(os.path.join(self.out_dir, sub)):
                names += sorted(os.path.join(sub, n) for n in os.listdir(os.path.join(self.out_dir, sub))
                                if not n.startswith(PARTIAL_PREFIX))
        if names:
            shown = ", ".join(names[:3]) + (", ..." if len(names) > 3 else "")
            count = "1 entry" if len(names) == 1 else f"{len(names)} entries"
            raise InputError(f"out_dir {self.out_dir!r} holds {count} ({shown}) and no {MANIFEST}: not a "
                             f"{self.what} to resume; expected an empty or new folder (use another one)")

    def _refuse_stray_units(self) -> None:
        """InputError in one line when out_dir holds files matching unit_glob that are none of the job's units,
        or a folder (or a link to none) where a unit's file goes: not the job's to remove or to read."""
        if self.unit_glob is None:
            return
        ours = {os.path.normpath(self.unit_file(i)) for i in range(self.n_units)}
        found = sorted(os.path.relpath(p, self.out_dir) for p in glob.glob(os.path.join(glob.escape(self.out_dir),
                                                                                         self.unit_glob)))
        unit = self.units_key.removesuffix("s")
        odd = [name for name in found if name in ours and not os.path.isfile(os.path.join(self.out_dir, name))]
        if odd:
            kind = "a folder" if os.path.isdir(os.path.join(self.out_dir, odd[0])) else "a link to no file"
            raise InputError(f"out_dir {self.out_dir!r} holds {odd[0]} as {kind}, where the {self.what}'s {unit} "
                             f"file goes (expected a file it wrote, or nothing); move it out or use another folder")
        strays = [name for name in found if name not in ours]
        if strays:
            shown = ", ".join(strays[:3]) + (", ..." if len(strays) > 3 else "")
            first, last = self.unit_file(0), self.unit_file(self.n_units - 1)
            expected = first if self.n_units == 1 else f"{first} to {last}"
            raise InputError(f"out_dir {self.out_dir!r} holds {shown}: named like the {self.what}'s {self.units_key} "
                             f"but none of its {self.n_units} (expected {expected}; copied in, or another "
                             f"{self.what}'s, which a glob of {self.unit_glob!r} would take in); move it out or use "
                             "another folder")

    def open(self) -> dict | None:
        """Refuse another job's folder, then create the folder (and the units' subfolders), prove it writable
        and remove partial files. Returns the earlier run's manifest (None: none)."""
        previous = self.previous() if os.path.isdir(self.out_dir) else None
        make_out_dir(self.out_dir, self.subdirs())
        for folder in self.folders():
            remove_partial_files(folder)
        return previous

    def subdirs(self) -> list[str]:
        """The units' subfolders of out_dir (relative; none where every unit is in out_dir itself)."""
        return sorted({os.path.dirname(self.unit_file(i)) for i in range(self.n_units)} - {""})

    def folders(self) -> list[str]:
        """out_dir and the units' subfolders: where the units' partial files are."""
        return [self.out_dir, *(os.path.join(self.out_dir, s) for s in self.subdirs())]

    def resume(self, previous: dict | None) -> dict[int, dict]:
        """Keep the units `previous` vouches for, remove every other unit file, write the manifest. Pass None
        to redo every unit (a prerequisite changed). Returns {index: entry} of the kept units."""
        self.done = {}
        for entry in (previous or {}).get(self.units_key, []):
            i = entry.get("index")
            if not (isinstance(i, int) and 0 <= i < self.n_units):
                continue
            path = self.unit_path(i)
            if (os.path.isfile(path) and sha256_file(path) == entry.get("sha256")
                    and (self.verify_unit is None or self.verify_unit(entry, path))):
                self.done[i] = entry
        for i in range(self.n_units):  # a unit file the manifest does not vouch for is redone
            if i not in self.done and os.path.exists(self.unit_path(i)):
                os.remove(self.unit_path(i))
        self.write()
        return dict(self.done)

    def manifest(self) -> dict:
        return {"format": self.format, **self.identity, **self.header,
                self.units_key: [self.done[i] for i in sorted(self.done)],
                "complete": len(self.done) == self.n_units}

    def write(self) -> None:
        """Rewrite manifest.json atomically (key-sorted, indented) with every unit recorded."""
        start = self.clock()
        atomic_write_text(os.path.join(self.out_dir, MANIFEST),
                          json.dumps(self.manifest(), sort_keys=True, indent=1) + "\n")
        end = self.clock()
        self._unwritten, self._next_write = 0, end + MANIFEST_REWRITE_WAIT * (end - start)

    def record(self, entry: dict) -> None:
        """A finished unit: add its entry and rewrite the manifest, unless the last rewrite was too recent for
        what it cost (MANIFEST_REWRITE_WAIT; `flush` writes what waits)."""
        self.done[int(entry["index"])] = entry
        self._unwritten += 1
        if self.clock() >= self._next_write:
            self.write()

    def flush(self) -> None:
        """Rewrite the manifest if units were recorded since its last rewrite."""
        if self._unwritten:
            self.write()

    def todo(self) -> list[int]:
        return [i for i in range(self.n_units) if i not in self.done]

    def run(self, fn: Callable[..., dict], args_of: Callable[[int], tuple], cfg: RunnerConfig,
            on_unit: Callable[[dict], None] | None = None) -> dict:
        """Run fn(*args_of(i)) for every unit not done (tasks of `run_tasks`; each returns its unit's entry),
        recording each as it finishes and then calling on_unit(entry). Returns the final manifest. A unit's error, a
        Ctrl-C or SIGTERM stops the workers, then removes the partial files they were writing (this machine's:
        another scheduler's workers may still write theirs, removed on a resume); the finished units stay."""
        tasks = run_tasks(fn, [args_of(i) for i in self.todo()], cfg)
        try:
            for _, entry in tasks:
                self.record(entry)
                if on_unit is not None:
                    on_unit(entry)
            self.flush()
        except BaseException:
            tasks.close()  # the pool's workers ended (run_tasks), their files no longer written
            with contextlib.suppress(OSError):  # the finished units vouched for (a full disk: the job's error says)
                self.flush()
            if cfg.scheduler is None:
                with contextlib.suppress(OSError):  # the job's own error is the one to say
                    for folder in self.folders():
                        remove_partial_files(folder)
            raise
        return self.manifest()
