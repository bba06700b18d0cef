"""The wheel as a user gets it, built in one place for the tests that install it (``tests/test_wheel.py``,
``tests/test_readme_installed.py``), and the files it must hold, read from the checkout without building it.

The wheel is built from a copy of the sources (pyproject.toml, README.md, LICENSE, lasagna/, layers/) so the
checkout gets no build/ or egg-info, with this interpreter's setuptools (``--no-build-isolation``) and no index.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from glob import glob
from pathlib import Path

from tests.support.bounded import HANG_SECONDS

ROOT = Path(__file__).resolve().parents[2]

# What the wheel is built from: the sdist's files, less what only a checkout needs (tests, docs, examples).
SOURCES = ("pyproject.toml", "README.md", "LICENSE", "lasagna", "layers")


def build_wheel(tmp: Path) -> Path:
    """Build the distribution's wheel under ``tmp`` (``tmp/src`` the copied sources, ``tmp/dist`` the wheel);
    returns the wheel's path."""
    src = tmp / "src"
    src.mkdir(parents=True)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for name in SOURCES:
        if (ROOT / name).is_dir():
            shutil.copytree(ROOT / name, src / name, ignore=ignore)
        else:
            shutil.copy2(ROOT / name, src / name)
    env = {**os.environ, "PIP_NO_INDEX": "1", "PIP_DISABLE_PIP_VERSION_CHECK": "1"}
    build = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "-q",
            "-w",
            str(tmp / "dist"),
            str(src),
        ],
        capture_output=True,
        text=True,
        timeout=HANG_SECONDS,
        env=env,
    )
    assert build.returncode == 0, build.stderr[-2000:]
    (wheel,) = (tmp / "dist").glob("lasagna_layers-*.whl")  # the distribution lasagna-layers
    return wheel


def required_data() -> set[str]:
    """Every file other than Python source that the wheel must hold, as its path in the wheel: the package's
    own data (the editor's page, py.typed, the world's paint, …) and the catalogue ``layers/`` as
    ``lasagna/_layers/`` (pyproject.toml's ``package-dir``)."""
    files = {
        p.relative_to(ROOT).as_posix()
        for p in (ROOT / "lasagna").rglob("*")
        if p.is_file() and p.suffix not in (".py", ".pyc") and "__pycache__" not in p.parts
    }
    files |= {
        f"lasagna/_layers/{p.relative_to(ROOT / 'layers').as_posix()}"
        for p in (ROOT / "layers").rglob("*")
        if p.is_file() and "__pycache__" not in p.parts
    }
    return files


def declared_data() -> set[str]:
    """The files pyproject.toml's ``[tool.setuptools.package-data]`` globs pick, as their paths in the wheel —
    expanded as setuptools' build_py does (``glob(..., recursive=True)`` under each package's folder)."""
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10: the tomli it was made from, where installed
        import pytest

        tomllib = pytest.importorskip("tomli")
    tool = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]
    package_dir = tool.get("package-dir", {})
    found = set()
    for package, patterns in tool["package-data"].items():
        folder = ROOT / package_dir.get(package, package.replace(".", "/"))
        wheel_folder = package.replace(".", "/")
        for pattern in patterns:
            for hit in glob(str(folder / pattern), recursive=True):
                if Path(hit).is_file():
                    found.add(f"{wheel_folder}/{Path(hit).relative_to(folder).as_posix()}")
    return found
