"""`envisat generate` and `envisat dataset verify` agree on a dataset folder: a stray shard that verify reports is
refused by generate (not left behind under exit 0); a finished dataset on read-only media is 'nothing to do' with
nothing written; a damaged manifest is a problem verify finds (exit 1), not a usage error; the end line counts
'1 image in 1 shard'."""



from envisat_pose.app.generate import generate_line

FLAGS = ["--num-images", "2", "--shard-size", "1", "--resolution", "64", "--seed", "3", "--quiet"]


def test_the_end_line_counts_one_image_in_one_shard():
    entry = {"count": 1}
    one = {"shards": [entry]}
    assert generate_line(one, [entry], "d").startswith("wrote 1 image in 1 shard to d (")
    assert generate_line(one, [], "d") == "nothing to do: 1 image already there in 1 shard in d"
    two = {"shards": [{"count": 2}, entry]}
    assert generate_line(two, [entry], "d").startswith("wrote 1 image in 1 shard to d; 2 images already there (")
    assert generate_line({"shards": [{"count": 2}] * 2}, [], "d") == "nothing to do: 4 images already there in 2 shards in d"
