"""One job at a time on an output (envisat_pose/out_lock.py): two jobs on one --out were "safe, not exclusive";
now the second is refused at once in one line naming the folder, the first job's verb and pid, having written
nothing; the lock goes with its job (a second run after it works, a SIGKILLed holder blocks nothing) and leaves
no file behind; a folder's listing (resume, export's empty check) does not count a killed job's lock file."""

import os
import signal
import subprocess
import sys
import threading

os.environ.setdefault("MUJOCO_GL", "osmesa")

import pytest

from envisat_pose.app.cli import main
from envisat_pose.config import InputError
from envisat_pose.out_lock import LOCK_NAME, lock_file, output_lock

HOLD = ("import sys, time; from envisat_pose.out_lock import output_lock\n"
        "with output_lock(sys.argv[1], sys.argv[2], folder=sys.argv[3] != 'file', beside=sys.argv[3] == 'beside'):\n"
        "    print('held', flush=True); time.sleep(120)\n")
BESIDE = ("dataset export", "export_dataset")  # a folder published whole by a rename: its lock file beside it


@pytest.fixture()
def holder():
    """hold(path, job, folder=True): another process holding the lock of path as job `job` (killed after)."""
    procs = []

    def hold(path, job="generate", folder=True):  # folder: True, False or "beside"
        mode = "beside" if folder == "beside" else "folder" if folder else "file"
        proc = subprocess.Popen([sys.executable, "-c", HOLD, str(path), job, mode],
                                stdout=subprocess.PIPE, text=True)
        procs.append(proc)
        assert proc.stdout.readline().strip() == "held"
        return proc

    yield hold
    for proc in procs:
        proc.kill()
        proc.wait()


def refused(err: str, path, pid: int, verb: str) -> bool:
    return (len(err.strip().splitlines()) == 1 and repr(str(path)) in err and f"pid {pid}" in err
            and f"envisat {verb}," in err and "in use by another job" in err)


def test_a_second_job_on_a_held_folder_is_refused_in_one_line_having_written_nothing(tmp_path, holder, capsys):
    """The pipeline function and the verb: refused at once, the folder as the first job left it."""
    from envisat_pose.pipelines.campaigns.campaign import MonteCarloConfig, run_campaign

    out = tmp_path / "mc"
    first = holder(out, "montecarlo")
    before = sorted(os.listdir(out))
    assert before == [LOCK_NAME]
    with pytest.raises(InputError) as err:
        run_campaign(MonteCarloConfig(scenario="default", runs=2, duration_s=10.0), str(out))
    assert refused(str(err.value), out, first.pid, "montecarlo"), err.value
    assert str(err.value).startswith("out_dir ")
    argv = ["montecarlo", "--scenario", "default", "--runs", "2", "--duration-s", "10", "--out", str(out), "--quiet"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"envisat montecarlo: error: --out {str(out)!r} is in use") and refused(
        err, out, first.pid, "montecarlo"), err
    assert sorted(os.listdir(out)) == before and first.poll() is None  # nothing written; the first runs on


# every writing verb with its output held by another job; the inputs need not exist: the lock comes first
FOLDER_VERBS = {
    "generate": ["generate", "--num-images", "2", "--resolution", "64", "--quiet", "--out"],
    "run": ["run", "--scenario", "default", "--duration-s", "10", "--quiet", "--out"],
    "train": ["train", "--online", "--quiet", "--out"],  # its inputs are checked first (a resume's folder)
    "dataset export": ["dataset", "export", "ds", "--format", "coco", "--quiet", "--out"],
}
FILE_VERBS = {
    "simulate": ["simulate", "--duration-s", "10", "--quiet", "--out"],
    "estimate": ["estimate", "--scenario", "default", "--duration-s", "10", "--quiet", "--out"],
    "detect": ["detect", "--data", "ds", "--quiet", "--out"],
    "calibrate": ["calibrate", "--data", "ds", "--quiet", "--out"],
    "evaluate": ["evaluate", "--data", "ds", "--quiet", "--json"],
}


