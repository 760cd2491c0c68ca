"""What a default pool may take of the machine (envisat_pose.pools): the usable cores (os.cpu_count lowered by the
CPU affinity and a cgroup CPU quota), the usable memory, the default process count and the workers' thread
shares; and the one shard check's threads."""

import os

import pytest

from envisat_pose import pools


@pytest.mark.parametrize("cores, affinity, quota, usable", [
    (1, None, None, 1),     # one core
    (64, None, None, 64),   # a big machine, all of it
    (64, 2, None, 2),       # taskset / a container's cpuset: os.cpu_count() still says 64
    (64, None, 2, 2),       # a container's --cpus=2: affinity says 64, the quota 2
    (64, 8, 3, 3),
])
def test_usable_cores_follow_the_affinity_and_the_quota(machine, cores, affinity, quota, usable):
    machine(cores, affinity, quota)
    assert pools.usable_cores() == usable
    assert pools.cpu_share(1) == usable and pools.cpu_share(usable + 1) == 1


@pytest.mark.parametrize("files, cores", [
    ({"cpu.max": "150000 100000\n"}, 2),  # 1.5 cores of quota: 2 threads
    ({"cpu.max": "max 100000\n"}, None),
    ({"cpu/cpu.cfs_quota_us": "200000\n", "cpu/cpu.cfs_period_us": "100000\n"}, 2),  # cgroup v1
    ({"cpu/cpu.cfs_quota_us": "-1\n", "cpu/cpu.cfs_period_us": "100000\n"}, None),
    ({"cpu.max": "garbage\n"}, None),
    ({}, None),
])
def test_the_cgroup_quota_is_read_as_a_container_sees_it(monkeypatch, tmp_path, files, cores):
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_text(text)
    monkeypatch.setattr(pools, "CGROUP_ROOT", str(tmp_path))
    assert pools.cgroup_cpu_limit() == cores


def test_usable_memory_is_the_smaller_of_memavailable_and_the_cgroups_room(monkeypatch, tmp_path):
    (tmp_path / "meminfo").write_text("MemTotal: 24000000 kB\nMemAvailable: 4000000 kB\n")
    monkeypatch.setattr(pools, "MEMINFO", str(tmp_path / "meminfo"))
    monkeypatch.setattr(pools, "CGROUP_ROOT", str(tmp_path))
    assert pools.usable_memory_bytes() == 4000000 * 1024
    (tmp_path / "memory").mkdir()
    (tmp_path / "memory" / "memory.limit_in_bytes").write_text("9223372036854771712\n")  # v1's 'no limit'
    (tmp_path / "memory" / "memory.usage_in_bytes").write_text("1000\n")
    assert pools.usable_memory_bytes() == 4000000 * 1024
    (tmp_path / "memory.max").write_text("2000000000\n")
    (tmp_path / "memory.current").write_text("500000000\n")
    assert pools.usable_memory_bytes() == 1_500_000_000
    monkeypatch.setattr(pools, "MEMINFO", str(tmp_path / "none"))
    (tmp_path / "memory.max").write_text("max\n")
    assert pools.usable_memory_bytes() is None


def test_default_processes_stop_at_the_work_the_cores_and_the_memory(machine):
    machine(64, memory_gb=24)
    assert pools.default_processes(100, 1_000_000_000) == 24  # 64 cores, but 24 GB at 1 GB each
    assert pools.default_processes(8, 1_000_000_000) == 8  # no more than the work
    assert pools.default_processes(100, 1_000) == 64
    machine(64, memory_gb=0.5)
    assert pools.default_processes(100, 1_000_000_000) == 1  # at least one
    machine(64, affinity=2)
    assert pools.default_processes(100, 1_000) == 2


def test_the_thread_share_is_of_the_processes_that_start(machine):
    machine(8)
    assert pools.thread_env(8) == {"LP_NUM_THREADS": "1"}
    assert pools.thread_env(8, units=2) == {"LP_NUM_THREADS": "4"}  # a pool of 8 over 2 shards starts 2
    machine(64, affinity=2)
    assert pools.thread_env(1, pools.BLAS_THREADS) == {name: "2" for name in pools.BLAS_THREADS}  # not 64


def test_the_shard_check_hashes_on_the_usable_cores(machine, monkeypatch, tmp_path):
    """64 cores by os.cpu_count but an affinity of 2: two hashing threads, not 64."""
    import concurrent.futures
    import hashlib

    from envisat_pose.shard_reader import shard_problems

    machine(64, affinity=2)
    seen = []

    class Recording(concurrent.futures.ThreadPoolExecutor):
        def __init__(self, threads, **kwargs):
            seen.append(threads)
            super().__init__(threads, **kwargs)

    monkeypatch.setattr(concurrent.futures, "ThreadPoolExecutor", Recording)
    entries = [{"name": f"s-{i}.tar", "bytes": 3, "sha256": hashlib.sha256(b"abc").hexdigest()} for i in range(10)]
    for entry in entries:
        (tmp_path / entry["name"]).write_bytes(b"abc")
    assert shard_problems(str(tmp_path), entries) == [None] * 10
    assert seen == [2] and os.cpu_count() == 64


