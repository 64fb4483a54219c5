"""An install without pyrealsense2 (macOS, Linux aarch64: PyPI has no wheel there): the simulated rig,
offline calibration and the report work; the RealSense rigs say how to install it. The machine without
it is emulated by a sitecustomize that makes `import pyrealsense2` fail as on such a machine."""

import subprocess
import sys
import tomllib

import pytest
from packaging.requirements import Requirement

from _station_helpers import REPO, popen_procam, run_procam

HIDE = "import sys\nsys.modules['pyrealsense2'] = None  # `import pyrealsense2` raises ModuleNotFoundError\n"


@pytest.fixture
def no_realsense(tmp_path):
    d = tmp_path / "site"
    d.mkdir()
    (d / "sitecustomize.py").write_text(HIDE)
    return {"PYTHONPATH": f"{d}:{REPO}"}


def _requirements(extra=None) -> list[Requirement]:
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    deps = project["dependencies"] if extra is None else project["optional-dependencies"][extra]
    return [Requirement(r) for r in deps]


@pytest.mark.parametrize("platform, machine, wanted", [
    ("linux", "x86_64", True), ("win32", "AMD64", True), ("linux", "aarch64", False), ("darwin", "arm64", False),
    ("darwin", "x86_64", False)])
def test_pyrealsense2_is_required_only_where_pypi_has_a_wheel(platform, machine, wanted):
    (rs,) = [r for r in _requirements() if r.name == "pyrealsense2"]
    env = {"sys_platform": platform, "platform_machine": machine}
    assert rs.marker is not None and rs.marker.evaluate(env) is wanted
    assert [r.name for r in _requirements("realsense")] == ["pyrealsense2"]  # the extra names it everywhere


@pytest.mark.parametrize("rig", ["realsense", "sim-realsense"])
def test_a_realsense_rig_without_pyrealsense2_says_how_to_install_it(no_realsense, tmp_path, rig):
    out = tmp_path / "s"
    r = run_procam("session", "--rig", rig, "--board", "8x6:DICT_4X4_50:50:30", "--auto", "--out", str(out),
                   env_extra=no_realsense, timeout=300)
    assert r.returncode == 2, r.stdout + r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in r.stderr
    assert "pip install 'procam-station[realsense]'" in lines[0] and "--rig sim" in lines[0]


def test_without_pyrealsense2_offline_calibration_and_the_report_import(no_realsense):
    code = ("import sys, app.cli, app.commands.calibrate, app.commands.report, app.report.page, calib.pipeline, "
            "drivers.factory, drivers.sim.rig; assert sys.modules['pyrealsense2'] is None")
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, env={**no_realsense, "PATH": "/usr/bin:/bin"},
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr


def test_without_pyrealsense2_the_simulated_session_runs(no_realsense, tmp_path):
    """The README's main job starts and captures (its end, the calibration, is offline and imports
    nothing of librealsense: the test above)."""
    p = popen_procam("session", "--rig", "sim", "--auto", "--poses-per-position", "1", "--mirror-captures", "2",
                     "--out", str(tmp_path / "s"), env_extra=no_realsense)
    seen = []
    try:
        for line in p.stdout:
            seen.append(line)
            if "captured mrv0000" in line:
                break
    finally:
        p.terminate()
        p.wait(60)
    assert any("rig check: camera ok" in s for s in seen), "".join(seen)
    assert any("captured mrv0000" in s for s in seen), "".join(seen)
    assert (tmp_path / "s" / "session.json").is_file()
