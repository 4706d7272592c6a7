"""The installed packages: the folders vergence/ and services/ are the import packages of the same names (every
subpackage found, none listed by hand); the `vergence` command is services.ops.cli."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
VERGENCE = Path(sys.executable).with_name("vergence")


def _env() -> dict:
    """This environment without anything that would put the checkout on sys.path by hand."""
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONSTARTUP", "PYTHONHOME")}


def _py(code: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, env=_env(), capture_output=True, text=True,
                          timeout=120)


def test_pyproject_installs_both_folders_under_their_names():
    conf = tomllib.loads((ROOT / "pyproject.toml").read_text())
    st = conf["tool"]["setuptools"]
    assert st["packages"]["find"]["include"] == ["vergence", "vergence.*", "services", "services.*"]
    assert "package-dir" not in st
    assert conf["project"]["scripts"] == {"vergence": "services.ops.cli:main"}


@pytest.mark.slow
def test_installed_environment_serves_services_from_the_checkout(tmp_path):
    """Outside the checkout, services is served from services/ (an editable install)."""
    r = _py("import services.ops.cli, services.runtime.session as s; print(services.ops.cli.__file__); "
            "print(s.__name__)", tmp_path)
    assert r.returncode == 0, r.stderr
    path, name = r.stdout.split()
    assert Path(path).resolve() == (ROOT / "services" / "ops" / "cli.py").resolve()
    assert name == "services.runtime.session"
    r = subprocess.run([str(VERGENCE), "--help"], cwd=tmp_path, env=_env(), capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and "usage: vergence" in r.stdout and "capture" in r.stdout, r.stderr
    r = subprocess.run([sys.executable, "-m", "services.ops.cli", "match", "--help"], cwd=tmp_path, env=_env(),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "MASTER" in r.stdout, r.stderr


@pytest.mark.slow
def test_the_wheel_holds_vergence_and_services_with_every_subpackage(tmp_path):
    """What `pip install .` (the Dockerfile) installs: top-level vergence and services, each folder of them."""
    src = tmp_path / "src"  # a copy, as the Dockerfile's: the build leaves nothing in the checkout
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for name in ("vergence", "services"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.nb?"))
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", str(src), "-w", str(tmp_path)],
                       cwd=tmp_path, env=_env(), capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    (whl,) = tmp_path.glob("vergence-*.whl")
    names = zipfile.ZipFile(whl).namelist()
    assert {n.split("/")[0] for n in names} == {"vergence", "services", "vergence-0.1.0.dist-info"}
    folders = {p.parent.relative_to(ROOT).as_posix() for name in ("vergence", "services")
               for p in (ROOT / name).rglob("__init__.py")}
    assert folders == {n.rpartition("/")[0] for n in names if n.endswith("/__init__.py")}
    assert "services/ops/cli.py" in names and "vergence/wire/keys.py" in names and "vergence/sim/__init__.py" in names
    entry = next(n for n in names if n.endswith("entry_points.txt"))
    assert "vergence = services.ops.cli:main" in zipfile.ZipFile(whl).read(entry).decode()
