"""The core runner: the same results whatever the backend and worker count; errors reach the caller."""

import math

import pytest

from envisat_pose.config import ConfigError
from envisat_pose.pools import RunnerConfig, run_tasks

TASKS = [(n, k) for n in range(20, 26) for k in (3, 7)]
EXPECTED = {i: math.comb(*args) for i, args in enumerate(TASKS)}


@pytest.mark.parametrize("cfg", [RunnerConfig("inline"), RunnerConfig("local", 1), RunnerConfig("local", 2),
                                 RunnerConfig("dask", 2)], ids=["inline", "local-1", "local-2", "dask-2"])
def test_every_backend_returns_every_result_once(cfg):
    got = {}
    for i, result in run_tasks(math.comb, TASKS, cfg):
        assert i not in got
        got[i] = result
    assert got == EXPECTED


def _probe() -> str | None:
    import os

    return os.environ.get("ENVISAT_RUNNER_PROBE")


def test_inline_yields_in_order_and_sets_the_worker_environment_for_the_job_only(monkeypatch):
    """The tasks see the worker environment; the caller's is as it was after the job (once the library left
    OMP_NUM_THREADS and the like set in a user's process)."""
    import os

    monkeypatch.delenv("ENVISAT_RUNNER_PROBE", raising=False)
    cfg = RunnerConfig("inline", env={"ENVISAT_RUNNER_PROBE": "1"})
    assert [i for i, _ in run_tasks(math.comb, TASKS, cfg)] == list(range(len(TASKS)))
    assert [r for _, r in run_tasks(_probe, [(), ()], cfg)] == ["1", "1"]
    assert "ENVISAT_RUNNER_PROBE" not in os.environ
    monkeypatch.setenv("ENVISAT_RUNNER_PROBE", "mine")  # a value the caller set is kept, in the tasks too
    assert [r for _, r in run_tasks(_probe, [()], cfg)] == ["mine"] and os.environ["ENVISAT_RUNNER_PROBE"] == "mine"


@pytest.mark.parametrize("cfg", [RunnerConfig("inline"), RunnerConfig("local", 2)], ids=["inline", "local-2"])
def test_a_failing_task_raises_in_the_caller(cfg):
    with pytest.raises(ValueError):
        list(run_tasks(math.comb, [(5, 2), (-1, 2), (6, 2)], cfg))


def test_bad_runner_config_names_the_field():
    with pytest.raises(ConfigError, match="workers"):
        list(run_tasks(math.comb, TASKS, RunnerConfig("local", 0)))
    with pytest.raises(ConfigError, match="scheduler"):
        list(run_tasks(math.comb, TASKS, RunnerConfig("local", 2, scheduler="tcp://127.0.0.1:1")))


# ---------------------------------------------------------------- resumable jobs

def unit_file(i: int) -> str:
    return f"units/u-{i:02d}.txt"


def write_unit(out_dir: str, i: int, fail_at: int) -> dict:
    """A job's task: unit i written atomically; unit fail_at is the moment the job is killed."""
    import os

    from envisat_pose.io import atomic_write_text, sha256_file

    if i == fail_at:
        raise KeyboardInterrupt
    path = os.path.join(out_dir, unit_file(i))
    atomic_write_text(path, f"unit {i}\n")
    return {"index": i, "sha256": sha256_file(path), "lines": 1}


def make_job(out_dir, seed=0, n=5, verify=None):
    from envisat_pose.resumable import ResumableJob

    return ResumableJob(str(out_dir), "test job v1", "test set", {"config": {"seed": seed, "n": n}}, "units", n,
                        unit_file, header={"n_units": n}, verify_unit=verify)


def run_job(out_dir, fail_at=-1, **kw):
    job = make_job(out_dir, **kw)
    job.resume(job.open())
    return job, job.run(write_unit, lambda i: (str(out_dir), i, fail_at), RunnerConfig("inline"))


