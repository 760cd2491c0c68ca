"""`envisat dataset export|inspect|verify` and `envisat generate` on the inputs a user gets wrong: an unfinished
dataset, an existing empty --out, a bad seed or split, a target file given for another dataset, stray shards."""

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import json
import shutil

import pytest

from envisat_pose.app.cli import main as envisat_main
from envisat_pose.config import from_dict
from envisat_pose.datagen.factory import run_generate
from envisat_pose.datagen.generate_config import GenerateConfig

SMALL = {"num_images": 6, "shard_size": 2, "resolution_px": 64, "seed": 3}


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """A finished 6-image random-views dataset of 3 shards, and the same run interrupted after its first shard."""
    root = tmp_path_factory.mktemp("inputs")
    done, unfinished = str(root / "done"), str(root / "unfinished")
    run_generate(from_dict(GenerateConfig, SMALL), done)

    def interrupt(_):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_generate(from_dict(GenerateConfig, SMALL), unfinished, on_shard=interrupt)
    return {"done": done, "unfinished": unfinished}


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_export_refuses_and_inspect_flags_a_dataset_whose_generate_was_interrupted(small, tmp_path, capsys):
    src = small["unfinished"]
    rc = envisat_main(["dataset", "export", src, "--format", "coco", "--out", str(tmp_path / "out"), "--quiet"])
    line = one_error_line(capsys)
    assert rc == 2 and "an unfinished dataset (1 of 3 shards)" in line and "envisat generate" in line
    assert os.listdir(tmp_path) == []
    montage = str(tmp_path / "m.png")
    assert envisat_main(["dataset", "inspect", src, "--montage", montage, "--count", "1"]) == 0
    out, err = capsys.readouterr()
    assert "warning:" in err and "an unfinished dataset (1 of 3 shards)" in err
    stats = json.loads(out[:out.rindex("}") + 1])
    assert stats["samples"] == 2 and "1 of 3 shards" in stats["unfinished_dataset"]
    assert envisat_main(["dataset", "inspect", small["done"], "--montage", montage, "--count", "1"]) == 0
    out, err = capsys.readouterr()
    assert "unfinished_dataset" not in out and "warning" not in err


def test_export_into_the_empty_working_folder(small, tmp_path, monkeypatch, capsys):
    """`--out .`: an existing empty folder that cannot be removed gets the export's entries; an interrupt while
    they move leaves it empty again, and nothing beside it."""
    from envisat_pose.pipelines.datasets import export

    here = tmp_path / "here"
    here.mkdir()
    monkeypatch.chdir(here)
    real_move, calls = shutil.move, []

    def move_then_interrupt(a, b):
        calls.append(real_move(a, b))
        if len(calls) == 2:
            raise KeyboardInterrupt

    with monkeypatch.context() as mp:
        mp.setattr(export.shutil, "move", move_then_interrupt)
        assert envisat_main(["dataset", "export", small["done"], "--format", "yolo-pose", "--out", ".",
                             "--quiet"]) == 130
    assert len(calls) == 2 and os.listdir(here) == [] and os.listdir(tmp_path) == ["here"]
    assert envisat_main(["dataset", "export", small["done"], "--format", "yolo-pose", "--out", ".", "--quiet"]) == 0
    assert "wrote yolo-pose export" in capsys.readouterr().out
    assert sorted(os.listdir(here)) == ["README.md", "data.yaml", "export.json", "images", "labels"]
    assert f'path: "{here}"' in (here / "data.yaml").read_text() and os.listdir(tmp_path) == ["here"]


@pytest.mark.parametrize("flag, value, expected", [("--seed", "-1", "a non-negative integer seed below 2^63"),
                                                     ("--seed", str(2**63), "a non-negative integer seed"),
                                                     ("--val-fraction", "1.5", "a fraction in [0, 1)"),
                                                     ("--workers", "0", "at least 1 worker process")])
def test_a_bad_flag_is_one_line_naming_the_flag(small, tmp_path, capsys, flag, value, expected):
    """The export's config is built from flags alone: its errors name the flag typed, not the config field."""
    rc = envisat_main(["dataset", "export", small["done"], "--format", "coco", "--out", str(tmp_path / "o"),
                       flag, value, "--quiet"])
    assert rc == 2 and f"{flag} {value}: expected {expected}" in one_error_line(capsys)
    assert os.listdir(tmp_path) == []