def test_a_local_dask_cluster_starts_no_more_workers_than_tasks(monkeypatch):
    """--backend dask --workers 64 over 2 tasks: a LocalCluster of 2 worker processes, not 64, with no per-worker
    memory cap (Dask's default share, memory over workers, would pause and restart factory workers the machine
    holds)."""
    import dask.distributed

    started = []

    def recording(**kwargs):
        started.append((kwargs["n_workers"], kwargs.get("memory_limit", "auto")))
        raise RuntimeError("no cluster in this test")

    monkeypatch.setattr(dask.distributed, "LocalCluster", recording)
    with pytest.raises(RuntimeError, match="no cluster"):
        list(pools.run_tasks(divmod, [(7, 2), (9, 4)], pools.RunnerConfig("dask", 64)))
    assert started == [(2, 0)]


@pytest.mark.parametrize("name", ["WORLD_SIZE", "RANK", "LOCAL_RANK", "LOCAL_WORLD_SIZE"])
def test_a_torchrun_variable_that_is_not_a_count_is_refused_naming_it(monkeypatch, name):
    """A launcher or shell that set torchrun's variables wrong: one line naming the variable (it was a bare
    int() ValueError in the training, the loaders and every job's output lock)."""
    from envisat_pose.config import InputError

    monkeypatch.setenv(name, "two")
    with pytest.raises(InputError, match=f"environment variable {name}='two': expected a whole number"):
        pools.torchrun_int(name, 1)
    monkeypatch.setenv(name, "-1")
    with pytest.raises(InputError, match=name):
        pools.torchrun_int(name, 1)
    monkeypatch.setenv(name, " ")
    assert pools.torchrun_int(name, 7) == 7
    monkeypatch.setenv(name, "3")
    assert pools.torchrun_int(name, 7) == 3


def test_a_job_under_a_broken_world_size_says_so_in_one_line(monkeypatch, tmp_path):
    from envisat_pose.config import InputError
    from envisat_pose.out_lock import output_lock

    monkeypatch.setenv("WORLD_SIZE", "abc")
    with pytest.raises(InputError, match="WORLD_SIZE='abc'"):
        with output_lock(str(tmp_path / "out"), "generate"):
            pass
    assert not (tmp_path / "out").exists()


def test_a_worker_count_given_above_the_cores_or_the_memory_is_warned_of_once_in_one_line(machine):
    """Only the defaults were capped: `--workers 8` on 2 usable cores (or 8 closed loops of 1.4 GB on 5 GB) ran
    without a word. The one warning names the field, the value, the cores or the memory; the job still runs."""
    import warnings
    from types import SimpleNamespace

    machine(64, affinity=2, memory_gb=5.0)
    with pytest.warns(UserWarning) as said:
        pools.warn_oversubscribed(8, "workers")
    assert [str(w.message) for w in said] == ["workers = 8: more processes than the 2 usable cores (they share "
                                              "them); the job runs as asked"]
    with pytest.warns(UserWarning) as said:
        pools.warn_oversubscribed(2, "online.workers", bytes_each=4_000_000_000)  # within the cores, not the memory
    assert len(said) == 1 and str(said[0].message) == (
        "online.workers = 2: 2 processes at ~4.0 GB each need ~8.0 GB, more than the 5.0 GB of memory available; the "
        "job runs as asked")
    with pytest.warns(UserWarning) as said:
        pools.warn_oversubscribed(8, bytes_each=1_400_000_000)  # both: one line
    assert len(said) == 1 and "2 usable cores" in str(said[0].message) and "~11.2 GB" in str(said[0].message)
    assert "\n" not in str(said[0].message)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pools.warn_oversubscribed(2, bytes_each=1_000_000_000)  # what the machine holds
        pools.warn_oversubscribed(8, units=2)  # a pool starts no more processes than its tasks
        pools.warn_runner(pools.RunnerConfig("inline", 8), 100)  # in this process
        existing = SimpleNamespace(backend="dask", workers=8, scheduler="tcp://127.0.0.1:8786")  # not connected to
        pools.warn_runner(existing, 100)  # a cluster's own machines
    with pytest.warns(UserWarning, match="^workers = 8: more processes than the 2 usable cores"):
        pools.warn_runner(pools.RunnerConfig("local", 8), 100)