def test_a_killed_job_resumes_to_the_same_manifest_redoing_only_what_is_unvouched(tmp_path):
    import json
    import os

    _, ref = run_job(tmp_path / "ref")
    assert ref["complete"] and [e["index"] for e in ref["units"]] == list(range(5)) and ref["n_units"] == 5
    d = tmp_path / "d"
    with pytest.raises(KeyboardInterrupt):
        run_job(d, fail_at=3)
    killed = json.loads((d / "manifest.json").read_text())  # rewritten after every unit
    assert not killed["complete"] and [e["index"] for e in killed["units"]] == [0, 1, 2]
    (d / unit_file(1)).write_text("damaged\n")  # its sha256 no longer matches: redone
    (d / unit_file(4)).write_text("unit 4\n")  # a file the manifest does not vouch for: removed, redone
    (d / "units" / ".tmp-partial.txt").write_text("x")  # a killed writer's partial file
    (d / ".tmp-partial.json").write_text("x")
    kept = os.stat(d / unit_file(0)).st_mtime_ns
    job = make_job(d)
    done = job.resume(job.open())
    assert sorted(done) == [0, 2]
    assert not (d / unit_file(1)).exists() and not (d / unit_file(4)).exists()
    assert not (d / "units" / ".tmp-partial.txt").exists() and not (d / ".tmp-partial.json").exists()
    assert job.todo() == [1, 3, 4]
    manifest = job.run(write_unit, lambda i: (str(d), i, -1), RunnerConfig("inline"))
    assert manifest == ref and json.loads((d / "manifest.json").read_text()) == ref
    assert os.stat(d / unit_file(0)).st_mtime_ns == kept  # a vouched unit is not redone


@pytest.mark.parametrize("write_s, most_writes", [(0.0, 41), (1.0, 2)], ids=["cheap", "costly"])
def test_a_manifest_costly_to_rewrite_waits_for_several_units_and_a_stop_still_records_every_finished_one(
        tmp_path, monkeypatch, write_s, most_writes):
    """The manifest was rewritten after every unit: a job of 100 000 one-image shards (a 17 MB manifest, ~1 s to
    write) spent hours rewriting it. A rewrite that costs much (the job's clock moves only while it writes) waits;
    a cheap one is made after every unit; the job's end and its interruption write every finished unit."""
    import json

    import envisat_pose.resumable as resumable

    now, writes = [0.0], []
    real_write = resumable.atomic_write_text

    def timed_write(path, text):
        writes.append(path)
        now[0] += write_s
        real_write(path, text)

    monkeypatch.setattr(resumable, "atomic_write_text", timed_write)
    for fail_at, out in ((-1, tmp_path / "whole"), (30, tmp_path / "stopped")):
        writes.clear()
        job = make_job(out, n=40)
        job.clock = lambda: now[0]
        job.resume(job.open())
        if fail_at < 0:
            manifest = job.run(write_unit, lambda i: (str(out), i, fail_at), RunnerConfig("inline"))
            assert manifest["complete"] and len(manifest["units"]) == 40
        else:
            with pytest.raises(KeyboardInterrupt):
                job.run(write_unit, lambda i: (str(out), i, fail_at), RunnerConfig("inline"))
        on_disk = json.loads((out / "manifest.json").read_text())
        assert [e["index"] for e in on_disk["units"]] == list(range(40 if fail_at < 0 else fail_at))
        if fail_at < 0:
            assert len(writes) == most_writes  # the resume's write, then one per unit or one at the end


def test_a_unit_that_fails_its_own_check_is_redone(tmp_path):
    run_job(tmp_path)
    job = make_job(tmp_path, verify=lambda entry, path: entry["index"] != 2)
    assert sorted(job.resume(job.open())) == [0, 1, 3, 4]


def test_another_config_is_refused_before_anything_is_written(tmp_path):
    import os

    from envisat_pose.config import InputError

    run_job(tmp_path)
    before = {f: os.stat(tmp_path / f).st_mtime_ns for f in ("manifest.json", unit_file(0))}
    # the library names its argument (out_dir); a verb's error maps it to its flag (--out)
    with pytest.raises(InputError, match=r"^out_dir '.*' holds a test set of another config or seed \(seed = 0 there, "
                                         r"7 here\)"):
        make_job(tmp_path, seed=7).open()
    assert before == {f: os.stat(tmp_path / f).st_mtime_ns for f in before}


@pytest.mark.parametrize("text, message", [("{not json", "unreadable manifest.json"),
                                           ("[1, 2]", "holds a JSON list, not an object; remove it or use another"),
                                           ('{"format": "other v1"}', "is not a test set manifest"),
                                           ('{"format": "test job v1", "units": "oops"}',
                                            "manifest.json's 'units' is not a list of entries")])
def test_a_foreign_or_broken_manifest_is_one_error(tmp_path, text, message):
    from envisat_pose.config import InputError

    (tmp_path / "manifest.json").write_text(text)
    with pytest.raises(InputError, match=message):
        make_job(tmp_path).open()


