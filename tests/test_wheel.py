"""The learned-layer catalogue ships in the wheel: build it, install it apart from the checkout, load presets.

The wheel is built from a copy of the sources (``tests.support.wheel.build_wheel``); it is installed with
``pip install --no-deps --target`` and imported from a temporary folder in a fresh interpreter, with
``LASAGNA_LAYERS`` unset — the checkout is not importable there, so the presets can only come from the
installed package (``lasagna/_layers``). Every README command run from the wheel installed by name into a fresh
venv is ``tests/test_readme_installed.py`` (slow).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from lasagna.version import DISTRIBUTION, __version__, install_hint
from tests.support.bounded import HANG_SECONDS
from tests.support.wheel import ROOT, build_wheel, declared_data, required_data

CHECK = r"""
import json, sys
import lasagna
from lasagna import catalogue
from lasagna.document import default_catalogues
preset = catalogue.load_preset("shading")
print(json.dumps({"lasagna": lasagna.__file__, "preset": str(catalogue.find("shading")), "name": preset.name,
                  "blend": preset.blend, "available": catalogue.available()["preset"],
                  "catalogues": [str(c) for c in catalogue.catalogues()],
                  "default": [str(c) for c in default_catalogues()]}))
"""


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> tuple[Path, Path]:
    """(the wheel, the folder it is installed into)."""
    if subprocess.run([sys.executable, "-m", "pip", "--version"], capture_output=True).returncode != 0:
        pytest.skip("pip is not available to this interpreter")
    tmp = tmp_path_factory.mktemp("wheel")
    wheel = build_wheel(tmp)
    env = {**os.environ, "PIP_NO_INDEX": "1", "PIP_DISABLE_PIP_VERSION_CHECK": "1"}
    pip = [sys.executable, "-m", "pip"]
    target = tmp / "site"
    inst = subprocess.run(
        [*pip, "install", "--no-deps", "-q", "--target", str(target), str(wheel)],
        capture_output=True,
        text=True,
        timeout=HANG_SECONDS,
        env=env,
    )
    assert inst.returncode == 0, inst.stderr[-2000:]
    return wheel, target


def test_wheel_holds_every_catalogue_file(installed):
    wheel, _ = installed
    names = set(zipfile.ZipFile(wheel).namelist())
    assert required_data() <= names  # the catalogue, the editor's page, the world's paint, py.typed
    assert "lasagna/catalogue.py" in names and "lasagna/_layers/PACKAGING.md" in names
    page = {f"lasagna/serve/static/{p.name}" for p in (ROOT / "lasagna" / "serve" / "static").iterdir()}
    assert page and page <= names  # the editor's page works from an installed package, offline
    assert "lasagna/py.typed" in names  # PEP 561: type checkers read the package's annotations
    assert any(n.endswith("LICENSE") and ".dist-info/" in n for n in names)
    assert f"lasagna_layers-{__version__}.dist-info/METADATA" in names  # the distribution lasagna-layers


def test_every_data_file_is_declared_package_data():
    """Without building: every non-Python file under lasagna/ and layers/ (the catalogue a CLI command reads
    outside a checkout, the editor's page, the world's paint) is picked by pyproject.toml's package-data globs,
    so a file added there cannot silently stay out of the wheel."""
    required = required_data()
    assert {"lasagna/_layers/shading/preset.json", "lasagna/serve/static/index.html", "lasagna/py.typed"} <= required
    missing = sorted(required - declared_data())
    assert not missing, f"not in [tool.setuptools.package-data] of pyproject.toml: {missing}"


def test_the_distribution_name_is_one_and_every_install_hint_names_it():
    """``lasagna`` on the package index is another project: pyproject, ``DISTRIBUTION`` and every ``pip install``
    hint in the package, README and docs name ``lasagna-layers`` (issue 27)."""
    pyproject = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    assert re.search(r'^name = "([^"]+)"', pyproject, re.M).group(1) == DISTRIBUTION == "lasagna-layers"
    assert install_hint("serve") == "pip install 'lasagna-layers[serve]'"
    texts = [*(ROOT / "lasagna").rglob("*.py"), ROOT / "README.md", *(ROOT / "docs").rglob("*.md")]
    wrong = [
        f"{path.relative_to(ROOT)}: {hint}"
        for path in texts
        for hint in re.findall(r"pip install ['\"]?lasagna(?!-layers)\b\S*", path.read_text(encoding="utf-8"))
    ]
    assert wrong == []


def test_presets_resolve_from_the_installed_package(installed, tmp_path):
    _, target = installed
    env = {k: v for k, v in os.environ.items() if k not in ("LASAGNA_LAYERS", "PYTHONPATH")}
    env["PYTHONPATH"] = str(target)
    proc = subprocess.run(
        [sys.executable, "-c", CHECK], cwd=tmp_path, capture_output=True, text=True, timeout=HANG_SECONDS, env=env
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    got = json.loads(proc.stdout)
    packaged = target / "lasagna" / "_layers"
    assert Path(got["lasagna"]).resolve().is_relative_to(target.resolve())  # not the checkout
    assert got["default"] == [str(packaged)]  # the installed copy, no checkout layers/
    assert got["catalogues"] == [str(packaged)]
    assert got["preset"] == str(packaged / "shading" / "preset.json") and (got["name"], got["blend"]) == (
        "shading",
        "multiply",
    )
    assert set(got["available"]) >= {"shading", "color", "light"}
