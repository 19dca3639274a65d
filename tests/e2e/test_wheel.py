"""`pip install .` puts one import package, `fluxcal`, into site-packages (issue 39): no top-level `service` or
`drivers` that another project's names could shadow or be shadowed by; `fluxcal --help` and the Python API work from
that install alone. The wheel is built from this checkout and installed into a fresh virtual environment that
borrows the test environment's dependencies (numpy, scipy, zenoh ...) through a path file, never its fluxcal."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(the wheel, the fresh environment's bin folder)."""
    tmp = tmp_path_factory.mktemp("wheel")
    # built from a copy: setuptools leaves build/ and the egg-info in the tree it builds
    src = shutil.copytree(ROOT, tmp / "src", ignore=shutil.ignore_patterns(".git", ".venv", "build", "*.egg-info",
                                                                       "__pycache__", ".pytest_cache", "state", "out", "live"))
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w",
                    str(tmp / "dist"), str(src)], check=True, cwd=tmp, capture_output=True)
    wheel = next((tmp / "dist").glob("fluxcal-*.whl"))
    subprocess.run([sys.executable, "-m", "venv", str(tmp / "fresh")], check=True)
    bin_dir = tmp / "fresh" / "bin"
    subprocess.run([str(bin_dir / "pip"), "install", "-q", "--no-deps", "--no-index", str(wheel)], check=True,
                   capture_output=True)
    fresh_site = next((tmp / "fresh" / "lib").glob("python3*/site-packages"))
    # the dependencies from the test environment's site-packages (a path file adds the folder; the path files in it,
    # the editable install's finder among them, are not run)
    (fresh_site / "zz-test-dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    return wheel, bin_dir, fresh_site


def test_the_wheel_holds_one_package_fluxcal(installed):
    wheel, _, site = installed
    tops = {name.split("/")[0] for name in zipfile.ZipFile(wheel).namelist()}
    assert tops == {"fluxcal", f"{wheel.name.split('-')[0]}-{wheel.name.split('-')[1]}.dist-info"}, tops
    assert {p.name for p in site.iterdir() if p.is_dir() and not p.name.endswith(".dist-info")
            and p.name != "__pycache__"} >= {"fluxcal"}
    assert not (site / "service").exists() and not (site / "drivers").exists()
    assert (site / "fluxcal" / "service" / "wiring" / "dashboard" / "static" / "app.js").is_file()
    assert (site / "fluxcal" / "py.typed").is_file()
    # pyproject.toml lists the packages by name: a new folder left out of the list would be missing here
    held = set(zipfile.ZipFile(wheel).namelist())
    for folder, package in (("fluxcal", "fluxcal"), ("service", "fluxcal/service"), ("drivers", "fluxcal/drivers")):
        for module in (ROOT / folder).rglob("*.py"):
            assert f"{package}/{module.relative_to(ROOT / folder).as_posix()}" in held, module


def test_the_installed_command_and_api_work_from_the_install_alone(installed, tmp_path):
    _, bin_dir, site = installed
    env = {**os.environ, "PYTHONPATH": ""}
    out = subprocess.run([str(bin_dir / "fluxcal"), "--help"], capture_output=True, text=True, cwd=tmp_path, env=env)
    assert out.returncode == 0 and "fit" in out.stdout and "diagnose" in out.stdout, out.stderr
    code = ("import fluxcal, fluxcal.effects, fluxcal.recordings, fluxcal.bus; "
            "print(fluxcal.__file__); import importlib.util as u; "
            "print(u.find_spec('service'), u.find_spec('drivers'))")
    out = subprocess.run([str(bin_dir / "python"), "-c", code], capture_output=True, text=True, cwd=tmp_path, env=env)
    assert out.returncode == 0, out.stderr
    where, missing = out.stdout.splitlines()
    assert where.startswith(str(site)) and missing == "None None", out.stdout
    sim = tmp_path / "grad.csv"
    out = subprocess.run([str(bin_dir / "fluxcal"), "simulate", "--out", str(sim)], capture_output=True, text=True,
                         cwd=tmp_path, env=env)
    assert out.returncode == 0 and sim.is_file(), out.stderr
    out = subprocess.run([str(bin_dir / "python"), "-c", f"import fluxcal; print(round(fluxcal.fit({str(sim)!r}).rms_nT, 1))"],
                         capture_output=True, text=True, cwd=tmp_path, env=env)
    assert out.returncode == 0 and float(out.stdout) < 5.0, out.stderr
