"""The gravity plugin is found by a plain `import mujoco` (entry point) and rejects bad attributes."""

import os
import subprocess
import sys

import mujoco
import numpy as np
import pytest

from envisat_pose.datagen.scenario import scenario_config
from envisat_pose.datagen.sim import model_xml
from envisat_pose.geometry import model_path


def test_plain_import_mujoco_finds_the_plugin(tmp_path):
    code = (
        "import mujoco, sys\n"
        f"m = mujoco.MjModel.from_xml_path({model_path()!r})\n"
        "assert m.nplugin == 1 and m.body_plugin[m.body('target').id] == 0\n"
        "assert 'envisat_pose.datagen.sim' not in sys.modules  # only the entry point ran\n"
        "print('ok')\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "ok"


def test_plugin_force_equals_the_differential_gravity():
    """One evaluation of qfrc_passive against the formula, at an off-axis position."""
    cfg = scenario_config()
    model = mujoco.MjModel.from_xml_string(model_xml(cfg))
    data = mujoco.MjData(model)
    data.qpos[0:3] = [12.0, -40.0, 7.0]
    data.time = 1234.5
    mujoco.mj_forward(model, data)
    # independent chaser position: Kepler solved here with scipy's root finder
    from scipy.optimize import brentq
    from scipy.spatial.transform import Rotation

    o = cfg.orbit
    n = np.sqrt(o.mu_m3_s2 / o.a_m**3)
    nu0 = np.radians(o.nu0_deg)
    E0 = 2 * np.arctan(np.sqrt((1 - o.e) / (1 + o.e)) * np.tan(nu0 / 2))
    M = E0 - o.e * np.sin(E0) + n * data.time
    E = brentq(lambda E: E - o.e * np.sin(E) - M, M - 1, M + 1, xtol=1e-15)
    r_pf = o.a_m * np.array([np.cos(E) - o.e, np.sqrt(1 - o.e**2) * np.sin(E), 0])
    r_c = Rotation.from_euler("ZXZ", [o.raan_deg, o.i_deg, o.argp_deg], degrees=True).as_matrix() @ r_pf
    R = r_c + data.qpos[0:3]
    acc = -o.mu_m3_s2 * R / np.linalg.norm(R) ** 3 + o.mu_m3_s2 * r_c / np.linalg.norm(r_c) ** 3
    np.testing.assert_allclose(data.qfrc_passive[0:3] / model.body_mass[model.body('target').id], acc, rtol=1e-9, atol=1e-15)
    assert np.linalg.norm(acc) > 1e-5  # ~ n^2 |rho|, a real force


def test_bad_plugin_attribute_is_refused():
    xml = model_xml(scenario_config()).replace('key="e" value="0.001"', 'key="e" value="1.5"')
    with pytest.raises(ValueError, match=r"0 <= e < 1"):
        mujoco.MjModel.from_xml_string(xml)


@pytest.mark.parametrize("value", ["0.001abc", "0.001 0.002", "0,001", "abc"])
def test_attribute_with_trailing_garbage_is_refused(value):
    """Only a complete number is an attribute: strtod alone would read '0.001abc' as 0.001."""
    xml = model_xml(scenario_config()).replace('key="e" value="0.001"', f'key="e" value="{value}"')
    with pytest.raises(ValueError, match=r"attribute 'e'.*not a finite number"):
        mujoco.MjData(mujoco.MjModel.from_xml_string(xml))


def test_attribute_with_surrounding_whitespace_is_accepted():
    base = model_xml(scenario_config())
    xml = base.replace('key="e" value="0.001"', 'key="e" value=" 0.001 \t"')
    for text in (base, xml):
        model = mujoco.MjModel.from_xml_string(text)
        data = mujoco.MjData(model)
        data.qpos[0:3] = [12.0, -40.0, 7.0]
        mujoco.mj_forward(model, data)
        if text is base:
            ref = data.qfrc_passive[0:3].copy()
    np.testing.assert_array_equal(data.qfrc_passive[0:3], ref)


def comma_locale(tmp_path) -> tuple[str, str] | None:
    """(LOCPATH, name) of a comma-decimal locale built here with localedef, or None where that cannot be done."""
    import shutil

    if shutil.which("localedef") is None:
        return None
    out = tmp_path / "locales"
    out.mkdir()
    subprocess.run(["localedef", "-i", "de_DE", "-f", "UTF-8", str(out / "de_DE.UTF-8")],
                          capture_output=True, text=True)
    if not (out / "de_DE.UTF-8").exists():
        return None
    return str(out), "de_DE.UTF-8"


def test_attributes_are_read_the_same_under_a_comma_decimal_locale(tmp_path):
    """strtod follows LC_NUMERIC: under de_DE it reads '0.001' as 0 and '98.4' as 98, a different orbit. The
    plugin must give the same force whatever the locale. Runs in a subprocess with a locale built by localedef."""
    found = comma_locale(tmp_path)
    if found is None:
        pytest.skip("no comma-decimal locale: localedef or the de_DE locale source is missing on this machine")
    locpath, name = found
    code = (
        "import locale, sys\n"
        "import mujoco, numpy as np\n"
        "from envisat_pose.datagen.scenario import scenario_config\n"
        "from envisat_pose.datagen.sim import model_xml\n"
        "xml = model_xml(scenario_config())\n"
        "def force():\n"
        "    m = mujoco.MjModel.from_xml_string(xml); d = mujoco.MjData(m)\n"
        "    d.qpos[0:3] = [12.0, -40.0, 7.0]; d.time = 1234.5; mujoco.mj_forward(m, d)\n"
        "    return d.qfrc_passive[0:3].copy()\n"
        "ref = force()\n"
        f"locale.setlocale(locale.LC_NUMERIC, {name!r})\n"
        "assert locale.localeconv()['decimal_point'] == ',', locale.localeconv()\n"
        "print(repr(ref.tolist())); print(repr(force().tolist()))\n"
    )
    env = dict(os.environ, LOCPATH=locpath)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    ref, under_comma = (np.array(eval(line)) for line in proc.stdout.strip().splitlines())
    np.testing.assert_array_equal(under_comma, ref)
