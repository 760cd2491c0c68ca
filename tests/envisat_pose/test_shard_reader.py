"""The core's check of a dataset's shards (envisat_pose/shard_reader.py: checked_shards) and its reader's one-line
errors: shards written by hand with a manifest as the factory writes it (name, count, sha256, bytes)."""

import hashlib
import io
import json
import os
import tarfile

import pytest

from envisat_pose.config import InputError
from envisat_pose.shard_reader import DamagedShardError, ShardReadError, checked_shards, read_shard


def write_dataset(folder, n_shards=3, per_shard=2, manifest=True):
    """n_shards tars of per_shard samples (key.json, key.png of filler bytes) and, if asked, their manifest."""
    folder.mkdir(parents=True, exist_ok=True)
    entries = []
    for s in range(n_shards):
        path = folder / f"shard-{s:06d}.tar"
        with tarfile.open(path, "w", format=tarfile.USTAR_FORMAT) as tar:
            for i in range(per_shard):
                for suffix, data in (("json", b'{"k": 1}'), ("png", bytes(range(256)) * 8)):
                    info = tarfile.TarInfo(f"{s * per_shard + i:09d}.{suffix}")
                    info.size = len(data)
                    tar.addfile(info, io.BytesIO(data))
        data = path.read_bytes()
        entries.append({"index": s, "name": path.name, "count": per_shard, "bytes": len(data),
                        "sha256": hashlib.sha256(data).hexdigest()})
    if manifest:
        (folder / "manifest.json").write_text(json.dumps({"format": "test", "shards": entries, "complete": True}))
    return [str(folder / e["name"]) for e in entries]


