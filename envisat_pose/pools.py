"""One runner for every parallel job (design.md, Scale): a task function over a list of argument tuples, run
in this process, on a local process pool, or on a Dask cluster, with results yielded as they finish
(`run_tasks(fn, tasks, RunnerConfig)`); `thread_env` the workers' thread shares; `usable_cores`,
`usable_memory_bytes` and `default_processes` what a default pool may take of this machine, `warn_oversubscribed`
the one warning where a count given takes more.

A task is a module-level function (importable by name in a worker) whose arguments and result are plain data:
numbers, strings, lists, dicts, numpy arrays. Each task draws its randomness from its own arguments (a seed),
never from where or when it runs, so the results are the same whatever the backend and the worker count; the
caller reassembles them by index (or writes each unit of output by its index, as the image factory does).

Local pools use spawned processes (no state inherited from the parent) that die with the parent. A Dask
cluster started here listens on 127.0.0.1 only; `scheduler` connects to an existing one instead.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import types
import warnings
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator, Literal, Sequence

from envisat_pose.config import Config, InputError, check
from envisat_pose.config_errors import TargetFileWarning

Backend = Literal["inline", "local", "dask"]


@dataclass(frozen=True)
class RunnerConfig(Config):
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
        if self.scheduler is not None:
            check_scheduler(self.scheduler, f"{p}scheduler")


def check_scheduler(address: str, field: str = "scheduler") -> None:
    """ConfigError in one line unless `address` is a Dask scheduler's tcp://HOST:PORT (or HOST:PORT) that accepts a
    connection within 5 s: before a job makes its folder, not after it (a 30-s timeout and a traceback)."""
    import socket
    import urllib.parse

    parsed = urllib.parse.urlsplit(address if "://" in address else f"tcp://{address}")
    try:
        host, port = parsed.hostname, parsed.port
    except ValueError:
        host, port = None, None
    check(parsed.scheme == "tcp" and bool(host) and port is not None, field, address,
          "a Dask scheduler's address tcp://HOST:PORT")
    try:
        socket.create_connection((host, port), timeout=5.0).close()
    except OSError as err:
        check(False, field, address, f"a Dask scheduler that accepts a connection ({err.strerror or err})")


@contextlib.contextmanager
def without_main_script(fn: Callable | None = None):
    """While worker processes start: `__main__` seen as a module without a file, so spawned workers do not run
    the calling script again (multiprocessing's spawn re-imports a script's top level in every child: a plain
    script that calls a job without `if __name__ == "__main__":` would start the job again in each, and fail).
    The workers need nothing of the script where the task fn is a function of this package; a task the script
    defines itself (a bench script's, under its main guard) is found in the script by the workers, which then
    import it as spawn does (the script kept)."""
    main = sys.modules.get("__main__")
    if main is None or getattr(main, "__file__", None) is None or getattr(getattr(fn, "func", fn), "__module__", None) == "__main__":
        yield
        return
    sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        yield
    finally:
        sys.modules["__main__"] = main


CGROUP_ROOT = "/sys/fs/cgroup"  # the cgroup file system as a container sees it: its own group at the root
MEMINFO = "/proc/meminfo"


def _read_int(path: str) -> int | None:
    """The integer a one-value kernel file holds; None where it is missing, unreadable or not a number ('max')."""
    try:
        with open(path, encoding="ascii") as fh:
            return int(fh.read().split()[0])
    except (OSError, ValueError, IndexError):
        return None


def cgroup_cpu_limit() -> int | None:
    """The cores a cgroup CPU quota allows (a container's --cpus: its quota over its period, rounded up), None
    without one: cgroup v2's cpu.max ('QUOTA PERIOD'; 'max PERIOD' is none), else v1's cpu/cpu.cfs_quota_us over
    cpu/cpu.cfs_period_us (-1 is none)."""
    root = CGROUP_ROOT
    try:
        with open(os.path.join(root, "cpu.max"), encoding="ascii") as fh:
            quota_text, period_text = fh.read().split()[:2]
        quota, period = (int(quota_text) if quota_text.isdigit() else None), int(period_text)
    except (OSError, ValueError):
        quota, period = _read_int(os.path.join(root, "cpu", "cpu.cfs_quota_us")), \
            _read_int(os.path.join(root, "cpu", "cpu.cfs_period_us"))
    if quota is None or period is None or quota <= 0 or period <= 0:
        return None
    return max(1, -(-quota // period))


def torchrun_int(name: str, default: int) -> int:
    """torchrun's environment variable `name` (WORLD_SIZE, RANK, LOCAL_RANK, LOCAL_WORLD_SIZE) as a whole number,
    default where it is unset or empty; InputError in one line naming it for anything else (a launcher or a shell
    that set it wrong), never a bare int() traceback."""
    text = os.environ.get(name, "").strip()
    if not text:
        return default
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise InputError(f"environment variable {name}={text!r}: expected a whole number >= 0 (torchrun sets it; "
                         f"unset it to run in one process)")
    return value


def usable_cores() -> int:
    """The cores this process may use, the one count every default that scales with the machine starts from: the
    machine's (os.cpu_count), fewer where the CPU affinity (taskset, a container's cpuset) or a cgroup CPU quota
    (cgroup_cpu_limit) allows fewer; at least 1."""
    cores = os.cpu_count() or 1
    if hasattr(os, "sched_getaffinity"):
        cores = min(cores, len(os.sched_getaffinity(0)) or cores)
    return max(1, min(cores, cgroup_cpu_limit() or cores))


def usable_memory_bytes() -> int | None:
    """The memory this process's new workers may still take: /proc/meminfo's MemAvailable, less where a cgroup
    memory limit leaves less (v2 memory.max less memory.current, v1 memory.limit_in_bytes less
    memory.usage_in_bytes); None where neither is known."""
    found, root = [], CGROUP_ROOT
    try:
        with open(MEMINFO, encoding="ascii") as fh:
            found += [int(line.split()[1]) * 1024 for line in fh if line.startswith("MemAvailable:")]
    except (OSError, ValueError, IndexError):
        pass
    for limit, usage in (("memory.max", "memory.current"),
                         ("memory/memory.limit_in_bytes", "memory/memory.usage_in_bytes")):
        cap, used = _read_int(os.path.join(root, limit)), _read_int(os.path.join(root, usage))
        if cap is not None and used is not None and cap < 1 << 60:  # v1 writes 'no limit' as about 2^63
            found.append(max(0, cap - used))
    return min(found) if found else None


# The most processes (or torch threads) a job may start: a 512-core machine's default count was refused; torch
# refuses 2^31 threads or more (a ValueError), and 2^63 - 1 processes is a fork without end
MAX_WORKERS = 256


def default_processes(limit: int, bytes_each: int) -> int:
    """How many worker processes a job starts when none are asked for: no more than `limit` (its units of work),
    the usable cores, and the usable memory at `bytes_each` a process (its measured peak); at least 1."""
    memory = usable_memory_bytes()
    by_memory = limit if memory is None else memory // max(1, bytes_each)
    return max(1, min(limit, usable_cores(), by_memory))


def warn_oversubscribed(workers: int, field: str = "workers", bytes_each: int | None = None,
                        units: int | None = None, ranks: int = 1) -> None:
    """One warning in one line (warnings.warn; the verbs print it naming the flag) where the processes a job asked
    for start more than the usable cores, or at `bytes_each` a process (its measured peak, where known) need more
    than the usable memory: `field = value`, the cores or memory, and that the job runs. The processes that start
    are `workers`, or fewer where the job has fewer `units` of work, for each of the machine's `ranks` (torchrun's
    local ranks each start their own). Only defaults are capped: a count given runs."""
    n = (workers if units is None else min(workers, units)) * ranks
    cores, memory, over = usable_cores(), usable_memory_bytes(), []
    if n > cores:
        over.append(f"more processes than the {cores} usable core{'s' * (cores > 1)} (they share them)")
    if bytes_each and memory is not None and n * bytes_each > memory:
        over.append(f"{n} processes at ~{bytes_each / 1e9:.1f} GB each need ~{n * bytes_each / 1e9:.1f} GB, more "
                    f"than the {memory / 1e9:.1f} GB of memory available")
    if over:
        import warnings

        each = f" for each of the machine's {ranks} ranks ({n} processes)" if ranks > 1 else ""
        warnings.warn(f"{field} = {workers}{each}: {'; '.join(over)}; the job runs as asked", stacklevel=3)


def warn_runner(cfg: RunnerConfig, units: int) -> None:
    """warn_oversubscribed for the processes a runner starts on this machine for `units` tasks: none inline or on an
    existing scheduler's workers (a cluster's own machines)."""
    if cfg.backend != "inline" and cfg.scheduler is None:
        warn_oversubscribed(cfg.workers, units=units)


def cpu_share(workers: int) -> int:
    """The usable cores shared among `workers` processes (at least 1 each)."""
    return max(1, usable_cores() // max(1, workers))


RASTERIZER_THREADS = ("LP_NUM_THREADS",)  # llvmpipe's threads: MuJoCo's software renderer (OSMesa, EGL on a CPU)
BLAS_THREADS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")  # numpy's and scipy's linear algebra


def thread_env(workers: int, variables: tuple[str, ...] = RASTERIZER_THREADS, units: int | None = None
               ) -> dict[str, str]:
    """The one home of the worker thread environment: each of `variables` set to the usable cores shared among
    the processes that start, `workers` or fewer where the job has fewer `units` of work (a pool starts no more
    than its tasks), for RunnerConfig.env (a worker keeps a value its parent already set)."""
    n = str(cpu_share(workers if units is None else min(workers, units)))
    return {name: n for name in variables}


def _worker_init(env: dict[str, str]) -> None:
    """Process-pool worker start: its environment, the job's warnings of its target file left to the job (it
    said them once; config_errors.TargetFileWarning), and death with the parent (no orphan writers)."""
    for key, value in env.items():
        os.environ.setdefault(key, value)
    warnings.simplefilter("ignore", TargetFileWarning)
    try:
        import ctypes
        import signal

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _dask_task(fn: Callable, env: dict[str, str], args: tuple) -> Any:
    for key, value in env.items():
        os.environ.setdefault(key, value)
    warnings.simplefilter("ignore", TargetFileWarning)  # the job said them (_worker_init)
    return fn(*args)


def _quiet_job_workers() -> None:
    """In each worker of a job's own LocalCluster (its setup, registered with the cluster): what the job's own line
    says already left out of the worker's log, its other records kept (a worker that dies for itself, memory
    warnings). Left out: the 'Compute Failed' error, a block with the task's traceback (the task's error reaches
    the job, whose one line says it), the state machine's warning that a running task's instruction ended
    cancelled (the client closed by an interrupted job), and 'Batched Comm Closed' to a scheduler that a signal
    to the group ended first. A user's own scheduler's workers keep theirs: their logs
    are the user's."""
    import logging

    # equal filters are added once (a frozen dataclass)
    logging.getLogger("distributed.worker").addFilter(_Without("Compute Failed"))
    logging.getLogger("distributed.worker.state_machine").addFilter(_Without("CancelledError"))
    logging.getLogger("distributed.batched").addFilter(_Without("Batched Comm Closed"))  # its scheduler gone first