def test_the_output_folder_rule(tmp_path):
    from envisat_pose.config import InputError
    from envisat_pose.out_dirs import check_out_dir, make_out_dir

    check_out_dir(str(tmp_path / "new"))  # creates nothing
    check_out_dir(str(tmp_path / "no" / "new"))  # parents are made by make_out_dir
    assert not (tmp_path / "new").exists() and not (tmp_path / "no").exists()
    with pytest.raises(InputError, match="does not exist"):
        check_out_dir(str(tmp_path / "no" / "new"), parents=False)
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        make_out_dir(str(tmp_path / "file"))
    for under in (tmp_path / "file" / "run", tmp_path / "file" / "a" / "b"):  # under a file: one line, no traceback
        with pytest.raises(InputError, match=r"'.*file' is a file, not a folder") as err:
            make_out_dir(str(under))
        assert "\n" not in str(err.value) and str(under) in str(err.value)
    make_out_dir(str(tmp_path / "p" / "q" / "r"))
    assert (tmp_path / "p" / "q" / "r").is_dir()
    make_out_dir(str(tmp_path / "new"), ["a/b"])
    assert (tmp_path / "new" / "a" / "b").is_dir() and list((tmp_path / "new").iterdir()) == [tmp_path / "new" / "a"]
    with pytest.raises(InputError, match="cannot write there"):
        make_out_dir("/proc/envisat-test-out")


def test_an_empty_output_path_is_refused_before_any_work(tmp_path, monkeypatch):
    """An empty path (`--out ""`, a script's unset variable) read as the working folder: the checks passed, and the
    job failed only at its first write (dataset export after every image was exported)."""
    from envisat_pose.config import InputError
    from envisat_pose.out_dirs import check_makeable, check_out_dir, check_out_file, make_out_dir

    monkeypatch.chdir(tmp_path)
    for check in (check_out_dir, make_out_dir, check_makeable):
        with pytest.raises(InputError, match=r"^out_dir '': expected a folder path"):
            check("")
    with pytest.raises(InputError, match=r"^--montage '': expected a file path"):
        check_out_file("", "--montage")
    assert list(tmp_path.iterdir()) == []


def test_the_output_file_rule(tmp_path):
    from envisat_pose.config import InputError
    from envisat_pose.out_dirs import check_out_file, make_out_file_dir

    target = tmp_path / "a" / "b" / "det.npz"
    check_out_file(str(target))  # creates nothing
    assert not (tmp_path / "a").exists()
    make_out_file_dir(str(target))
    assert (tmp_path / "a" / "b").is_dir() and list((tmp_path / "a" / "b").iterdir()) == []
    (tmp_path / "f").write_text("x")
    with pytest.raises(InputError, match="is a file, not a folder"):
        check_out_file(str(tmp_path / "f" / "det.npz"), "--json")
    with pytest.raises(InputError, match="out .* is a folder"):
        check_out_file(str(tmp_path / "a"))


def test_a_plain_script_runs_a_local_pool_without_a_main_guard(tmp_path):
    """A user's script without `if __name__ == "__main__":` whose job starts spawned workers (export_dataset,
    run_generate with workers=2): the workers do not run the script again (once each failed in multiprocessing's
    bootstrapping check and the job died with BrokenProcessPool)."""
    import subprocess
    import sys

    script = tmp_path / "plain.py"
    script.write_text("import math\nfrom envisat_pose.pools import RunnerConfig, run_tasks\n"
                      "print('start')\n"
                      "print(sorted(r for _, r in run_tasks(math.sqrt, [(4.0,), (9.0,)], RunnerConfig('local', 2))))\n")
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.split() == ["start", "[2.0,", "3.0]"]  # the script's lines once: not again in a worker


@pytest.mark.parametrize("address, needle", [("notanaddress", "tcp://HOST:PORT"), ("tcp://host", "tcp://HOST:PORT"),
                                             ("tcp://127.0.0.1:1", "accepts a connection")])
def test_a_dask_scheduler_that_is_not_there_is_one_line(address, needle):
    from envisat_pose.config import ConfigError

    with pytest.raises(ConfigError, match=needle):
        RunnerConfig("dask", 1, address)