def truncate(path, keep=None):
    os.truncate(path, os.path.getsize(path) // 2 if keep is None else keep)


def flip(path, at=None):
    data = bytearray(open(path, "rb").read())
    data[len(data) // 3 if at is None else at] ^= 0x01
    open(path, "wb").write(bytes(data))


def test_a_sound_dataset_is_read_in_manifest_order(tmp_path):
    paths = write_dataset(tmp_path / "ds")
    assert checked_shards(str(tmp_path / "ds")) == (paths, [])


@pytest.mark.parametrize("damage, why", [(truncate, r"size \d+ bytes, manifest says \d+"),
                                         (flip, r"sha256 [0-9a-f]{12}\.\.\., manifest says [0-9a-f]{12}\.\.\."),
                                         (os.remove, "missing")])
def test_a_damaged_shard_is_one_line_naming_it_or_skipped(tmp_path, damage, why):
    paths = write_dataset(tmp_path / "ds")
    damage(paths[1])
    with pytest.raises(DamagedShardError, match=f"data_dir '.*ds': shard shard-000001.tar is damaged \\({why}\\)$"
                       ) as err:
        checked_shards(str(tmp_path / "ds"))
    assert "\n" not in str(err.value) and err.value.name == "shard-000001.tar"
    assert checked_shards(str(tmp_path / "ds"), skip_damaged=True) == ([paths[0], paths[2]], ["shard-000001.tar"])


def test_a_flip_the_tar_reader_would_not_see_is_refused(tmp_path):
    """A flipped bit in a tar's zero padding reads back fine: only the sha256 finds it."""
    paths = write_dataset(tmp_path / "ds", n_shards=1)
    flip(paths[0], at=os.path.getsize(paths[0]) - 10)
    assert len(list(read_shard(paths[0]))) == 2
    with pytest.raises(DamagedShardError, match="sha256"):
        checked_shards(str(tmp_path / "ds"))


def test_nothing_left_and_no_folder(tmp_path):
    paths = write_dataset(tmp_path / "ds", n_shards=1)
    truncate(paths[0])
    with pytest.raises(InputError, match=r"empty dataset .*1 damaged shard\(s\) skipped: shard-000000.tar"):
        checked_shards(str(tmp_path / "ds"), skip_damaged=True)
    with pytest.raises(InputError, match="--data '.*nope': no such folder"):
        checked_shards(str(tmp_path / "nope"), field="--data")


def test_without_a_manifest_every_tar_is_read_as_it_is(tmp_path):
    paths = write_dataset(tmp_path / "ds", manifest=False)
    truncate(paths[2])
    assert checked_shards(str(tmp_path / "ds")) == (paths, [])  # nothing to check against


def test_a_shard_failing_while_read_is_one_line_naming_it(tmp_path):
    paths = write_dataset(tmp_path / "ds", n_shards=1, per_shard=6)
    truncate(paths[0], 3000)  # inside the second member's data
    with pytest.raises(InputError, match="shard '.*shard-000000.tar' cannot be read") as err:
        list(read_shard(paths[0]))
    assert "\n" not in str(err.value)
    assert isinstance(err.value, tarfile.TarError)  # what the dataset verifier lists as a problem
    with pytest.raises(ShardReadError):
        list(read_shard(str(tmp_path / "ds" / "absent.tar")))


def test_the_one_shard_check_counts_the_samples_from_the_headers(tmp_path):
    """shard_problem's last step, for an entry without a sha256, walks the tar's headers: a sample without its
    image, another count than the manifest's, or a tar that cannot be walked is named; the walk agrees with
    tarfile on a pax or GNU tar. A matching sha256 ends the check (the bytes are the factory's finished shard)."""
    from envisat_pose.shard_reader import sample_suffixes, shard_problem, tar_member_names

    paths = write_dataset(tmp_path / "ds", n_shards=1, per_shard=3)
    entry = json.loads((tmp_path / "ds" / "manifest.json").read_text())["shards"][0]
    assert shard_problem(paths[0], entry) is None
    unhashed = {k: v for k, v in entry.items() if k != "sha256"}
    assert shard_problem(paths[0], unhashed) is None
    assert shard_problem(paths[0], {**unhashed, "count": 4}) == "3 samples, manifest says 4"
    lacking = tmp_path / "lacking.tar"
    with tarfile.open(lacking, "w", format=tarfile.USTAR_FORMAT) as tar:
        for name in ("000000000.json", "000000000.png", "000000001.json"):
            tar.addfile(tarfile.TarInfo(name), io.BytesIO(b""))
    assert shard_problem(str(lacking), {"count": 2}) == "sample 000000001 lacks png"
    truncate(paths[0], 3000)  # inside the second member's data; no size or sha256 to catch it first
    assert shard_problem(paths[0], {"count": 3}).startswith("unreadable tar (ReadError: ")
    for fmt in (tarfile.PAX_FORMAT, tarfile.GNU_FORMAT):  # long names: headers the quick walk leaves to tarfile
        path = tmp_path / f"{fmt}.tar"
        with tarfile.open(path, "w", format=fmt) as tar:
            for name in ("a" * 120 + "/000000000.json", "a" * 120 + "/000000000.png", "000000001.json"):
                tar.addfile(tarfile.TarInfo(name), io.BytesIO(b""))
        with tarfile.open(path) as tar:
            assert tar_member_names(str(path)) == tar.getnames()
        assert [k for k, _ in sample_suffixes(str(path))] == ["a" * 120 + "/000000000", "000000001"]


def test_the_dataset_manifest_reader_names_the_field_the_folder_and_the_entry(tmp_path):
    from envisat_pose.shard_reader import load_dataset_manifest

    write_dataset(tmp_path / "ds")
    assert [e["name"] for e in load_dataset_manifest(str(tmp_path / "ds"))["shards"]] == [
        "shard-000000.tar", "shard-000001.tar", "shard-000002.tar"]
    (tmp_path / "none").mkdir()
    assert load_dataset_manifest(str(tmp_path / "none"), required=False) is None
    with pytest.raises(InputError, match=r"^--data '.*none': no manifest.json: not a generated dataset$"):
        load_dataset_manifest(str(tmp_path / "none"), "--data")
    manifest = tmp_path / "ds" / "manifest.json"
    for record, why in (([], r"holds a JSON list, not an object"),
                        ({"shards": [{"name": "../x.tar", "count": 1}]},
                         r"not a dataset manifest \(shards\[0\].name = '../x.tar': expected a file name"),
                        ({"shards": [{"name": "a.tar", "count": -1}]},
                         r"shards\[0\].count = -1: expected a non-negative integer"),
                        ({"shards": [{"name": "a.tar"}]}, r"shards\[0\]: expected an entry with a name and a count"),
                        # a shard listed twice: inspect counted its samples twice, train and export read them twice
                        ({"shards": [{"name": "a.tar", "count": 1}, {"name": "b.tar", "count": 1},
                                     {"name": "a.tar", "count": 1}]},
                         r"shards\[2\].name = 'a.tar': listed twice \(also shards\[0\]\); expected each once")):
        manifest.write_text(json.dumps(record))
        with pytest.raises(InputError, match=f"^dataset '.*ds': .*{why}") as err:
            load_dataset_manifest(str(tmp_path / "ds"))
        assert "\n" not in str(err.value)
    manifest.write_text("{not json")
    with pytest.raises(InputError, match=r"dataset '.*ds': unreadable manifest.json \("):
        checked_shards(str(tmp_path / "ds"), field="dataset")


def test_a_progress_bars_total_is_the_manifests_count(tmp_path, monkeypatch):
    """sample_total: the samples the shard files hold by their manifest (counted here from the tars), at most
    `limit`, across folders and working folders; unknown (None) for shards no manifest lists."""
    from envisat_pose.shard_reader import sample_total

    a = write_dataset(tmp_path / "a", n_shards=3, per_shard=2)
    b = write_dataset(tmp_path / "b", n_shards=1, per_shard=5)
    held = sum(len([m for m in tarfile.open(p).getnames() if m.endswith(".json")]) for p in a + b)
    assert sample_total(a + b) == held == 11
    assert sample_total(a, limit=4) == 4 and sample_total(a[:1], limit=10) == 2
    monkeypatch.chdir(tmp_path)
    assert sample_total([os.path.join("a", os.path.basename(p)) for p in a]) == 6  # relative paths
    assert sample_total(write_dataset(tmp_path / "c", manifest=False)) is None
