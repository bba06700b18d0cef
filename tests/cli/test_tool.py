"""The CLI behaves as a tool in this ecosystem does (issue 27): ``python -m lasagna``, outputs named as what they
are, no folders made where a file was asked for."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from lasagna.cli import main

ROOT = Path(__file__).resolve().parents[2]
BASIC = ROOT / "examples" / "stacks" / "basic"


def test_python_m_lasagna():
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, "-m", "lasagna", "--version"], capture_output=True, text=True, env=env)
    assert proc.returncode == 0 and proc.stdout.startswith("lasagna "), proc.stderr


@pytest.mark.parametrize("name", ["relit.png", "relit.JPG", "out.ora"])
def test_edit_output_named_as_a_file_is_refused(tmp_path, capsys, name):
    photo = tmp_path / "photo.png"
    Image.fromarray(np.full((8, 8, 3), 100, np.uint8)).save(photo)
    code = main(["edit", str(photo), "--condition", "left", "-o", str(tmp_path / name)])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1
    stem = Path(name).stem
    assert f"OUT is a stack folder; expected a folder name, e.g. -o {tmp_path / stem}" in err
    assert not (tmp_path / name).exists()


def test_composite_into_a_missing_folder_is_refused(tmp_path, capsys):
    out = tmp_path / "nonexistent" / "dir" / "x.png"
    code = main(["composite", str(BASIC), "-o", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "does not exist; expected a file in an existing folder" in err
    assert not (tmp_path / "nonexistent").exists()