def test_the_target_file_to_give_is_named_and_another_target_file_is_refused_by_its_sha256(tmp_path, monkeypatch,
                                                                                            capsys):
    """A dataset of a target named by a relative path, exported from another folder: the line says to give the
    file with --target; another target's file given there is refused by its sha256, before the dataset's generate
    config is built on it (its sizes would follow that other target)."""
    from envisat_pose.geometry import model_path

    models = os.path.dirname(model_path())
    (tmp_path / "home" / "mytgt").mkdir(parents=True)
    shutil.copy(os.path.join(models, "cubesat_3u.xml"), tmp_path / "home" / "mytgt" / "cs.xml")
    monkeypatch.chdir(tmp_path / "home")
    src = str(tmp_path / "cs")
    run_generate(from_dict(GenerateConfig, {**SMALL, "num_images": 2, "target": "mytgt/cs.xml"}), src)
    monkeypatch.chdir(tmp_path)
    export = ["dataset", "export", src, "--format", "coco", "--quiet", "--out"]
    assert envisat_main(export + ["a"]) == 2
    line = one_error_line(capsys)
    assert "its target file 'mytgt/cs.xml'" in line and "give that file with --target" in line
    assert envisat_main(export + ["b", "--target", os.path.join(models, "upper_stage.xml")]) == 2
    line = one_error_line(capsys)
    assert "--target" in line and f"not the target file of the dataset {src!r}" in line and "'cubesat_3u'" in line
    assert "range" not in line  # not a check of the generate config built on the upper stage
    assert envisat_main(export + ["c", "--target", os.path.join("home", "mytgt", "cs.xml")]) == 0
    assert sorted(os.listdir(tmp_path)) == ["c", "cs", "home"]


def test_a_dataset_without_masks_says_its_boxes_come_from_the_projected_model(small, tmp_path):
    """write_mask = false: COCO's and YOLO-pose's boxes are the projected model's, COCO's area the box's w x h;
    the READMEs and export.json say so (a dataset with masks: the mask)."""
    from envisat_pose.pipelines.datasets.export import ExportConfig, export_dataset

    src = str(tmp_path / "nomask")
    run_generate(from_dict(GenerateConfig, {**SMALL, "num_images": 2, "write_mask": False}), src)
    for fmt in ("coco", "yolo-pose"):
        out = export_dataset(src, str(tmp_path / fmt), ExportConfig(fmt, val_fraction=0.0), progress=False).out_dir
        readme = open(os.path.join(out, "README.md")).read()
        assert "the projected model" in readme and "write_mask = false" in readme and "the target's mask" not in readme
        assert json.load(open(os.path.join(out, "export.json")))["box_source"] == "projected_model"
    coco = json.load(open(os.path.join(tmp_path, "coco", "annotations", "keypoints_train.json")))
    assert coco["annotations"] and all(a["area"] == a["bbox"][2] * a["bbox"][3] for a in coco["annotations"])
    assert "area: the box's w x h" in open(os.path.join(tmp_path, "coco", "README.md")).read()
    out = export_dataset(small["done"], str(tmp_path / "masked"), ExportConfig("coco"), progress=False).out_dir
    assert "the target's mask" in open(os.path.join(out, "README.md")).read()
    assert json.load(open(os.path.join(out, "export.json")))["box_source"] == "mask"


@pytest.mark.parametrize("fraction, empty", [("0.99", "training"), ("0.05", "validation")])
def test_a_val_fraction_that_leaves_a_split_empty_is_one_line(small, tmp_path, capsys, fraction, empty):
    rc = envisat_main(["dataset", "export", small["done"], "--format", "yolo-pose", "--out", str(tmp_path / "o"),
                       "--val-fraction", fraction, "--quiet"])
    line = one_error_line(capsys)
    assert rc == 2 and f"--val-fraction {fraction}:" in line and f"leaves the {empty} split empty" in line
    assert os.listdir(tmp_path) == []


def test_a_val_fraction_for_bop_is_one_line(small, tmp_path, capsys):
    """BOP has one split (train_pbr): a fraction asked for wrote every image there without a word."""
    rc = envisat_main(["dataset", "export", small["done"], "--format", "bop", "--out", str(tmp_path / "o"),
                       "--val-fraction", "0.5", "--quiet"])
    line = one_error_line(capsys)
    assert rc == 2 and "--val-fraction 0.5: bop exports one split, train_pbr" in line, line
    assert os.listdir(tmp_path) == []


