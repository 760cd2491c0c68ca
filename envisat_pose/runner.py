"""One runner for every parallel job (design.md, Scale): a task function over a list of argument tuples, run
in this process, on a local process pool, or on a Dask cluster, with results yielded as they finish.

A task is a module-level function (importable by name in a worker) whose arguments and result are plain data:
numbers, strings, lists, dicts, numpy arrays. Each task draws its randomness from its own arguments (a seed),
never from where or when it runs, so the results are the same whatever the backend and the worker count; the
caller reassembles them by index (or writes each unit of output by its index, as the image factory does).

Local pools use spawned processes (no state inherited from the parent) that die with the parent. A Dask
cluster started here listens on 127.0.0.1 only; `scheduler` connects to an existing one instead.

Resumable jobs (`ResumableJob`): the one protocol for outputs written unit by unit into a folder (the image
factory's shards, a campaign's blocks): units with sha256 in manifest.json, rewritten atomically after each
unit; a folder of another config refused; unvouched unit files and partial files removed and redone.

In their own modules: the output-folder rule (envisat_pose/out_dirs.py) and the real-time factor
(envisat_pose/realtime.py), re-exported here for the files that still import them from the runner (other
engineers' files, being edited now).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Literal, Sequence

from envisat_pose.config import InputError, check, flatten
from envisat_pose.io import atomic_write_text, sha256_file
from envisat_pose.out_dirs import PARTIAL_PREFIX, make_out_dir

Backend = Literal["inline", "local", "dask"]


@dataclass(frozen=True)
class RunnerConfig:
    """Where tasks run. backend: 'inline' (this process), 'local' (process pool; one worker runs inline) or
    'dask'. workers: processes for 'local' and for a LocalCluster. scheduler: address of an existing Dask
    scheduler (then workers is ignored). env: environment variables set in every worker before its first task
    (e.g. LP_NUM_THREADS, the rasterizer's threads per worker)."""

    backend: Backend = "local"
    workers: int = 1
    scheduler: str | None = None
    env: dict[str, str] = field(default_factory=dict)

    def validate(self, prefix: str = "") -> None:
        p = f"{prefix}." if prefix else ""
        check(self.backend in ("inline", "local", "dask"), f"{p}backend", self.backend, "'inline', 'local' or 'dask'")
        check(self.workers >= 1, f"{p}workers", self.workers, "at least 1 worker")
        check(self.scheduler is None or self.backend == "dask", f"{p}scheduler", self.scheduler,
              "an address only with backend 'dask'")


def cpu_share(workers: int) -> int:
    """The machine's cores shared among `workers` processes (at least 1 each)."""
    return max(1, (os.cpu_count() or 1) // max(1, workers))


RASTERIZER_THREADS = ("LP_NUM_THREADS",)  # llvmpipe's threads: MuJoCo's software renderer (OSMesa, EGL on a CPU)
BLAS_THREADS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")  # numpy's and scipy's linear algebra


def thread_env(workers: int, variables: tuple[str, ...] = RASTERIZER_THREADS) -> dict[str, str]:
    """The one home of the worker thread environment: each of `variables` set to the machine's cores shared among
    `workers` processes (cpu_share), for RunnerConfig.env (a worker keeps a value its parent already set)."""
    n = str(cpu_share(workers))
    return {name: n for name in variables}


def _worker_init(env: dict[str, str]) -> None:
    """Process-pool worker start: its environment, and death with the parent (no orphan writers)."""
    for key, value in env.items():
        os.environ.setdefault(key, value)
    try:
        import ctypes
        import signal

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _dask_task(fn: Callable, env: dict[str, str], args: tuple) -> Any:
    for key, value in env.items():
        os.environ.setdefault(key, value)
    return fn(*args)


def run_tasks(fn: Callable[..., Any], tasks: Sequence[tuple], cfg: RunnerConfig = RunnerConfig()
              ) -> Iterator[tuple[int, Any]]:
    """Run fn(*tasks[i]) for every i and yield (i, result) as each one finishes (completion order).

    An exception in a task propagates to the caller, after which no more results are yielded (results
    already yielded stay valid: a resumable job has recorded them).
    """
    cfg.validate()
    if not tasks:
        return
    if cfg.backend == "inline" or (cfg.backend == "local" and (cfg.workers == 1 or len(tasks) == 1)):
        for key, value in cfg.env.items():
            os.environ.setdefault(key, value)
        for i, args in enumerate(tasks):
            yield i, fn(*args)
        return
    if cfg.backend == "local":
        yield from _run_pool(fn, tasks, cfg)
    else:
        yield from _run_dask(fn, tasks, cfg)


def _run_pool(fn: Callable, tasks: Sequence[tuple], cfg: RunnerConfig) -> Iterator[tuple[int, Any]]:
    import concurrent.futures as cf
    import multiprocessing as mp

    with cf.ProcessPoolExecutor(max_workers=min(cfg.workers, len(tasks)), mp_context=mp.get_context("spawn"),
                                initializer=_worker_init, initargs=(dict(cfg.env),)) as pool:
        futures = {pool.submit(fn, *args): i for i, args in enumerate(tasks)}
        try:
            for fut in cf.as_completed(futures):
                yield futures[fut], fut.result()
        finally:
            for fut in futures:
                fut.cancel()


def _run_dask(fn: Callable, tasks: Sequence[tuple], cfg: RunnerConfig) -> Iterator[tuple[int, Any]]:
    from dask.distributed import Client, LocalCluster, as_completed

    cluster = None
    if cfg.scheduler:
        client = Client(cfg.scheduler)
    else:
        cluster = LocalCluster(n_workers=cfg.workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                               dashboard_address=None, env=dict(cfg.env))
        client = Client(cluster)
    try:
        futures = {client.submit(_dask_task, fn, dict(cfg.env), tuple(args), pure=False): i
                   for i, args in enumerate(tasks)}
        for fut in as_completed(futures):
            yield futures[fut], fut.result()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


# ---------------------------------------------------------------------------------------------------------
# Resumable jobs: the one manifest protocol (the image factory's shards, the Monte Carlo campaign's blocks), run on
# the pools above. Its home is to be envisat_pose/resumable.py once datagen/factory.py (another engineer's file
# now) imports it from there: a re-export here would make the two modules import each other.

MANIFEST = "manifest.json"


def remove_partial_files(folder: str) -> None:
    """Remove the temporary files (and io.staged_folder's folders) a killed writer left in folder."""
    import shutil

    for name in os.listdir(folder):
        if name.startswith(PARTIAL_PREFIX):
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
    writer, is removed and redone.

    format: the manifest's format string. what: the job's output in messages ('dataset', 'campaign').
    units_key: the manifest's list of unit entries ('shards', 'blocks'). unit_file(i): unit i's path relative
    to out_dir. header: further manifest fields (counts, a prerequisite's sha256). verify_unit(entry, path):
    checks beyond the sha256. A unit's entry (its task's result) holds at least 'index' and 'sha256'.
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
    done: dict[int, dict] = field(default_factory=dict, init=False)

    def unit_path(self, index: int) -> str:
        return os.path.join(self.out_dir, self.unit_file(index))

    def previous(self) -> dict | None:
        """The manifest of an earlier run in out_dir (None: none yet). InputError when it is unreadable, of
        another kind of job, or of another identity (the message names the first differences)."""
        path = os.path.join(self.out_dir, MANIFEST)
        if not os.path.isfile(path):
            return None
        try:
            with open(path, encoding="utf-8") as fh:
                manifest = json.load(fh)
        except (OSError, ValueError) as err:
            raise InputError(f"--out {self.out_dir!r}: unreadable {MANIFEST} ({err}); remove it or use another "
                             "folder") from None
        if not isinstance(manifest, dict) or manifest.get("format") != self.format:
            raise InputError(f"--out {self.out_dir!r}: {MANIFEST} is not a {self.what} manifest (format "
                             f"{self.format!r} expected); use another folder")
        theirs = flatten({k: manifest.get(k) for k in self.identity})
        ours = flatten(self.identity)
        diff = sorted(k for k in set(theirs) | set(ours) if theirs.get(k) != ours.get(k))
        if diff:
            def shown(k: str) -> str:
                return f"{k.removeprefix('config.')} = {theirs.get(k)!r} there, {ours.get(k)!r} here"

            raise InputError(f"--out {self.out_dir!r} holds a {self.what} of another config or seed ("
                             + ", ".join(shown(k) for k in diff[:3]) + (", ..." if len(diff) > 3 else "")
                             + "); rerun with the same settings or use another folder")
        return manifest

    def open(self) -> dict | None:
        """Refuse another job's folder, then create the folder (and the units' subfolders), prove it writable
        and remove partial files. Returns the earlier run's manifest (None: none)."""
        previous = self.previous() if os.path.isdir(self.out_dir) else None
        subdirs = sorted({os.path.dirname(self.unit_file(i)) for i in range(self.n_units)} - {""})
        make_out_dir(self.out_dir, subdirs)
        for folder in [self.out_dir, *(os.path.join(self.out_dir, s) for s in subdirs)]:
            remove_partial_files(folder)
        return previous

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
        """Rewrite manifest.json atomically (key-sorted, indented)."""
        atomic_write_text(os.path.join(self.out_dir, MANIFEST),
                          json.dumps(self.manifest(), sort_keys=True, indent=1) + "\n")

    def record(self, entry: dict) -> None:
        """A finished unit: add its entry and rewrite the manifest."""
        self.done[int(entry["index"])] = entry
        self.write()

    def todo(self) -> list[int]:
        return [i for i in range(self.n_units) if i not in self.done]

    def run(self, fn: Callable[..., dict], args_of: Callable[[int], tuple], cfg: RunnerConfig,
            on_unit: Callable[[dict], None] | None = None) -> dict:
        """Run fn(*args_of(i)) for every unit not done (tasks of `run_tasks`; each returns its unit's entry),
        recording each as it finishes and then calling on_unit(entry). Returns the final manifest."""
        todo = self.todo()
        for _, entry in run_tasks(fn, [args_of(i) for i in todo], cfg):
            self.record(entry)
            if on_unit is not None:
                on_unit(entry)
        return self.manifest()


# the output-folder rule and the real-time factor live in their own modules; re-exported for the modules still
# importing them from here (datagen/factory.py, pipelines/export.py, pipelines/adapt.py, app/dataset.py,
# app/simulate.py: other engineers' files now)
from envisat_pose.out_dirs import check_out_dir, check_out_file, make_out_file_dir, make_out_file_dirs  # noqa: E402, F401, I001
from envisat_pose.realtime import real_time_factor  # noqa: E402, F401
