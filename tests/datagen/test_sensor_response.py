"""The space camera's response (datagen/sensor.py step 9): the 8-bit output stored through the sRGB curve or a
gamma after optics and sensor, checked against the curves' closed forms on the linear camera's own output (same
parameters, same noise seed); the factory's draw records it in the label only when it is not linear."""

import numpy as np
import pytest

from envisat_pose.config import to_dict
from envisat_pose.datagen.generate_config import SensorConfig
from envisat_pose.datagen.sensor import apply_sensor, draw_sensor


def params(response: str) -> dict:
    cfg = to_dict(SensorConfig(psf="gaussian", psf_sigma_px_1024=(1.5, 1.5), response=response))
    return draw_sensor(cfg, 256, 300.0, 10.0, 30.0, np.random.default_rng(480))


@pytest.fixture(scope="module")
def clean():
    img = np.zeros((256, 256), np.uint8)
    img[80:180, 60:200] = 170
    return img


@pytest.mark.parametrize("response, encode", [
    ("srgb", lambda v: np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)),
    ("gamma 2.2", lambda v: v ** (1 / 2.2)),
])
def test_the_output_is_stored_through_the_response(clean, response, encode):
    lin, enc = params("linear"), params(response)
    assert "response" not in lin and enc["response"] == response
    assert {k: v for k, v in enc.items() if k != "response"} == lin  # the same camera, the same noise
    out_lin, out_enc = apply_sensor(clean, lin), apply_sensor(clean, enc)
    expected = np.rint(255.0 * encode(out_lin / 255.0)).astype(np.uint8)
    assert np.array_equal(out_enc, expected)
    assert out_enc[130, 130] > out_lin[130, 130]  # a mid grey stored brighter


def test_a_response_that_is_none_is_refused_by_name():
    with pytest.raises(Exception, match="response"):
        SensorConfig(response="log").validate()
