"""SIGTERM stops every verb as Ctrl-C does (app/interrupts.py): the same one line, exit 143, staged outputs
removed and a resumable job's units kept; it ended verbs other than train without a word (exit -15). A pool's
workers are not waited for, and SIGTERM to the whole process group (a service manager's stop) prints no
traceback from them or from the pool."""

import json
import os
import signal
import subprocess
import sys
import threading
import time

os.environ.setdefault("MUJOCO_GL", "osmesa")

import pytest

CLI = [sys.executable, "-m", "envisat_pose.app.cli"]


def wait_for(path, proc, timeout=60.0):
    """Until path exists (the job has started writing there) or the process ended."""
    deadline = time.monotonic() + timeout
    while not os.path.exists(path) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)


def test_sigterm_stops_a_verb_with_its_ctrl_c_line_and_leaves_no_half_written_file(tmp_path):
    out = tmp_path / "truth"
    out.mkdir()
    proc = subprocess.Popen(CLI + ["simulate", "--duration-s", "200000", "--plot", "--quiet", "--out",
                                   str(out / "run.npz")], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_for(out / ".run.npz.envisat.lock", proc)
        time.sleep(1.0)  # simulating
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGTERM)
        stdout, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 143, err
    assert err == "envisat simulate: interrupted\n" and stdout == ""
    assert os.listdir(out) == []  # no run.npz, staging folder, partial file or lock file


def test_sigterm_is_restored_after_an_in_process_main(monkeypatch):
    import envisat_pose.app.simulate as simulate
    from envisat_pose.app.cli import main

    seen = []
    monkeypatch.setattr(simulate, "run_simulate_cli", lambda args: seen.append(signal.getsignal(signal.SIGTERM)))
    before = signal.getsignal(signal.SIGTERM)
    assert main(["simulate", "--out", "x.npz"]) == 0
    assert seen[0] is not before and signal.getsignal(signal.SIGTERM) is before


def test_a_sigterm_that_came_in_ignored_stays_ignored(monkeypatch):
    """A job started with SIGTERM ignored (a supervisor's choice, as a shell's `&` leaves SIGINT ignored, which
    Python keeps) is not stopped by it: the verb leaves the disposition as it found it."""
    import envisat_pose.app.simulate as simulate
    from envisat_pose.app.cli import main

    seen = []
    monkeypatch.setattr(simulate, "run_simulate_cli", lambda args: seen.append(signal.getsignal(signal.SIGTERM)))
    before = signal.signal(signal.SIGTERM, signal.SIG_IGN)
    try:
        assert main(["simulate", "--out", "x.npz"]) == 0
        assert seen == [signal.SIG_IGN] and signal.getsignal(signal.SIGTERM) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGTERM, before)


def test_an_interrupted_pool_does_not_wait_for_its_units_in_progress():
    """Ctrl-C or SIGTERM while a process pool runs: the workers are ended at once (their units, partial files,
    are redone on a resume); the pool waited for every unit in progress (and the queued ones it had sent)."""
    from envisat_pose.pools import RunnerConfig, run_tasks

    tasks = run_tasks(time.sleep, [(0.1,), (30.0,), (30.0,)], RunnerConfig("local", 2))
    start = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        try:
            for _ in tasks:
                raise KeyboardInterrupt  # at the first unit done, as a signal would
        finally:
            tasks.close()  # as the job's frame going away would
    assert time.monotonic() - start < 15.0


def running_in_group(pgid: int) -> list[int]:
    """The processes of group pgid still running (zombies apart: a container without an init reaps none)."""
    found = []
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            with open(f"/proc/{pid}/stat") as fh:
                fields = fh.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            found.append(int(pid))
    return found


def recorded_shard(out, proc, timeout=60.0):
    """Until the dataset's manifest records a finished shard (a resumable unit kept for the rerun) or the
    process ended (the manifest is written atomically)."""
    deadline = time.monotonic() + timeout
    while proc.poll() is None and time.monotonic() < deadline:
        try:
            with open(out / "manifest.json") as fh:
                if json.load(fh).get("shards"):
                    return
        except (OSError, ValueError):
            pass
        time.sleep(0.05)