def _label_shard(path, visible_lists, named=True):
    """A shard of samples whose labels hold what dataset_stats reads, one per list of visible flags; named: the
    labels name their keypoints (another target's), else ENVISAT's corners_px."""
    import io
    import tarfile

    with tarfile.open(path, "w") as tar:
        for i, visible in enumerate(visible_lists):
            points = {"keypoint_names": [f"k{j}" for j in range(len(visible))], "keypoints_px": [[1.0, 2.0]] *
                      len(visible)} if named else {"corners_px": [[1.0, 2.0]] * len(visible)}
            label = {"t_cam_from_target_m": [0.0, 0.0, 5.0], "visible": visible, "in_frame": [True] * len(visible),
                     "scene": {}, "corruption": {"model": "none"}, **points}
            for suffix, data in (("json", json.dumps(label).encode()), ("png", b"not read")):
                info = tarfile.TarInfo(f"{i:09d}.{suffix}")
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))
    return str(path)


def test_the_visible_keypoints_histogram_has_a_bin_for_each_count_of_the_targets_keypoints(tmp_path):
    from envisat_pose.datagen.dataset import dataset_stats

    twelve = _label_shard(tmp_path / "cubesat.tar", [[False] * 12, [True] * 3 + [False] * 9])
    assert dataset_stats([twelve])["visible_keypoints_histogram"] == [1, 0, 0, 1] + [0] * 9  # 0 to 12 visible
    eight = _label_shard(tmp_path / "envisat.tar", [[True] * 8], named=False)
    assert dataset_stats([eight])["visible_keypoints_histogram"] == [0] * 8 + [1]


def test_the_statistics_name_keypoints_and_keep_the_corner_keys_for_envisats_labels_only(tmp_path):
    """Another target's labels have keypoints, not corners: its statistics have no corner-named key and say
    "keypoints (of K)"; ENVISAT's keep the old corner keys beside (the same values), said to be deprecated."""
    from envisat_pose.app.dataset import stats_lines
    from envisat_pose.datagen.dataset import dataset_stats

    other = dataset_stats([_label_shard(tmp_path / "o.tar", [[True] * 12, [True] * 2 + [False] * 10])])
    assert other["keypoints_noun"] == "keypoints" and other["in_frame_keypoints_mean"] == 12.0
    assert not [key for key in other if "corner" in key], other
    assert stats_lines(other) == ["keypoints (of 12) per image: 7.00 visible, 12.00 in frame, on average"]
    envisat = dataset_stats([_label_shard(tmp_path / "e.tar", [[True] * 8, [True] * 4 + [False] * 4], named=False)])
    assert envisat["keypoints_noun"] == "corners"
    assert envisat["visible_corners_histogram"] == envisat["visible_keypoints_histogram"] == [0] * 4 + [1, 0, 0, 0, 1]
    assert envisat["in_frame_corners_mean"] == envisat["in_frame_keypoints_mean"] == 8.0
    first, deprecated = stats_lines(envisat)
    assert first == "corners (of 8) per image: 6.00 visible, 8.00 in frame, on average"
    assert deprecated.startswith("deprecated: visible_corners_histogram, in_frame_corners_mean, the same as "
                                 "visible_keypoints_histogram, in_frame_keypoints_mean"), deprecated
    assert stats_lines(dataset_stats([])) == []


def test_inspect_prints_another_targets_keypoints_and_envisats_corners(small, tmp_path, capsys):
    cfg = from_dict(GenerateConfig, {**SMALL, "num_images": 2, "target": "models/cubesat_3u.xml"})
    run_generate(cfg, str(tmp_path / "cubesat"))
    for folder, said, unsaid in ((str(tmp_path / "cubesat"), "keypoints (of ", "corner"),
                                 (small["done"], "corners (of 8) per image", None)):
        assert envisat_main(["dataset", "inspect", folder, "--montage", str(tmp_path / "m.png"), "--count", "1"]) == 0
        out = capsys.readouterr().out
        assert said in out and (unsaid is None or unsaid not in out), out
    assert "deprecated: visible_corners_histogram" in out


@pytest.mark.parametrize("count", ["0", "-3"])
def test_inspect_refuses_a_montage_of_no_images(small, tmp_path, capsys, count):
    rc = envisat_main(["dataset", "inspect", small["done"], "--montage", str(tmp_path / "m.png"), "--count", count])
    assert rc == 2 and f"--count {count}: expected at least 1" in one_error_line(capsys)
    assert os.listdir(tmp_path) == []