@pytest.mark.parametrize("verb", sorted(FOLDER_VERBS) + sorted(FILE_VERBS))
def test_every_writing_verb_is_refused_on_a_held_output(verb, tmp_path, holder, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    folder = verb in FOLDER_VERBS
    out = tmp_path / ("out" if folder else "out.npz" if verb in ("simulate", "estimate", "detect") else
                      "out.json" if verb == "evaluate" else "out.safetensors")
    first = holder(out, "someverb", "beside" if verb in BESIDE else folder)
    before = sorted(os.listdir(tmp_path))
    assert main((FOLDER_VERBS if folder else FILE_VERBS)[verb] + [str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"envisat {verb.split()[0]}: error: --") and refused(err, out, first.pid, "someverb"), err
    assert sorted(os.listdir(tmp_path)) == before  # nothing written
    assert not folder or verb in BESIDE or os.listdir(out) == [LOCK_NAME]


# every job's function (the verbs' and the Python API's): (module, function, its output argument, a folder?)
FUNCTIONS = [
    ("datagen.factory", "run_generate", "out_dir", True),
    ("pipelines.campaigns.simulate", "run_simulate", "out", False),
    ("pipelines.campaigns.estimate", "run_estimate", "out", False),
    ("pipelines.campaigns.campaign", "run_campaign", "out_dir", True),
    ("pipelines.campaigns.sweep", "run_sweep", "out_dir", True),
    ("pipelines.campaigns.report", "write_report", "out", False),
    ("pipelines.detector.train", "train_detector", "run_dir", True),
    ("pipelines.detector.detect", "run_detect", "out", False),
    ("pipelines.detector.detect_target", "run_detect_target", "out", False),
    ("pipelines.detector.evaluate", "run_evaluate", "json_path", False),
    ("pipelines.detector.evaluate_target", "evaluate_target_detector", "json_path", False),
    ("pipelines.detector.calibrate", "run_calibration", "out", False),
    ("pipelines.detector.calibrate", "fit_face_cue", "out", False),
    ("pipelines.detector.calibrate_target", "run_calibrate_target", "out", False),
    ("pipelines.runs.closed_loop", "run_closed_loop", "out_dir", True),
    ("pipelines.runs.track", "track_frames", "out_dir", True),
    ("pipelines.adaptation.adapt", "adapt", "out_dir", True),
    ("pipelines.datasets.export", "export_dataset", "out_dir", True),
]


@pytest.mark.parametrize("module,name,arg,folder", FUNCTIONS, ids=[f[1] for f in FUNCTIONS])
def test_every_jobs_function_is_refused_on_a_held_output(module, name, arg, folder, tmp_path, holder):
    """What a verb does its function does: the lock is taken first, so no other argument needs to be valid."""
    import importlib
    import inspect

    fn = getattr(importlib.import_module(f"envisat_pose.{module}"), name)
    out = tmp_path / ("out" if folder else "out.file")
    first = holder(out, "someverb", "beside" if name in BESIDE else folder)
    before = sorted(os.listdir(tmp_path))
    required = [p for p in inspect.signature(fn).parameters.values() if p.default is inspect.Parameter.empty
                and p.kind is p.POSITIONAL_OR_KEYWORD]
    given = {p.name: None for p in required if p.name != arg}
    if name == "train_detector":  # locked after its arguments' checks (a resume needs its folder): valid ones
        from envisat_pose.datagen.generate_config import GenerateConfig
        from envisat_pose.perception.train import TrainConfig
        from envisat_pose.pipelines.detector.train import OnlineConfig

        given = {"cfg": TrainConfig(), "data_dirs": [], "online": OnlineConfig(GenerateConfig(resolution_px=64), 1)}
    if name == "run_generate":  # locked after its arguments' checks (a finished dataset read-only takes no lock)
        from envisat_pose.datagen.generate_config import GenerateConfig

        given = {"cfg": GenerateConfig(resolution_px=64)}
    with pytest.raises(InputError) as err:
        fn(**given, **{arg: str(out)})
    assert str(err.value).startswith(f"{arg} ") and refused(str(err.value), out, first.pid, "someverb"), err.value
    assert sorted(os.listdir(tmp_path)) == before


# the outputs beside a job's main one: (module, function, the side output's argument, the other arguments)
SIDE_OUTPUTS = [
    ("pipelines.campaigns.simulate", "run_simulate", "rrd", {"cfg": None, "out": "sim.npz"}),
    ("pipelines.campaigns.estimate", "run_estimate", "rrd", {"cfg": None, "out": "est.npz"}),
    ("pipelines.campaigns.campaign", "run_campaign", "rrd", {"cfg": None, "out_dir": "mc"}),
    ("pipelines.datasets.inspect", "inspect_dataset", "rrd", {"src": "ds", "montage": "m.png"}),
    ("pipelines.datasets.inspect", "inspect_dataset", "montage", {"src": "ds"}),
]


@pytest.mark.parametrize("module,name,arg,others", SIDE_OUTPUTS, ids=[f"{f[1]}-{f[2]}" for f in SIDE_OUTPUTS])
def test_an_output_beside_the_main_one_held_by_another_job_is_refused(module, name, arg, others, tmp_path, holder,
                                                                        monkeypatch):
    """A recording (--rrd) or a montage another job is writing: refused in one line naming it, nothing written
    (they were written over by whichever job ended last). The dataset a montage reads must exist: it is made."""
    import importlib

    monkeypatch.chdir(tmp_path)
    if name == "inspect_dataset":
        assert main(["generate", "--num-images", "2", "--shard-size", "2", "--resolution", "64", "--workers", "1",
                     "--out", "ds", "--quiet"]) == 0
    fn = getattr(importlib.import_module(f"envisat_pose.{module}"), name)
    if "cfg" in others:
        from envisat_pose.pipelines.jobs import resolve_job

        kind = {"run_simulate": "simulate", "run_estimate": "estimate", "run_campaign": "montecarlo"}[name]
        others = {**others, "cfg": resolve_job(kind, "default")}  # refused before any work: no duration needed
    side = tmp_path / ("side.rrd" if arg == "rrd" else "side.png")
    first = holder(side, "someverb", False)
    before = sorted(os.listdir(tmp_path))
    with pytest.raises(InputError) as err:
        fn(**others, **{arg: str(side)})
    assert str(err.value).startswith(f"{arg} ") and refused(str(err.value), side, first.pid, "someverb"), err.value
    assert sorted(os.listdir(tmp_path)) == before


def test_the_lock_goes_with_its_job_and_leaves_no_file(tmp_path):
    """A run, then a second on the same output: both write (the first's lock is gone), and the folder holds only
    the job's files; another process takes the lock after them. A job stopped leaves no folder it made."""
    from envisat_pose.datagen.scenario import ScenarioConfig
    from envisat_pose.pipelines.campaigns.simulate import run_simulate

    for seed in (1, 2):
        run_simulate(ScenarioConfig(duration_s=5.0, seed=seed), str(tmp_path / "run.npz"))
    assert sorted(os.listdir(tmp_path)) == ["run.config.toml", "run.npz"]
    took = subprocess.run([sys.executable, "-c", HOLD.replace("time.sleep(120)", "pass"), str(tmp_path / "run.npz"),
                           "simulate", "file"], capture_output=True, text=True)
    assert took.stdout == "held\n", took.stderr  # another process takes it after them
    with pytest.raises(KeyboardInterrupt):
        with output_lock(tmp_path / "new" / "deeper", "run"):
            assert os.listdir(tmp_path / "new" / "deeper") == [LOCK_NAME]
            raise KeyboardInterrupt
    assert sorted(os.listdir(tmp_path)) == ["run.config.toml", "run.npz"]  # the folders it made are gone


def test_a_sigkilled_holder_blocks_nothing(tmp_path, holder):
    """The kernel's lock dies with its process: the lock file a SIGKILLed job leaves (its text naming a pid that
    may be anyone's now) does not block the next job, which takes it over and removes it."""
    from envisat_pose.datagen.scenario import ScenarioConfig
    from envisat_pose.pipelines.campaigns.simulate import run_simulate

    for out, folder in ((tmp_path / "mc", True), (tmp_path / "run.npz", False)):
        first = holder(out, "montecarlo", folder)
        first.send_signal(signal.SIGKILL)
        first.wait()
        assert os.path.exists(lock_file(str(out), folder))  # left behind, with the dead job's text
        if folder:
            with output_lock(out, "montecarlo"):
                pass
        else:
            run_simulate(ScenarioConfig(duration_s=5.0, seed=1), str(out))
        assert not os.path.exists(lock_file(str(out), folder))


def test_a_killed_jobs_lock_file_is_not_another_jobs_entry(tmp_path, holder):
    """generate on a folder holding only a killed job's lock file writes its dataset (a resumable job's foreign
    entries skip it); an export beside a killed export's lock file writes its folder."""
    from envisat_pose.config import from_dict
    from envisat_pose.datagen.factory import run_generate
    from envisat_pose.datagen.generate_config import GenerateConfig
    from envisat_pose.pipelines.datasets.export import ExportConfig, export_dataset

    data, coco = tmp_path / "data", tmp_path / "coco"
    for out, mode in ((data, True), (coco, "beside")):
        proc = holder(out, folder=mode)
        proc.kill()
        proc.wait()
    run_generate(from_dict(GenerateConfig, {"num_images": 2, "shard_size": 2, "resolution_px": 64}), str(data))
    assert sorted(os.listdir(data)) == ["generate.config.toml", "manifest.json", "shard-000000.tar"]
    export_dataset(str(data), str(coco), ExportConfig(fmt="coco"))
    assert LOCK_NAME not in os.listdir(coco) and "export.json" in os.listdir(coco)


def locked_from_another_thread(out) -> list[str]:
    """The errors of output_lock(out) taken on another thread of this process ([] where it was taken)."""
    errors = []

    def second():
        try:
            with output_lock(out, "track"):
                pass
        except InputError as err:
            errors.append(str(err))

    t = threading.Thread(target=second)
    t.start()
    t.join()
    return errors


def test_a_job_calling_another_on_its_own_output_goes_on_and_another_thread_is_refused(tmp_path):
    out = tmp_path / "run"
    with output_lock(out, "run"):
        with output_lock(out, "run"):  # the same thread's job: under the same lock
            pass
        assert os.path.exists(out / LOCK_NAME)
        errors = locked_from_another_thread(out)
        assert len(errors) == 1 and f"envisat run, pid {os.getpid()}" in errors[0], errors
    assert not os.path.exists(out / LOCK_NAME)


def test_a_folder_that_refuses_a_new_file_is_named_with_its_own_reason(tmp_path, monkeypatch):
    """A folder where the user may not create files (another user's, read-only), and no lock file there to share:
    the line says 'Permission denied', the creation's reason, not the read-only retry's 'No such file'."""
    import errno

    from envisat_pose import out_lock

    real_open = os.open

    def no_new_lock_file(path, flags, *args):
        if str(path).endswith(LOCK_NAME) and flags & os.O_CREAT:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), path)
        return real_open(path, flags, *args)

    out = tmp_path / "theirs"
    out.mkdir()
    monkeypatch.setattr(out_lock.os, "open", no_new_lock_file)
    with pytest.raises(InputError) as err:
        with output_lock(out, "run"):
            pass
    monkeypatch.undo()
    assert str(err.value) == f"out_dir {str(out)!r}: cannot write there ({os.strerror(errno.EACCES)})", err.value
    assert os.listdir(out) == []