def test_a_field_compared_by_its_record_takes_another_spelling_of_the_same_file(tmp_path):
    """compared_by: a path given as another text (absolute, from another folder) is the same input when the
    header's record of the file (its sha256) is the same; another file is still another config."""
    from envisat_pose.config import InputError
    from envisat_pose.resumable import ResumableJob

    def job(path, sha):
        return ResumableJob(str(tmp_path), "test job v1", "test set", {"config": {"seed": 0, "file": path}}, "units",
                            2, unit_file, header={"file": {"sha256": sha}},
                            compared_by={"config.file": "file.sha256"})

    first = job("a/t.xml", "aa")
    first.resume(first.open())
    again = job("/elsewhere/a/t.xml", "aa")
    assert again.open() is not None  # the same file under another path: resumed
    with pytest.raises(InputError, match=r"another config or seed \(file = 'a/t.xml' \(sha256 aa\) there, 'a/t.xml' "
                                         r"\(sha256 bb\) here\)"):
        job("a/t.xml", "bb").open()
    plain = ResumableJob(str(tmp_path), "test job v1", "test set", {"config": {"seed": 0, "file": "x.xml"}}, "units",
                         2, unit_file, header={"file": {"sha256": "aa"}})
    with pytest.raises(InputError, match=r"file = 'a/t.xml' there, 'x.xml' here"):
        plain.open()  # without compared_by the text is compared


def test_another_target_is_named_first_among_the_differences_it_brings(tmp_path):
    """Another --target on a dataset's folder: the target's size scales config fields (generate's range and keep-out
    margin), whose differences sort before 'target' and filled the three shown ('random.keepout_margin_m = 2.0
    there, 0.07289 here, ...'), the target itself left out. The file compared by its record comes first, named by
    its path as given with its sha256 (its text alone may be the same, its sha256 alone names no file)."""
    from envisat_pose.config import InputError
    from envisat_pose.resumable import ResumableJob

    def job(path, sha, scale):
        config = {"seed": 0, "a_range_m": scale, "b_margin_m": scale, "c_offset_m": scale, "target": path}
        return ResumableJob(str(tmp_path), "test job v1", "test set", {"config": config}, "units", 2, unit_file,
                            header={"target": {"sha256": sha}}, compared_by={"config.target": "target.sha256"})

    first = job("models/big.xml", "aa11", 1.0)
    first.resume(first.open())
    with pytest.raises(InputError, match=r"another config or seed \(target = 'models/big.xml' \(sha256 aa11\) there, "
                                         r"'models/small.xml' \(sha256 bb22\) here, a_range_m = 1.0 there, 0.1 here, "
                                         r"b_margin_m = 1.0 there, 0.1 here, \.\.\.\)"):
        job("models/small.xml", "bb22", 0.1).open()


def test_a_script_whose_own_function_is_the_task_runs_a_local_pool(tmp_path):
    """A script (bench/tracking.py, bench/acquisition.py) that hands the pool a function it defines itself, under
    its main guard: the workers find it in the script (the pickled task names `__main__.square`). Hiding the
    script from the workers for a plain script (above) failed these with "Can't pickle <function ...>"."""
    import subprocess
    import sys

    script = tmp_path / "own_task.py"
    script.write_text("from envisat_pose.pools import RunnerConfig, run_tasks\n\n\ndef square(x):\n    return x * x\n\n\n"
                      "if __name__ == '__main__':\n"
                      "    print(sorted(r for _, r in run_tasks(square, [(2,), (3,)], RunnerConfig('local', 2))))\n")
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.split() == ["[4,", "9]"]


def test_a_partial_of_the_scripts_own_function_runs_a_local_pool(tmp_path):
    """functools.partial over a function the script defines: the workers find it in the script as above."""
    import subprocess
    import sys

    script = tmp_path / "own_partial.py"
    script.write_text("import functools\n\nfrom envisat_pose.pools import RunnerConfig, run_tasks\n\n\n"
                      "def power(x, n):\n    return x ** n\n\n\n"
                      "if __name__ == '__main__':\n    cube = functools.partial(power, n=3)\n"
                      "    print(sorted(r for _, r in run_tasks(cube, [(2,), (3,)], RunnerConfig('local', 2))))\n")
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.split() == ["[8,", "27]"]