def test_verify_reports_a_shard_the_manifest_does_not_list(small, tmp_path, capsys):
    out = tmp_path / "ds"
    shutil.copytree(small["done"], out)
    assert envisat_main(["dataset", "verify", str(out)]) == 0
    shutil.copy(out / "shard-000000.tar", out / "shard-000007.tar")  # a copied-in file: a glob would read it
    capsys.readouterr()
    assert envisat_main(["dataset", "verify", str(out)]) == 1
    assert "PROBLEM shard-000007.tar: not part of the dataset" in capsys.readouterr().out


def test_generate_refuses_a_folder_of_files_without_a_manifest(small, tmp_path, capsys):
    """Shards without a manifest are not a dataset to resume: generate there would overwrite them."""
    out = tmp_path / "shards"
    out.mkdir()
    shutil.copy(os.path.join(small["done"], "shard-000000.tar"), out / "shard-000000.tar")
    before = (out / "shard-000000.tar").read_bytes()
    rc = envisat_main(["generate", "--out", str(out), "--num-images", "2", "--resolution", "64", "--quiet"])
    line = one_error_line(capsys)
    assert rc == 2 and "shard-000000.tar" in line and "no manifest.json" in line
    assert os.listdir(out) == ["shard-000000.tar"] and (out / "shard-000000.tar").read_bytes() == before


def test_inspect_as_a_python_call_is_the_verb(small, tmp_path, capsys):
    import pathlib

    import cv2

    from envisat_pose.config import InputError
    from envisat_pose.datagen.dataset import dataset_stats
    from envisat_pose.pipelines.datasets.inspect import inspect_dataset

    result = inspect_dataset(pathlib.Path(small["done"]), tmp_path / "m.png", count=3)
    assert result["montage"] == str(tmp_path / "m.png") and result["montage_images"] == 3 and result["rrd"] is None
    assert cv2.imread(result["montage"]) is not None
    assert {k: v for k, v in result.items() if k not in ("montage", "montage_images", "rrd")} == \
        dataset_stats(small["done"])  # recomputed here from the shards
    assert envisat_main(["dataset", "inspect", small["done"], "--montage", str(tmp_path / "v.png"), "--count", "3"]) == 0
    out = capsys.readouterr().out
    assert json.loads(out[:out.rindex("}") + 1]) == dataset_stats(small["done"])
    for kwargs, message in (({"count": 0}, "count 0: expected at least 1"),
                            ({"rrd": str(tmp_path / "x.txt")}, r"rrd .*expected a path ending in \.rrd")):
        with pytest.raises(InputError, match=message):
            inspect_dataset(small["done"], tmp_path / "n.png", **kwargs)
    with pytest.raises(InputError, match="^src .*: no such folder"):  # the argument's own name
        inspect_dataset(str(tmp_path / "missing"), tmp_path / "n.png")
    assert not (tmp_path / "n.png").exists()


def test_inspect_refuses_a_users_montage_png_at_its_default_path_and_replaces_its_own(small, tmp_path, capsys):
    """`dataset inspect DIR` writes DIR/montage.png: it replaced a user's file of that name unasked. Its own montage
    carries a PNG mark (png_marks) and is replaced on a rerun; another file there is refused in one line."""
    from envisat_pose.png_marks import png_job

    ds = str(tmp_path / "ds")
    shutil.copytree(small["done"], ds)
    assert envisat_main(["dataset", "inspect", ds, "--count", "1"]) == 0
    assert png_job(os.path.join(ds, "montage.png")) == "dataset inspect"
    assert envisat_main(["dataset", "inspect", ds, "--count", "2"]) == 0  # its own: replaced
    mine = b"\x89PNG\r\n\x1a\n the user's own montage"
    with open(os.path.join(ds, "montage.png"), "wb") as fh:
        fh.write(mine)
    capsys.readouterr()
    assert envisat_main(["dataset", "inspect", ds, "--count", "1"]) == 2
    line = one_error_line(capsys)
    assert f"--montage {os.path.join(ds, 'montage.png')!r} (the default) holds a file no `envisat dataset " \
           "inspect` wrote" in line and "give another --montage path" in line, line
    with open(os.path.join(ds, "montage.png"), "rb") as fh:
        assert fh.read() == mine