def test_a_rank_set_outside_torchrun_still_locks(tmp_path, monkeypatch):
    """RANK 1 with WORLD_SIZE 2 (a torchrun rank besides 0): no lock of its own (rank 0 holds the job's); RANK set
    alone (another tool's variable) locks as usual."""
    out = tmp_path / "run"
    with output_lock(out, "run"):
        monkeypatch.setenv("RANK", "1")
        monkeypatch.setenv("WORLD_SIZE", "2")
        with output_lock(out, "train"):  # rank 1 of 2: rank 0's lock is the job's
            pass
        monkeypatch.delenv("WORLD_SIZE")
        errors = locked_from_another_thread(out)
        assert len(errors) == 1 and "in use by another job" in errors[0], errors


def test_under_torchrun_rank_0_holds_the_jobs_lock_and_the_other_ranks_none(tmp_path, monkeypatch):
    """WORLD_SIZE 2: rank 0 takes the job's lock (another job is refused while it runs); rank 1 takes none (another
    job takes the folder while rank 1 is inside)."""
    for rank, refused in (("0", True), ("1", False)):
        out = tmp_path / f"rank{rank}"
        monkeypatch.setenv("WORLD_SIZE", "2")
        monkeypatch.setenv("RANK", rank)
        with output_lock(out, "train"):
            monkeypatch.delenv("WORLD_SIZE")
            monkeypatch.delenv("RANK")
            errors = locked_from_another_thread(out)
        assert (len(errors) == 1 and "in use by another job" in errors[0]) if refused else errors == [], (rank, errors)


