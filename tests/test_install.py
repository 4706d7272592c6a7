"""The installed package: the folder services/ is the import package vergence_services, so that installing
vergence never claims the name `services` (it would collide in site-packages); the `vergence` command stays."""

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


def test_pyproject_lists_every_package():
    """The packages are listed by hand (a find would name the folder services): every folder with an
    __init__.py under vergence/ must be there, and services/ under its import name only."""
    conf = tomllib.loads((ROOT / "pyproject.toml").read_text())
    st = conf["tool"]["setuptools"]
    on_disk = sorted(".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "vergence").rglob("__init__.py"))
    assert sorted(p for p in st["packages"] if p.startswith("vergence.") or p == "vergence") == on_disk
    assert "vergence_services" in st["packages"] and not any(p.split(".")[0] == "services" for p in st["packages"])
    assert st["package-dir"] == {"vergence_services": "services"}
    assert conf["project"]["scripts"] == {"vergence": "vergence_services.cli:main"}


@pytest.mark.slow
def test_installed_environment_has_no_services_package(tmp_path):
    """Outside the checkout, `import services` fails and vergence_services is served from services/."""
    r = _py("import services", tmp_path)
    assert r.returncode == 1 and "ModuleNotFoundError: No module named 'services'" in r.stderr, r.stderr
    r = _py("import vergence_services.cli, vergence_services.session as s; print(vergence_services.cli.__file__); "
            "print(s.__name__)", tmp_path)
    assert r.returncode == 0, r.stderr
    path, name = r.stdout.split()
    assert Path(path).resolve() == (ROOT / "services" / "cli.py").resolve() and name == "vergence_services.session"
    assert "services" not in sys.modules  # nor did this test process import it under that name
    r = subprocess.run([str(VERGENCE), "--help"], cwd=tmp_path, env=_env(), capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and "usage: vergence" in r.stdout and "capture" in r.stdout, r.stderr
    r = subprocess.run([sys.executable, "-m", "vergence_services.cli", "match", "--help"], cwd=tmp_path, env=_env(),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and "MASTER" in r.stdout, r.stderr


@pytest.mark.slow
def test_the_wheel_holds_vergence_and_vergence_services_only(tmp_path):
    """What `pip install .` (the Dockerfile) installs: top-level vergence and vergence_services, no services."""
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
    assert {n.split("/")[0] for n in names} == {"vergence", "vergence_services", "vergence-0.1.0.dist-info"}
    assert "vergence_services/cli.py" in names and "vergence/keys.py" in names and "vergence/sim/__init__.py" in names
    entry = next(n for n in names if n.endswith("entry_points.txt"))
    assert "vergence = vergence_services.cli:main" in zipfile.ZipFile(whl).read(entry).decode()
