"""One recipe per learned layer (#26): the three routes that make a layer without stored settings — ``lasagna edit``,
``lasagna render`` of a settings-less learned layer and the editor's per-image add (a layer added to be made,
then its rerender job) — make the same layer, bit for bit, at the preset's working size.

References: the PNG bytes and the stored settings of ``lasagna edit``'s layer (the recipe's first constructor),
against those of the other two routes (its second); the catalogue's entries counted per edit by a profiler."""

from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from lasagna.cli import main
from lasagna.io.stack import Stack, load_stack
from tests.support.tinylayers import ROOT, tiny_variant

SIDE = 16  # the working size of the preset below: smaller than the image, so a full-size run would differ
PRESET = "shading"
LABEL = "left"


@pytest.fixture(scope="module")
def catalogue(tiny, tmp_path_factory) -> Path:
    """A variant of the tiny catalogue: no shading generator, its shading preset per-image (its default method)
    at working size ``SIDE``."""
    folder = tiny_variant(tiny, tmp_path_factory.mktemp("recipe") / "layers", generator=False)
    path = folder / PRESET / "preset.json"
    data = json.loads(path.read_text(encoding="utf-8"))
    data.update(method="per-image", working_size=SIDE)
    path.write_text(json.dumps(data), encoding="utf-8")
    return folder


@pytest.fixture(autouse=True)
def _catalogue(catalogue, monkeypatch):
    monkeypatch.setenv("LASAGNA_LAYERS", str(catalogue))


@pytest.fixture(scope="module")
def photo(tmp_path_factory) -> Path:
    """A 40×32 crop of an example photo (larger than the working size, not square)."""
    out = tmp_path_factory.mktemp("photo") / "photo.png"
    with Image.open(ROOT / "examples" / "photos" / "coffee.png") as im:
        im.convert("RGB").crop((10, 20, 50, 52)).save(out)
    return out


def _layer(folder: Path, id: str) -> tuple[bytes, dict]:
    doc = json.loads((folder / "stack.json").read_text(encoding="utf-8"))
    layer = next(x for x in doc["layers"] if x["id"] == id)
    return (folder / layer["source"]).read_bytes(), layer["settings"]


@pytest.fixture(scope="module")
def edited(photo, catalogue, tmp_path_factory) -> tuple[Path, bytes, dict]:
    out = tmp_path_factory.mktemp("edit") / "out"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("LASAGNA_LAYERS", str(catalogue))
        assert main(["edit", str(photo), "--layer", PRESET, "--condition", LABEL, "-o", str(out)]) == 0
    png, settings = _layer(out, f"{PRESET}-{LABEL}")
    assert settings["method"] == "per-image" and settings["working_size"] == SIDE
    return out, png, settings


def test_render_of_a_settings_less_layer_is_the_edit(edited, tmp_path, capsys):
    out, png, settings = edited
    folder = shutil.copytree(out, tmp_path / "copy")
    doc = json.loads((folder / "stack.json").read_text(encoding="utf-8"))
    layer = doc["layers"][-1]
    (folder / layer["source"]).unlink()
    layer.update(source=None, settings={})
    (folder / "stack.json").write_text(json.dumps(doc), encoding="utf-8")
    assert main(["render", str(folder)]) == 0
    assert _layer(folder, layer["id"]) == (png, settings)
    capsys.readouterr()


def test_the_editors_per_image_add_is_the_edit(edited, photo, catalogue, tmp_path):
    from lasagna.editing import read_image
    from lasagna.serve.session import EditSession

    out, png, settings = edited
    folder = tmp_path / "stack"
    read_image(photo).save(folder)
    session = EditSession(folder, catalogue_dirs=[catalogue])
    state = session.add_learned(session.version, PRESET, LABEL, method="per-image")
    id = state["document"]["layers"][-1]["id"]
    assert state["document"]["layers"][-1]["settings"] == {
        "method": "per-image",
        "optimize": settings["optimize"],
        "working_size": SIDE,
    }
    job = session.start_job(session.version, "rerender", id)
    deadline = time.monotonic() + 120
    while job.state == "running" and time.monotonic() < deadline:
        time.sleep(0.02)
    assert job.state == "done", job.error
    session.save(session.version)
    assert _layer(folder, id) == (png, settings)


def test_the_catalogue_is_entered_once_per_edit(photo):
    """Every call into lasagna/catalogue.py from outside it, during one ``edit``: one (``Recipe.for_edit``)."""
    import lasagna.catalogue as cat
    from lasagna.editing import edit

    here = cat.__file__
    entries: list[str] = []

    def profile(frame, event, arg):
        if event == "call" and frame.f_code.co_filename == here and frame.f_back is not None:
            if frame.f_back.f_code.co_filename != here:
                entries.append(f"{frame.f_back.f_code.co_name} -> {frame.f_code.co_name}")

    sys.setprofile(profile)
    try:
        result = edit(photo, PRESET, LABEL, optimize=1)
    finally:
        sys.setprofile(None)
    assert result.layer.shape[-2:] == (32, 40)
    assert entries == ["for_edit -> resolve"]


def test_a_stack_rendered_twice_is_the_same(edited, tmp_path):
    """``from_layer`` of a recorded per-image layer reproduces it (the recipe's second constructor)."""
    from lasagna.editing import render_learned

    out, png, _ = edited
    folder = shutil.copytree(out, tmp_path / "again")
    stack, ids = render_learned(load_stack(folder), all=True)
    assert ids == [f"{PRESET}-{LABEL}"]
    assert isinstance(stack, Stack) and _layer(folder, ids[0])[0] == png
    assert np.array_equal(stack.tensors[ids[0]].color.numpy(), load_stack(out).tensors[ids[0]].color.numpy())


def test_the_editors_presets_with_catalogue_folders(catalogue, photo, tmp_path):
    """``EditSession.presets`` lists the catalogue folders it was given (it passed them as the kind before)."""
    from lasagna.editing import read_image
    from lasagna.serve.session import EditSession

    folder = tmp_path / "stack"
    read_image(photo).save(folder)
    listed = {p["name"]: p for p in EditSession(folder, catalogue_dirs=[catalogue]).presets()}
    assert listed[PRESET]["ready"] and listed[PRESET]["method"] == "per-image", listed[PRESET]
