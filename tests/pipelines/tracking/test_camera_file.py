"""pipelines/tracking/camera_file.py: the camera TOML's response and PSF keys (issue 49) read as written, absent ones left
to the frames, and a bad value refused in one line that names the file, the key and what was expected."""

import pytest

from envisat_pose.camera_response import LINEAR, SRGB, Response
from envisat_pose.config import InputError
from envisat_pose.pipelines.tracking.camera_file import camera_from_intrinsics, read_camera_response

BASE = "fx = 600.0\nfy = 600.0\ncx = 255.5\ncy = 255.5\nwidth = 512\nheight = 512\n"


@pytest.mark.parametrize("text, expected", [
    ("", (None, None)),
    ('response = "srgb"\n', (SRGB, None)),
    ('response = "linear"\npsf_sigma_px = 1.2\n', (LINEAR, 1.2)),
    ("response = 2.4\npsf_sigma_px = 0\n", (Response("gamma", 2.4), 0.0)),
    ('response = "gamma 1.8"\n', (Response("gamma", 1.8), None)),
])
def test_the_response_and_psf_are_read(tmp_path, text, expected):
    path = tmp_path / "camera.toml"
    path.write_text(BASE + text)
    cam, remap = camera_from_intrinsics(str(path))  # the intrinsics still read; the new keys are known
    assert cam.width_px == 512 and remap is None
    assert read_camera_response(str(path)) == expected


@pytest.mark.parametrize("text, key", [('response = "log"\n', "response"), ("response = 9.0\n", "response"),
                                       ("psf_sigma_px = -1\n", "psf_sigma_px"),
                                       ('psf_sigma_px = "wide"\n', "psf_sigma_px")])
def test_a_bad_value_is_one_line_naming_the_key(tmp_path, text, key):
    path = tmp_path / "camera.toml"
    path.write_text(BASE + text)
    with pytest.raises(InputError) as err:
        camera_from_intrinsics(str(path))
    line = str(err.value)
    assert "\n" not in line and str(path) in line and key in line and "expected" in line