def test_an_export_folder_gets_the_users_usual_mode(small, tmp_path):
    """The export is staged in a temporary folder (mkdtemp: 0700) renamed to --out: the folder gets the mode the
    umask gives a new folder, as every other output does, so others can read what the user shares."""
    import stat

    from envisat_pose.pipelines.datasets.export import ExportConfig, export_dataset

    for umask, expected in ((0o022, 0o755), (0o027, 0o750)):
        old = os.umask(umask)
        try:
            out = tmp_path / f"ex-{umask:o}"
            export_dataset(small["done"], out, ExportConfig("coco", val_fraction=0.0))
        finally:
            os.umask(old)
        assert stat.S_IMODE(os.stat(out).st_mode) == expected


def test_a_dataset_resumes_with_its_target_file_named_from_another_folder(tmp_path, monkeypatch):
    """The target file is the input, not the text naming it: a rerun from another folder, or with the absolute
    path, finds nothing to do; another file under the same name is another config."""
    from envisat_pose.config import InputError
    from envisat_pose.target import resolve_target_path

    (tmp_path / "work" / "mine").mkdir(parents=True)
    shutil.copy(resolve_target_path("models/upper_stage.xml"), tmp_path / "work" / "mine" / "t.xml")
    cfg = {**SMALL, "num_images": 2, "shard_size": 1}
    monkeypatch.chdir(tmp_path / "work")
    run_generate(from_dict(GenerateConfig, {**cfg, "target": "mine/t.xml"}), "ds")
    before = {f: os.stat(tmp_path / "work" / "ds" / f).st_mtime_ns for f in os.listdir(tmp_path / "work" / "ds")}
    monkeypatch.chdir(tmp_path)
    again = run_generate(from_dict(GenerateConfig, {**cfg, "target": "work/mine/t.xml"}), "work/ds")
    assert again["complete"] and all(os.stat(tmp_path / "work" / "ds" / f).st_mtime_ns == t
                                     for f, t in before.items() if f.endswith(".tar"))
    shutil.copy(resolve_target_path("models/cubesat_3u.xml"), tmp_path / "work" / "mine" / "t.xml")
    with pytest.raises(InputError, match="another config or seed"):
        run_generate(from_dict(GenerateConfig, {**cfg, "target": "work/mine/t.xml"}), "work/ds")


def test_inspect_rrd_of_a_dataset_whose_target_path_is_not_found_from_here(tmp_path, monkeypatch):
    """The recording draws the dataset's target: a recorded path not found from here is one error before any
    output (the montage included), and the file given again (`target`) is taken when its sha256 is the recorded
    one."""
    from envisat_pose.config import InputError
    from envisat_pose.pipelines.datasets.inspect import inspect_dataset
    from envisat_pose.target import resolve_target_path

    (tmp_path / "work" / "mine").mkdir(parents=True)
    shutil.copy(resolve_target_path("models/upper_stage.xml"), tmp_path / "work" / "mine" / "t.xml")
    monkeypatch.chdir(tmp_path / "work")
    run_generate(from_dict(GenerateConfig, {**SMALL, "num_images": 2, "shard_size": 2, "target": "mine/t.xml"}), "ds")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError, match=r"its target file 'mine/t.xml' .* is not found from here: give that file"):
        inspect_dataset("work/ds", "m.png", count=2, rrd="s.rrd")
    assert not (tmp_path / "m.png").exists() and not (tmp_path / "s.rrd").exists()
    result = inspect_dataset("work/ds", "m.png", count=2, rrd="s.rrd", target="work/mine/t.xml")
    assert result["montage_images"] == 2 and (tmp_path / "s.rrd").stat().st_size > 0
    with pytest.raises(InputError, match="not the target file of the dataset 'work/ds'"):
        inspect_dataset("work/ds", "n.png", count=2, rrd="t.rrd", target=resolve_target_path("models/cubesat_3u.xml"))


def test_the_export_workers_share_the_cores_among_the_processes_that_start(small, tmp_path, monkeypatch, machine):
    """8 workers over 3 shards on 8 cores: 3 processes start, 2 threads each (8 // 3), not 8 // 8."""
    from envisat_pose.pipelines.datasets import export
    from envisat_pose.pools import RunnerConfig, run_tasks

    runners = []

    def inline(fn, tasks, runner):
        runners.append(runner)
        return run_tasks(fn, tasks, RunnerConfig("inline"))

    monkeypatch.setattr(export, "run_tasks", inline)
    machine(8)
    export.export_dataset(small["done"], str(tmp_path / "coco"), export.ExportConfig(fmt="coco"), workers=8)
    assert runners[0].workers == 3
    assert runners[0].env == {"OMP_NUM_THREADS": "2", "OPENCV_FOR_THREADS_NUM": "2"}