@dataclass(frozen=True)
class _Without:
    """A logging filter: the records whose message does not hold `phrase`."""

    phrase: str

    def filter(self, record) -> bool:
        return self.phrase not in record.getMessage()


# What a job's own LocalCluster logs in this process that the job's one line says already, held while it runs:
# the nanny's 'Restarting worker' (a Ctrl-C or SIGTERM to the terminal's group ends the workers too, and the nanny
# may see one gone before this process's own handler has run), and what an interrupted result leaves behind under
# load: distributed's sync() cancelling its wait (a NameError logged by tornado from its `cancel` callback, a
# library bug), then the scheduler's and the client's "Couldn't gather" of that result's key; and the scheduler's
# "Batched Comm Closed" (with its CommClosedError traceback) to a worker the signal ended first.
HELD = {"distributed.nanny": ("Restarting worker",),
        "tornado.application": ("sync.<locals>.cancel",),
        "distributed.scheduler": ("Couldn't gather keys",),
        "distributed.client": ("Couldn't gather",),
        "distributed.batched": ("Batched Comm Closed",)}


class _HeldRecords:
    """A logging filter for the loggers of HELD while a job's own LocalCluster runs: their records that hold one of
    the phrases held, then said (release: at the next result, or the job's end) or left out (a job interrupted: the
    job's one line says what happened). A worker that died for itself is still reported, a result later; every
    other record passes at once."""

    def __init__(self, phrases: dict[str, tuple[str, ...]] = HELD):
        self.phrases, self.held = phrases, []

    def filter(self, record) -> bool:
        if any(p in record.getMessage() for p in self.phrases.get(record.name, ())):
            self.held.append(record)
            return False
        return True

    def attach(self) -> None:
        import logging

        for name in self.phrases:
            logging.getLogger(name).addFilter(self)

    def detach(self) -> None:
        import logging

        for name in self.phrases:
            logging.getLogger(name).removeFilter(self)

    def release(self) -> None:
        """The held records handed to their loggers' handlers (their own and their parents', past this filter)."""
        import logging

        held, self.held = self.held, []
        for record in held:
            logging.getLogger(record.name).callHandlers(record)