@pytest.mark.slow
@pytest.mark.parametrize("group", [False, True], ids=["to-envisat", "to-its-group"])
def test_sigterm_stops_a_generate_with_workers_quietly_and_a_rerun_finishes_it(tmp_path, group):
    """generate with 2 worker processes: SIGTERM to envisat (`kill PID`) or to its whole group (a service
    manager): the resumable job's line, exit 143, no traceback (Python 3.11's pool thread raised InvalidStateError
    when the workers died too), no worker left; the same command finishes the dataset."""
    out = tmp_path / "data"
    cmd = CLI + ["generate", "--num-images", "200", "--shard-size", "2", "--resolution", "48", "--workers", "2",
                 "--quiet", "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        recorded_shard(out, proc, timeout=120)  # a shard file alone may not be recorded yet: then it is redone
        assert proc.poll() is None, proc.communicate()
        (os.killpg if group else os.kill)(proc.pid, signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        os.killpg(proc.pid, signal.SIGKILL) if proc.poll() is None else None
    assert proc.returncode == 143, err
    assert err == ("envisat generate: interrupted; run the same command again to finish it (what is written is "
                   "kept)\n")
    time.sleep(0.5)
    assert running_in_group(proc.pid) == []  # no worker left
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0 and "images already there" in done.stdout, done.stderr


def partial_shards(out) -> list[str]:
    return [n for n in os.listdir(out) if n.startswith(".tmp-") and "shard-" in n] if os.path.isdir(out) else []


@pytest.mark.parametrize("backend", ["local", pytest.param("dask", marks=pytest.mark.slow)])  # dask: 14 s
def test_ctrl_c_to_a_generate_with_workers_leaves_no_partial_shard(tmp_path, backend):
    """Ctrl-C (SIGINT to the terminal's process group) while 2 worker processes (a pool's, a LocalCluster's) write
    their shards: the job's line, exit 130, and no partial shard left (the stopped workers' temporary files stayed
    until a rerun)."""
    out = tmp_path / "data"
    cmd = CLI + ["generate", "--num-images", "400", "--shard-size", "200", "--resolution", "128", "--workers", "2",
                 "--backend", backend, "--quiet", "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # as a terminal's job
    try:
        deadline = time.monotonic() + 120
        while len(partial_shards(out)) < 2 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)  # until both workers are writing (a shard of 200 images takes them many seconds)
        assert proc.poll() is None and partial_shards(out), proc.communicate()
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=90)
    finally:
        os.killpg(proc.pid, signal.SIGKILL) if proc.poll() is None else None
    assert proc.returncode == 130, err
    assert err == ("envisat generate: interrupted; run the same command again to finish it (what is written is "
                   "kept)\n")
    assert sorted(os.listdir(out)) == ["generate.config.toml", "manifest.json"]


@pytest.mark.parametrize("name,code", [("SIGINT", 130), ("SIGTERM", 143)])
def test_train_stopped_by_a_signal_exits_as_every_verb(name, code, tmp_path, monkeypatch, capsys):
    """train stops itself after its step with a checkpoint on SIGINT or SIGTERM (perception's StopOnSignals); it
    exited 130 for both, now 143 after SIGTERM as every other verb."""
    import envisat_pose.app.train as app_train
    from envisat_pose.app.cli import main
    from envisat_pose.perception.train_run import TrainingInterrupted

    def stopped(*args, **kwargs):
        raise TrainingInterrupted(3, str(tmp_path / "run"), name)

    monkeypatch.setattr(app_train, "train_detector", stopped)
    assert main(["train", "--data", str(tmp_path), "--out", str(tmp_path / "run"), "--quiet"]) == code
    err = capsys.readouterr().err
    assert err.startswith(f"envisat train: {name} at step 3: checkpoint written") and "go on with" in err, err


@pytest.mark.slow
@pytest.mark.parametrize("name,code", [("SIGINT", 130), ("SIGTERM", 143)])
def test_ctrl_c_to_a_dask_generate_prints_its_one_line(name, code, tmp_path):
    """generate on a LocalCluster of 2 workers, Ctrl-C (SIGINT to the terminal's whole process group) or a service
    manager's SIGTERM to the group: the resumable job's line alone, no worker left. With Ctrl-C each worker
    printed a KeyboardInterrupt traceback, then a worker's 'Async instruction ... CancelledError' warning and the
    nanny's 'Worker process still alive after 4.0 seconds, killing' came after or before the line."""
    out = tmp_path / "data"
    cmd = CLI + ["generate", "--num-images", "400", "--shard-size", "2", "--resolution", "96", "--workers", "2",
                 "--backend", "dask", "--quiet", "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # as a terminal's job
    try:
        recorded_shard(out, proc, timeout=120)  # the cluster is up and its workers are rendering
        assert proc.poll() is None, proc.communicate()
        os.killpg(proc.pid, getattr(signal, name))
        _, err = proc.communicate(timeout=90)
    finally:
        os.killpg(proc.pid, signal.SIGKILL) if proc.poll() is None else None
    assert proc.returncode == code, err
    assert err == ("envisat generate: interrupted; run the same command again to finish it (what is written is "
                   "kept)\n")
    time.sleep(0.5)
    assert running_in_group(proc.pid) == []


def test_a_local_clusters_workers_start_with_ctrl_c_left_to_the_job():
    """Processes started while a LocalCluster starts its workers inherit SIGINT blocked (Python never unblocks
    it: a Ctrl-C to the group stays pending in them, no KeyboardInterrupt); the caller's own handler and mask come
    back after, and off the main thread nothing changes (signals are the main thread's)."""
    from envisat_pose.pools import ctrl_c_left_to_this_process

    probe = [sys.executable, "-c", "import signal; print(signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, "
                                   "[]), signal.getsignal(signal.SIGINT) is signal.default_int_handler)"]
    outer = signal.signal(signal.SIGINT, signal.default_int_handler)  # as a terminal's job has it (a shell's `&`
    try:  # starts its jobs with SIGINT ignored: then every child would inherit that anyway)
        with ctrl_c_left_to_this_process():
            inside = subprocess.run(probe, capture_output=True, text=True, check=True).stdout.split()
        assert inside == ["True", "True"]
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, [])
        assert subprocess.run(probe, capture_output=True, text=True, check=True).stdout.split() == ["False", "True"]
        seen = []

        def off_main():
            with ctrl_c_left_to_this_process():
                seen.append(signal.getsignal(signal.SIGINT))

        t = threading.Thread(target=off_main)
        t.start()
        t.join()
        assert seen == [signal.default_int_handler]
    finally:
        signal.signal(signal.SIGINT, outer)


@pytest.mark.parametrize("name,to", [("SIGINT", "process"), ("SIGINT", "thread"), ("SIGTERM", "process")])
def test_a_stop_while_the_cluster_starts_is_held_then_stops_the_job(name, to):
    """A Ctrl-C or SIGTERM in the seconds a LocalCluster starts (to the process: any of its threads may take it; or
    to the main thread alone) is not lost: nothing is raised inside, the job's own handler runs as the block ends.
    Ignoring SIGINT there (as before) dropped it: the job ran on, and a second Ctrl-C was needed; a SIGTERM raised
    inside LocalCluster's start left a half-started cluster whose close at exit printed Dask's traceback."""
    from envisat_pose.app.interrupts import Terminated, sigterm_as_interrupt
    from envisat_pose.pools import ctrl_c_left_to_this_process

    sig = getattr(signal, name)
    outer = signal.signal(signal.SIGINT, signal.default_int_handler)
    reached = []
    try:
        with sigterm_as_interrupt(), pytest.raises(KeyboardInterrupt if name == "SIGINT" else Terminated):
            with ctrl_c_left_to_this_process():
                if to == "process":
                    os.kill(os.getpid(), sig)
                else:
                    signal.pthread_kill(threading.main_thread().ident, sig)
                time.sleep(0.2)  # Python runs a caught signal's handler between bytecodes: several chances here
                reached.append(True)
        assert reached == [True]
        with ctrl_c_left_to_this_process():  # no signal: nothing raised, nothing left pending
            time.sleep(0.05)
        assert signal.SIGINT not in signal.sigpending()
    finally:
        signal.signal(signal.SIGINT, outer)


def test_an_interrupted_clusters_close_leaves_out_the_nannys_kill_warning_alone():
    """While an interrupted job closes its cluster, the nanny's 'still alive after' warning is left out and its
    other records kept; a job that was not interrupted, and what comes after the close, keep every record."""
    import logging

    from envisat_pose.pools import _closing_quietly

    log = logging.getLogger("distributed.nanny")
    kept = []

    class Keep(logging.Handler):
        def emit(self, record):
            kept.append(record.getMessage())

    handler = Keep()
    log.addHandler(handler)
    try:
        for interrupted in (True, False):
            with _closing_quietly(interrupted):
                log.warning("Worker process still alive after 4.0 seconds, killing")
                log.warning("Restarting worker")
        log.warning("Worker process still alive after 4.0 seconds, killing")
    finally:
        log.removeHandler(handler)
    assert kept == ["Restarting worker", "Worker process still alive after 4.0 seconds, killing",
                    "Restarting worker", "Worker process still alive after 4.0 seconds, killing"]


def test_a_restart_the_nanny_reports_is_held_until_the_next_result_and_dropped_for_an_interrupted_job():
    """The nanny's 'Restarting worker' of a job's own cluster: a Ctrl-C or SIGTERM to the group ends the workers
    too, and the nanny (this process) could see one gone before this process's handler ran: under load that warning
    came before the job's one line (the slow test above, on a machine with two benchmarks beside it). So did, under
    load, what an interrupted result leaves: tornado's error from distributed's sync() cancelling its wait (a
    NameError in its `cancel` callback), the scheduler's and the client's "Couldn't gather", and the scheduler's
    "Batched Comm Closed" to a worker the signal ended (with its traceback: CI's slow lane, SIGTERM). Held while the job
    runs, each is said at release (the next result, or the job's end), and never for an interrupted job; every
    other record passes at once."""
    import functools
    import logging

    from envisat_pose.pools import _HeldRecords

    def sync():
        def cancel():
            pass
        return cancel

    names = ("distributed.nanny", "tornado.application", "distributed.scheduler", "distributed.client",
             "distributed.batched")
    logs, kept = [logging.getLogger(n) for n in names], []

    class Keep(logging.Handler):
        def emit(self, record):
            kept.append((record.name, record.getMessage()))

    def noise():
        logs[0].warning("Restarting worker (status=Status.running)")
        logs[1].error("Exception in callback %r", functools.partial(sync()))
        logs[2].error("Couldn't gather keys: {'_dask_task-ff44': 'forgotten'}")
        logs[3].warning("Couldn't gather 1 keys, rescheduling ('_dask_task-ff44',)")
        try:
            raise OSError("stream closed")  # distributed's CommClosedError is an OSError
        except OSError:
            logs[4].info("Batched Comm Closed <TCP (closed)  local=tcp://127.0.0.1:1 remote=tcp://127.0.0.1:2>",
                         exc_info=True)

    handler, held = Keep(), _HeldRecords()
    levels = [log.level for log in logs]
    for log in logs:
        log.addHandler(handler)
        log.setLevel(logging.INFO)  # as distributed's own logging config sets its loggers
    held.attach()
    try:
        noise()
        logs[0].warning("Worker process still alive after 4.0 seconds, killing")
        logs[1].error("Exception in callback %r", print)  # another callback's error: said at once
        assert kept == [("distributed.nanny", "Worker process still alive after 4.0 seconds, killing"),
                        ("tornado.application", f"Exception in callback {print!r}")]
        held.release()  # the next result: said, once each
        held.release()
        assert [k[0] for k in kept[2:]] == list(names)
        assert "sync.<locals>.cancel" in kept[3][1]
        noise()  # then the job is interrupted: never released
    finally:
        held.detach()
        for log, level in zip(logs, levels):
            log.removeHandler(handler)
            log.setLevel(level)
    assert len(kept) == 7

