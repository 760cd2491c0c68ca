"""The bar of `envisat run --runs N` (pipelines/runs/run_progress.py): it counts every run's frames as the runs step
them, not whole runs (a 30-minute job sat at 0 % until a run ended), and ends at its total; each run counts its
frames into a file of its own that the job reads."""

from envisat_pose.pipelines.runs import run_progress


class FakeTqdm:
    """tqdm as the bar uses it: its total and unit, and its position after every update."""

    made: list = []

    def __init__(self, total=None, unit="it", desc=None, **kwargs):
        self.total, self.unit, self.desc, self.n, self.positions, self.closed = total, unit, desc, 0, [], False
        FakeTqdm.made.append(self)

    def update(self, n=1):
        self.n += n
        self.positions.append(self.n)

    def set_postfix_str(self, s="", refresh=True):
        self.postfix = s

    def close(self):
        self.closed = True


def test_the_bar_of_several_runs_counts_their_frames_one_by_one_to_its_total(tmp_path, monkeypatch):
    """`envisat run --runs 2` at 64 px for 2 s (3 frames a run), the runs inline (one process: the workers' counts
    are read as they are written): the job's bar is over 2 x 3 frames and stands on every frame count in turn, 1 to
    6, then closes at 6. Each run's count is read by the bar (poll) right after the run writes it, so that no frame
    depends on the bar thread's timing; the thread still runs as in a job."""
    from envisat_pose.pipelines.common.job_defaults import default_weights_path
    from envisat_pose.pipelines.jobs import resolve_job
    from envisat_pose.pipelines.runs.closed_loop import run_closed_loop

    monkeypatch.setattr("tqdm.tqdm", FakeTqdm)
    monkeypatch.setattr(FakeTqdm, "made", [])
    bars = []

    class Watched(run_progress.RunsBar):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            bars.append(self)

    written = []

    def advance(tally):  # every frame written, then read by the job's bar before the next frame is stepped
        tally.n += 1
        tally.write()
        written.append(tally.n)
        bars[0].poll()

    monkeypatch.setattr(run_progress, "RunsBar", Watched)
    monkeypatch.setattr(run_progress.FrameTally, "advance", advance)
    cfg = resolve_job("run", "default", overrides={"duration_s": 2.0, "runs": 2, "workers": 1,
                                                   "weights": default_weights_path(), "image.resolution_px": 64})
    summary = run_closed_loop(cfg, str(tmp_path / "run"), progress=True)
    T = summary["frames"]
    bar, = [b for b in FakeTqdm.made if b.desc.startswith("closed loop")]
    assert (bar.total, bar.unit, T) == (6, "frame", 3)
    assert bar.positions == [1, 2, 3, 4, 5, 6] and bar.n == bar.total and bar.closed
    assert written == [1, 2, 3, 1, 2, 3]  # each run's count, frame by frame


def test_the_bar_reads_each_runs_file_and_counts_a_finished_run_whole(tmp_path, monkeypatch):
    """Two runs of 5 frames: a run's count is on its file only from its first write, then as often as
    REPORT_INTERVAL_S allows and at close; the bar shows the files' sum (a missing or torn file counts nothing, a
    count beyond the run's frames is the run's frames), never moves back, and a run that returned counts whole
    whatever its file says."""
    monkeypatch.setattr("tqdm.tqdm", FakeTqdm)
    monkeypatch.setattr(FakeTqdm, "made", [])
    monkeypatch.setattr(run_progress, "REPORT_INTERVAL_S", 3600.0)  # the thread never polls in this test
    paths = [run_progress.tally_path(str(tmp_path)) + f"-{r}" for r in range(2)]
    a = run_progress.FrameTally(paths[0])
    a.advance()
    a.advance()  # within the interval: not written
    assert run_progress.read_tally(paths[0]) == 1 and run_progress.read_tally(paths[1]) is None
    with run_progress.runs_bar(paths, 5, "test") as finished:
        bar = FakeTqdm.made[-1]
        assert (bar.total, bar.unit) == (10, "frame")
        a.close()
        live = finished.__self__  # the RunsBar: its poll is what its thread calls every REPORT_INTERVAL_S
        live.poll()
        assert bar.n == 2
        with open(paths[1], "w") as fh:
            fh.write("9")  # past the run's 5 frames
        live.poll()
        assert bar.n == 7
        with open(paths[0], "w") as fh:
            fh.write("")  # torn or not yet written: the last count stands
        live.poll()
        assert bar.n == 7
        finished(0)
        assert bar.n == 10 and live.counts == [5, 5]
    assert bar.closed and not live._thread.is_alive()