@contextlib.contextmanager
def _closing_quietly(interrupted: bool):
    """While an interrupted job closes its LocalCluster: the nanny's warning that it killed a worker still busy
    after its 4 s (a worker in a render cannot stop sooner; the job's own line says what happened) left out."""
    import logging

    log, quiet = logging.getLogger("distributed.nanny"), _Without("still alive after")
    if interrupted:
        log.addFilter(quiet)
    try:
        yield
    finally:
        log.removeFilter(quiet)


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
        added = [key for key in cfg.env if key not in os.environ]  # the worker environment, for this job only
        for key in added:
            os.environ[key] = cfg.env[key]
        try:
            for i, args in enumerate(tasks):
                yield i, fn(*args)
        finally:
            for key in added:
                os.environ.pop(key, None)
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
        with without_main_script(fn):  # the workers start as tasks are submitted
            futures = {pool.submit(fn, *args): i for i, args in enumerate(tasks)}
        try:
            for fut in cf.as_completed(futures):
                yield futures[fut], fut.result()
        except BaseException:  # a task's error, Ctrl-C, SIGTERM, the caller gone: no unit in progress is waited for
            _stop_workers(pool)
            raise
        finally:
            for fut in futures:
                fut.cancel()


def _stop_workers(pool) -> None:
    """End a process pool's workers now (what they were writing is partial files, removed on a resume) and wait
    until the pool has marked its tasks failed: cancelling one before that broke Python 3.11's pool thread (an
    InvalidStateError traceback where SIGTERM had reached the workers too). A second Ctrl-C or SIGTERM meanwhile
    (Ctrl-C twice; `timeout` signals envisat, then its group) kills the workers and the wait goes on: an
    interrupted wait left the pool's thread marking tasks that the caller then cancelled (the same traceback, after
    the verb's line); the interrupt is raised once the pool has stopped."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    for process in processes:
        process.terminate()
    interrupt = None
    while True:
        try:
            pool.shutdown(wait=True)
            break
        except KeyboardInterrupt as again:
            interrupt = again
            for process in processes:
                process.kill()
    if interrupt is not None:
        raise interrupt


@contextlib.contextmanager
def ctrl_c_left_to_this_process():
    """While a LocalCluster starts its worker processes: SIGINT blocked on this thread and the ones it starts (the
    cluster's loop thread, which starts the workers), so the workers start with it blocked too (a signal mask
    stays across fork and exec, and Python never unblocks it): Ctrl-C reaches a terminal's whole process group,
    and each worker printed a KeyboardInterrupt traceback while this process was already stopping them (closing
    the cluster). A Ctrl-C or SIGTERM in those seconds (the cluster starting, ~1-3 s) is held, not lost: recorded
    (a thread started before may take a Ctrl-C: this process's handler then runs on the main thread), then given
    to this process's own handler once the block ends (KeyboardInterrupt, or the verb's Terminated, as the block
    exits), so the job closes a whole cluster (raised while it started, Dask's own close at exit failed with a
    traceback). SIGTERM is not blocked: a worker it reaches stops, as Dask's own close of a worker needs.
    Nothing changes off the main thread (signals are the main thread's)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()  # started inside, it unblocks SIGINT on the thread that starts it
    held = []
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    previous = {s: h for s, h in previous.items() if h is not None}  # one set outside Python is left as it is
    for s in previous:
        signal.signal(s, lambda signum, frame: held.append(signum))
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)  # a Ctrl-C pending on this thread reaches `held` now
        for s, h in previous.items():
            signal.signal(s, h)
        for s in dict.fromkeys(held):
            if callable(previous[s]):
                previous[s](s, None)  # Python's default handler: KeyboardInterrupt
            elif previous[s] == signal.SIG_DFL:
                signal.raise_signal(s)