def test_a_child_forked_under_the_lock_does_not_keep_it_after_its_job_is_killed(tmp_path):
    """A job holding the lock forks a child (a DataLoader worker) and is SIGKILLed: the child, still alive, holds
    no copy of the lock, so the next job takes it at once."""
    out = tmp_path / "run"
    code = ("import os, sys, time\nfrom envisat_pose.out_lock import output_lock\n"
            "with output_lock(sys.argv[1], 'train'):\n    pid = os.fork()\n    if pid == 0:\n"
            "        print('child', os.getpid(), flush=True)\n        time.sleep(60)\n        os._exit(0)\n"
            "    time.sleep(60)\n")
    job = subprocess.Popen([sys.executable, "-c", code, str(out)], stdout=subprocess.PIPE, text=True)
    # the child's line comes after its fork hooks ran (they run before os.fork returns in it): a loaded machine
    # may schedule the child late, and until then its copy of the descriptor holds the lock
    child = int(job.stdout.readline().split()[1])
    try:
        job.send_signal(signal.SIGKILL)
        job.wait()
        os.kill(child, 0)  # the forked child lives on
        with output_lock(out, "run"):
            pass
    finally:
        os.kill(child, signal.SIGKILL)


def test_an_export_appears_whole_by_one_rename(tmp_path, monkeypatch):
    """The export's folder appears whole, by one rename of its staging folder: its lock file lies beside it. A lock
    inside would make the folder first, and the export's entries would then be moved in one at a time, so a kill
    between two moves left half an export under the final name."""
    import shutil

    from envisat_pose.config import from_dict
    from envisat_pose.datagen.factory import run_generate
    from envisat_pose.datagen.generate_config import GenerateConfig
    from envisat_pose.pipelines.datasets import export as export_module
    from envisat_pose.pipelines.datasets.export import ExportConfig, export_dataset

    data, coco = tmp_path / "data", tmp_path / "coco"
    run_generate(from_dict(GenerateConfig, {"num_images": 2, "shard_size": 2, "resolution_px": 64}), str(data))
    moves = []

    def move(src, dst):
        moves.append(dst)
        return shutil.move(src, dst)

    monkeypatch.setattr(export_module.shutil, "move", move)
    export_dataset(str(data), str(coco), ExportConfig(fmt="coco"))
    assert moves == [] and "export.json" in os.listdir(coco)
    assert not any(n.endswith(LOCK_NAME) for n in os.listdir(tmp_path) + os.listdir(coco))