def _indented_block(text: str, heading: str) -> list[str]:
    """The README's indented command lines after `heading`, their indent removed."""
    lines = text[text.index(heading):].splitlines()[1:]
    return [ln[4:] for ln in lines[:next((i for i, ln in enumerate(lines) if not ln.startswith("    ")), len(lines))]]


def test_the_readme_commands_run_on_a_folder_with_a_space_and_a_quote_and_no_validation_split(small, tmp_path):
    """The README's commands name the export's files as their tools read them: the pycocotools lines, run as they
    stand, open a file the export holds (keypoints_train.json where --val-fraction 0 wrote no keypoints_val.json),
    and the yolo command, split as a shell splits it, passes data.yaml's path whole."""
    import shlex

    from envisat_pose.pipelines.datasets.export import ExportConfig, export_dataset

    parent = tmp_path / "my data's exports"
    coco = export_dataset(small["done"], str(parent / "coco set"), ExportConfig("coco", val_fraction=0.0),
                          progress=False).out_dir
    text = open(os.path.join(coco, "README.md"), encoding="utf-8").read()
    code = "\n".join(_indented_block(text, "## Run it")[:3])  # the imports and gt = COCO(...)
    scope: dict = {}
    exec(compile(code, "README.md", "exec"), scope)
    assert len(scope["gt"].dataset["images"]) == 6
    yolo = export_dataset(small["done"], str(parent / "yolo set"), ExportConfig("yolo-pose"), progress=False).out_dir
    text = open(os.path.join(yolo, "README.md"), encoding="utf-8").read()
    words = shlex.split(_indented_block(text, "## Run it")[0])
    assert words[:3] == ["yolo", "pose", "train"] and words[3] == f"data={os.path.join(yolo, 'data.yaml')}"


def test_more_workers_than_the_cores_are_warned_of_once_and_the_verb_names_the_flag(small, tmp_path, machine,
                                                                                    monkeypatch, capsys):
    """`--workers 8` on 2 usable cores started 3 processes (one a shard) without a word; the default is the cores."""
    from envisat_pose.pipelines.datasets import export

    machine(64, affinity=2)
    monkeypatch.setattr(export, "_generate_config", lambda *a: (_ for _ in ()).throw(KeyboardInterrupt))
    with pytest.warns(UserWarning, match=r"^workers = 8: more processes than the 2 usable cores") as record, \
            pytest.raises(KeyboardInterrupt):
        export.export_dataset(small["done"], str(tmp_path / "a"), export.ExportConfig(fmt="coco"), workers=8)
    assert len(record) == 1
    assert envisat_main(["dataset", "export", small["done"], "--format", "coco", "--out", str(tmp_path / "b"),
                         "--workers", "8", "--quiet"]) == 130
    assert capsys.readouterr().err.splitlines()[0] == ("envisat dataset: warning: --workers 8: more processes than the "
                                                      "2 usable cores (they share them); the job runs as asked")
    capsys.readouterr()
    assert envisat_main(["dataset", "export", small["done"], "--format", "coco", "--out", str(tmp_path / "c"),
                         "--quiet"]) == 130  # the default: the usable cores
    assert "warning" not in capsys.readouterr().err


@pytest.mark.parametrize("made", [False, True])
def test_an_out_inside_the_dataset_is_refused_before_any_work(small, tmp_path, capsys, made):
    """`--out SRC/sub` (made empty beforehand or not): one line naming --out, that it lies inside SRC, and the
    dataset; nothing written into the dataset's folder (an export among its shards, which verify then sees)."""
    src = tmp_path / "ds"
    shutil.copytree(small["done"], src)
    if made:
        (src / "sub").mkdir()
    before = sorted(os.listdir(src))
    rc = envisat_main(["dataset", "export", str(src), "--format", "coco", "--out", str(src / "sub"), "--quiet"])
    assert rc == 2
    line = one_error_line(capsys)
    assert "error: --out" in line and "lies inside SRC" in line and str(src) in line, line
    assert sorted(os.listdir(src)) == before and (not made or os.listdir(src / "sub") == [])