def _run_dask(fn: Callable, tasks: Sequence[tuple], cfg: RunnerConfig) -> Iterator[tuple[int, Any]]:
    from dask.distributed import Client, LocalCluster, as_completed

    cluster = None
    if cfg.scheduler:
        client = Client(cfg.scheduler)
    else:
        try:
            with without_main_script(), ctrl_c_left_to_this_process():
                # memory_limit 0: no per-worker cap, as the local pool. Dask's "auto" (the machine's memory over
                # the workers) pauses a worker at 80 % of its share and restarts it at 95 %, while a factory
                # worker's peak (650-1175 MB) varies: 24 workers on 24 GB fit, yet a 1-GB share stalled them.
                # No dashboard, and the scheduler's own HTTP server (its health routes: it starts one whatever
                # dashboard_address says) on a free loopback port: on Dask's default 8787, any other cluster or
                # notebook holding that port made every job print "Port 8787 is already in use" warnings.
                cluster = LocalCluster(n_workers=min(cfg.workers, len(tasks)), threads_per_worker=1, processes=True,
                                       host="127.0.0.1", dashboard_address=None, env=dict(cfg.env), memory_limit=0,
                                       scheduler_kwargs={"dashboard_address": "127.0.0.1:0"})
        except BaseException:  # a Ctrl-C held while it started: the cluster closed before the job's line
            if cluster is not None:
                with _closing_quietly(True):
                    cluster.close()
            raise
        client = Client(cluster)
    interrupted, held = False, _HeldRecords()
    if cluster is not None:
        held.attach()
    try:
        if cluster is not None:
            client.register_worker_callbacks(setup=_quiet_job_workers)  # workers restarted later run it too
        futures = {client.submit(_dask_task, fn, dict(cfg.env), tuple(args), pure=False): i
                   for i, args in enumerate(tasks)}
        for fut in as_completed(futures):
            result = fut.result()
            held.release()
            yield futures[fut], result
    except BaseException:
        interrupted = True
        raise
    finally:
        if not interrupted:
            held.release()
        with _closing_quietly(interrupted):
            client.close()
            if cluster is not None:
                cluster.close()
        held.detach()