def test_a_task_that_raises_on_a_jobs_own_cluster_is_the_jobs_one_line(tmp_path):
    """A task that raises on a job's own LocalCluster (generate on a full disk): its error reaches the job, whose
    one line says it. The worker's 'Compute Failed' block (the task's traceback, logged by the worker process on
    the terminal's stderr before the job's line) is left out; the worker's other error records are kept."""
    import subprocess
    import sys

    script = tmp_path / "raising.py"
    script.write_text("import logging\nimport sys\n\nfrom envisat_pose.pools import RunnerConfig, run_tasks\n\n\n"
                      "def task(k):\n    if k == 0:\n"
                      "        logging.getLogger('distributed.worker').error('an error of its own')\n"
                      "        return k\n    return 1 / 0\n\n\n"
                      "if __name__ == '__main__':\n    try:\n"
                      "        list(run_tasks(task, [(0,), (1,)], RunnerConfig('dask', 1)))\n"
                      "    except ZeroDivisionError as err:\n        sys.exit(f'job: error: {err}')\n")
    run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    err = run.stderr.splitlines()
    assert run.returncode == 1 and len(err) == 2, run.stderr[-3000:]
    assert err[0].endswith("distributed.worker - ERROR - an error of its own"), err
    assert err[1] == "job: error: division by zero", err


def test_a_jobs_own_cluster_says_nothing_while_another_holds_dasks_default_port(tmp_path):
    """Another Dask cluster or notebook on the machine holds port 8787 (Dask's default): a job's own LocalCluster
    ran its scheduler's HTTP server there anyway (it starts one whatever dashboard_address says) and printed
    "Port 8787 is already in use" warnings on every job. Its server now takes a free loopback port: the job's
    stderr is empty and its results whole."""
    import socket
    import subprocess
    import sys

    holder = socket.socket()
    try:
        holder.bind(("127.0.0.1", 8787))
        holder.listen(1)
    except OSError:  # something on this machine holds it already: the same condition
        holder.close()
        holder = None
    try:
        script = tmp_path / "quiet.py"
        script.write_text("from envisat_pose.pools import RunnerConfig, run_tasks\n\n\n"
                          "def square(x):\n    return x * x\n\n\n"
                          "if __name__ == '__main__':\n"
                          "    print(sorted(r for _, r in run_tasks(square, [(2,), (3,)], RunnerConfig('dask', 1))))\n")
        run = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120,
                             cwd=tmp_path)
    finally:
        if holder is not None:
            holder.close()
    assert run.returncode == 0 and run.stdout.split() == ["[4,", "9]"], run.stderr[-2000:]
    assert run.stderr == "", run.stderr[-2000:]


def test_a_second_interrupt_while_the_pool_stops_leaves_no_traceback_from_its_thread(monkeypatch):
    """Ctrl-C twice, or `timeout` (which signals envisat and then its group: two signals): the second lands while
    the pool's workers are stopped (the join of its thread). The stop still finishes before the queued tasks are
    cancelled: cancelled while the pool's thread marked them failed, Python 3.11's thread died with an
    InvalidStateError traceback, printed after the verb's one line."""
    import threading
    import time
    from concurrent.futures import ProcessPoolExecutor

    died, threads = [], []
    monkeypatch.setattr(threading, "excepthook", lambda hook_args: died.append(hook_args.exc_type))
    shutdown = ProcessPoolExecutor.shutdown

    def interrupted_once(self, wait=True, **kwargs):
        thread = self._executor_manager_thread
        if wait and thread is not None and not threads:
            threads.append(thread)

            def join(*_):  # the second signal's KeyboardInterrupt, raised in the join
                del thread.join
                raise KeyboardInterrupt

            thread.join = join
        return shutdown(self, wait, **kwargs)

    monkeypatch.setattr(ProcessPoolExecutor, "shutdown", interrupted_once)
    tasks = run_tasks(time.sleep, [(0.1,)] + [(30.0,)] * 8, RunnerConfig("local", 2))
    with pytest.raises(KeyboardInterrupt):
        try:
            for _ in tasks:
                raise KeyboardInterrupt  # the first signal, at the first unit done
        finally:
            tasks.close()
    threads[0].join(timeout=30.0)
    assert not threads[0].is_alive() and died == []


def test_pool_workers_leave_the_target_files_warnings_to_the_job(capfd):
    """A job with N workers printed its target file's warnings (latched joints) N more times, each as Python's
    raw two-line UserWarning, beside its own one line: each worker loads the file again. The job says them; the
    workers say nothing of them, and any other warning still reaches the user."""
    import warnings

    from envisat_pose.config_errors import TargetFileWarning

    tasks = [("said once by the job", TargetFileWarning), ("a worker's own warning", UserWarning)]
    assert len(list(run_tasks(warnings.warn, tasks, RunnerConfig("local", 2)))) == 2
    err = capfd.readouterr().err
    assert "said once by the job" not in err and "a worker's own warning" in err, err
