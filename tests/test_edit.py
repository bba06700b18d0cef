"""``lasagna edit`` / ``render`` / ``train-layer`` / ``demo`` and the API behind them (lasagna.editing), on a
tiny random catalogue (tests/support/tinylayers.py) put first in LASAGNA_LAYERS.

Checked against independent decoders (pypng, Pillow) and a float64 numpy composite, not against the
code's own output: the stored layer PNG, the composite PNG, re-rendering from the document alone.
"""

from __future__ import annotations

import json
import shutil
import zipfile
from pathlib import Path

import numpy as np
import png as pypng
import pytest
import torch
from PIL import Image

from lasagna.cli import main
from lasagna.editing import edit, render_learned
from lasagna.errors import LasagnaError
from tests.support.tinylayers import ROOT, STEPS

PHOTO = ROOT / "examples" / "photos" / "coffee.png"
SCENE = ROOT / "examples" / "world" / "heldout-s0-000000"


@pytest.fixture(autouse=True)
def _catalogue(tiny, monkeypatch):
    monkeypatch.setenv("LASAGNA_LAYERS", str(tiny))


def run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _png16(path: Path) -> np.ndarray:
    """(C, h, w) stored codes / 65535 of a 16-bit PNG, read by pypng (independent of lasagna.io)."""
    w, h, rows, info = pypng.Reader(filename=str(path)).asDirect()
    assert info["bitdepth"] == 16
    planes = info["planes"]
    return np.vstack([np.asarray(r, dtype=np.float64) for r in rows]).reshape(h, w, planes).transpose(2, 0, 1) / 65535.0


def _rgb8(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB")).astype(np.int64)


def _stack_json(folder: Path) -> dict:
    return json.loads((folder / "stack.json").read_text(encoding="utf-8"))


def _no_leftovers(parent: Path) -> list[str]:
    return [
        p.name
        for p in parent.iterdir()
        if p.name.startswith(".") and (p.name.endswith(".tmp") or p.name.endswith(".old"))
    ]


# ---- edit an image ------------------------------------------------------------------------------------


def test_edit_png_writes_a_complete_stack(tmp_path, capsys):
    out = tmp_path / "out"
    code, stdout, err = run(capsys, "edit", PHOTO, "--layer", "shading", "--condition", "left", "-o", out)
    assert code == 0, err
    assert f"wrote {out}/" in stdout and "amortised generator, one forward pass" in stdout
    doc = _stack_json(out)
    base, learned = doc["layers"]
    assert base["kind"] == "pixels" and base["source"] == "layers/base.png"
    assert learned["kind"] == "learned" and learned["preset"] == "shading" and learned["condition"]["label"] == "left"
    assert learned["conditioned_on"] == "base" and learned["blend"] == "multiply" and learned["range"] == [0.0, 2.0]
    assert learned["source"] == f"layers/{learned['id']}.png" and (out / learned["source"]).is_file()
    ckpt = out / learned["generator"]["checkpoint"]
    import hashlib

    assert hashlib.sha256(ckpt.read_bytes()).hexdigest() == learned["generator"]["sha256"]
    assert (ckpt.parent / "config.json").is_file()
    side = json.loads((ROOT / "layers" / "shading" / "preset.json").read_text(encoding="utf-8"))["working_size"]
    assert learned["settings"] == {"method": "amortised", "optimize": 0, "working_size": side}
    meta = doc["metadata"]["lasagna.edit"][learned["id"]]
    assert meta["tool"].startswith("lasagna ") and meta["seconds"] >= 0 and meta["input"] == "coffee.png"
    with zipfile.ZipFile(out / "stack.ora") as zf:
        assert zf.namelist()[0] == "mimetype" and zf.read("mimetype") == b"image/openraster"
    assert _no_leftovers(tmp_path) == []


def test_composite_matches_an_independent_float64_composite(tmp_path, capsys):
    out = tmp_path / "out"
    assert run(capsys, "edit", PHOTO, "--condition", "right", "-o", out)[0] == 0
    base = _rgb8(out / "layers" / "base.png").astype(np.float64) / 255.0  # (h, w, 3)
    y = 2.0 * _png16(out / "layers" / "shading-right.png")[0]  # v = y / 2 for range [0, 2]
    expected = np.rint(np.clip(base * y[:, :, None], 0.0, 1.0) * 255.0)
    assert np.abs(_rgb8(out / "composite.png") - expected).max() <= 1  # one step: float32 render vs float64


def test_composite_rerenders_to_the_same_png(tmp_path, capsys):
    out = tmp_path / "out"
    assert run(capsys, "edit", PHOTO, "--condition", "top", "--generator", "free", "-o", out)[0] == 0
    code, _, err = run(capsys, "composite", out, "-o", tmp_path / "again.png")
    assert code == 0, err
    assert np.array_equal(_rgb8(tmp_path / "again.png"), _rgb8(out / "composite.png"))


@pytest.mark.parametrize("method", [dict(generator="amortised"), dict(generator="free"), dict(optimize=2)])
def test_stored_layer_round_trips_within_one_16bit_step(tmp_path, method):
    result = edit(PHOTO, "shading", "left", **method)
    folder = result.save(tmp_path / "out")
    stored = 2.0 * _png16(folder / "layers" / f"{result.layer_id}.png")
    assert stored.shape == tuple(result.layer.shape)
    assert np.abs(stored - result.layer.double().numpy()).max() <= 2.0 / 65535 / 2 + 1e-7  # half a step of [0, 2]


def test_colour_layer_is_rgba_in_its_range(tmp_path):
    result = edit(PHOTO, "color", "natural")
    assert result.settings["method"] == "per-image" and result.settings["optimize"] == STEPS
    assert result.layer.shape == (4, 96, 96) and 0.0 <= float(result.layer.min()) and float(result.layer.max()) <= 1.0
    folder = result.save(tmp_path / "out", ora=False)
    stored = _png16(folder / "layers" / "color-natural.png")
    assert stored.shape[0] == 4 and np.abs(stored - result.layer.double().numpy()).max() <= 1 / 65535 / 2 + 1e-7
    assert not (folder / "stack.ora").exists()


def test_light_layer_is_a_plus_layer_that_only_brightens(tmp_path, capsys):
    code, _, err = run(capsys, "edit", PHOTO, "--layer", "light", "--condition", "warm", "-o", tmp_path / "lit")
    assert code == 0, err
    doc = _stack_json(tmp_path / "lit")
    layer = doc["layers"][-1]
    assert (layer["kind"], layer["blend"], layer["preset"], layer["condition"]["label"]) == (
        "learned",
        "plus",
        "light",
        "warm",
    )
    glow = _png16(tmp_path / "lit" / layer["source"])
    assert glow.shape[0] == 3 and glow.min() >= 0.0
    # plus never darkens: every composite pixel is at least the input's (8-bit, so within one step)
    assert (_rgb8(tmp_path / "lit" / "composite.png") >= _rgb8(PHOTO) - 1).all()
    code, _, err = run(capsys, "edit", PHOTO, "--layer", "light", "--condition", "left", "-o", tmp_path / "bad")
    assert code == 2 and "expected one of warm, cool, white" in err and not (tmp_path / "bad").exists()


def test_jpeg_and_tensor_inputs(tmp_path):
    rgb = np.asarray(Image.open(PHOTO).convert("RGB"))
    Image.fromarray(rgb).save(tmp_path / "photo.jpg", quality=95)
    result = edit(tmp_path / "photo.jpg", "shading", "bottom")
    assert result.stack.width == 96 and result.stack.document.layers[0].name == "photo"
    image = torch.rand(3, 20, 28)  # any size: the generator is fully convolutional
    t = edit(image, "shading", "top-left")
    assert t.layer.shape == (1, 20, 28)
    folder = t.save(tmp_path / "tensor")
    again, rendered = render_learned(folder, all=True, write=False)
    assert rendered == ["shading-top-left"]
    assert torch.equal(again.tensors["shading-top-left"].color, t.stack.tensors["shading-top-left"].color)


def test_16bit_gray_tiff_input_is_kept_at_16_bits(tmp_path, capsys):
    # Pillow reads "I;16" as mode I (32-bit codes); converting that to RGB saturated to all 1.0 before #16.
    Image.new("I;16", (16, 12), 30000).save(tmp_path / "i16.tif")
    out = tmp_path / "out"
    code, _, err = run(capsys, "edit", tmp_path / "i16.tif", "--condition", "left", "-o", out, "--no-ora")
    assert code == 0, err
    base = _stack_json(out)["layers"][0]
    values = _png16(out / base["source"])
    assert values.shape[1:] == (12, 16) and np.all(values == 30000 / 65535)


def test_per_image_is_seeded(tmp_path):
    a = edit(PHOTO, "shading", "left", generator="free", seed=3)
    b = edit(PHOTO, "shading", "left", generator="free", seed=3)
    c = edit(PHOTO, "shading", "left", generator="free", seed=4)
    assert torch.equal(a.layer, b.layer) and not torch.equal(a.layer, c.layer)
    assert a.settings["distill"]["seed"] == 3 and len(a.history) == STEPS


# ---- edit a stack -------------------------------------------------------------------------------------


def test_edit_a_stack_folder_on_a_named_layer(tmp_path, capsys):
    scene = shutil.copytree(SCENE, tmp_path / "scene")
    out = tmp_path / "out"
    code, _, err = run(capsys, "edit", scene, "--condition", "right", "--on", "albedo", "-o", out, "--optimize", "2")
    assert code == 0, err
    doc = _stack_json(out)
    assert [layer["id"] for layer in doc["layers"]] == ["albedo", "shading", "shading-right"]
    learned = doc["layers"][-1]
    assert learned["conditioned_on"] == "albedo" and learned["settings"]["method"] == "amortised"
    assert learned["settings"]["optimize"] == 2 and learned["settings"]["distill"]["weights"]["reg"]["end"] == 0.0
    assert doc["metadata"]["lasagna.world"]["split"] == "heldout"  # the input's metadata is kept
    code, _, err = run(capsys, "composite", out, "-o", tmp_path / "again.png")
    assert code == 0 and np.array_equal(_rgb8(tmp_path / "again.png"), _rgb8(out / "composite.png"))


def test_edit_a_stack_conditions_on_its_composite_and_carries_generators(tmp_path, capsys):
    first, second = tmp_path / "first", tmp_path / "second"
    assert run(capsys, "edit", PHOTO, "--condition", "left", "-o", first)[0] == 0
    assert run(capsys, "edit", first, "--condition", "top", "-o", second)[0] == 0
    doc = _stack_json(second)
    assert [layer["conditioned_on"] for layer in doc["layers"][1:]] == ["base", "shading-left"]
    for layer in doc["layers"][1:]:
        assert (second / layer["generator"]["checkpoint"]).is_file()  # the first edit's generator came along
    code, _, err = run(capsys, "validate", second)
    assert code == 0, err


def test_a_taken_id_gets_a_suffix():
    a = edit(PHOTO, "shading", "left")
    b = edit(a.stack, "shading", "left")
    assert b.layer_id == "shading-left-2" and b.stack.ids == ("base", "shading-left", "shading-left-2")


# ---- render ------------------------------------------------------------------------------------------


def _strip_learned_pixels(folder: Path) -> dict[str, bytes]:
    doc = _stack_json(folder)
    kept = {}
    for layer in doc["layers"]:
        if layer["kind"] == "learned":
            png = folder / layer["source"]
            kept[layer["source"]] = png.read_bytes()
            png.unlink()
            layer["source"] = None
    (folder / "stack.json").write_text(json.dumps(doc), encoding="utf-8")
    kept["composite.png"] = (folder / "composite.png").read_bytes()
    (folder / "composite.png").unlink()
    return kept


@pytest.mark.parametrize(
    "args",
    [
        (),
        ("--generator", "free", "--loss", "lmc-sds"),
        ("--optimize", "3"),
        ("--generator", "free", "--guidance", "3", "--seed", "7"),
    ],
)
def test_render_reproduces_the_edit(tmp_path, capsys, args):
    out = tmp_path / "out"
    assert run(capsys, "edit", PHOTO, "--condition", "bottom-right", "-o", out, *args)[0] == 0
    expected = _strip_learned_pixels(out)
    code, _, err = run(capsys, "validate", out)
    assert code == 0 and "1 learned layer(s) not rendered" in _
    code, stdout, err = run(capsys, "render", out)
    assert code == 0, err
    assert "rendered shading-bottom-right" in stdout
    for rel, data in expected.items():
        assert (out / rel).read_bytes() == data, rel


def test_render_fills_in_a_hand_written_learned_layer(tmp_path, capsys):
    folder = shutil.copytree(ROOT / "examples" / "stacks" / "learned", tmp_path / "learned")
    doc = _stack_json(folder)
    doc["layers"][1].update(source=None, settings={})
    (folder / "stack.json").write_text(json.dumps(doc), encoding="utf-8")
    (folder / "layers" / "relit.png").unlink()
    code, _, err = run(capsys, "render", folder)
    assert code == 0, err
    relit = _stack_json(folder)["layers"][1]
    # Made as `lasagna edit` makes it: the preset's method, steps and working size (#26).
    side = json.loads((ROOT / "layers" / "shading" / "preset.json").read_text(encoding="utf-8"))["working_size"]
    expected = {"method": "amortised", "optimize": 0, "working_size": side}
    assert relit["source"] == "layers/relit.png" and relit["settings"] == expected
    assert (folder / relit["generator"]["checkpoint"]).is_file() and (folder / "composite.png").is_file()


def test_render_all_and_nothing_to_render(tmp_path, capsys):
    out = tmp_path / "out"
    assert run(capsys, "edit", PHOTO, "--condition", "left", "-o", out)[0] == 0
    code, stdout, _ = run(capsys, "render", out)
    said = "nothing to render: every learned layer (shading-left) has its pixels; --all re-renders"
    assert code == 0 and said in stdout
    before = (out / "layers" / "shading-left.png").read_bytes()
    code, stdout, _ = run(capsys, "render", out, "--all")
    assert code == 0 and "rendered shading-left" in stdout
    assert (out / "layers" / "shading-left.png").read_bytes() == before
    assert "rendered" in _stack_json(out)["metadata"]["lasagna.edit"]["shading-left"]


def test_render_makes_a_learned_layer_whose_png_is_missing(tmp_path, capsys):
    """Without --all, ``render`` makes the learned layers not rendered yet: a PNG deleted (or never written) is
    one of them, not an error (issue 27); a pixels layer's missing PNG still is."""
    out = tmp_path / "out"
    assert run(capsys, "edit", PHOTO, "--condition", "left", "-o", out)[0] == 0
    png = out / "layers" / "shading-left.png"
    before = png.read_bytes()
    png.unlink()
    code, stdout, err = run(capsys, "render", out)
    assert code == 0 and "rendered shading-left" in stdout, err
    assert png.read_bytes() == before
    (out / "layers" / "base.png").unlink()
    code, _, err = run(capsys, "render", out)
    assert code == 2 and "base.png' does not exist" in err


@pytest.mark.parametrize(
    "fields, method, steps",
    [
        ({"method": "per-image"}, "per-image", STEPS),  # the preset's distill.steps
        ({"method": None, "refine_steps": 2}, "amortised", 2),  # the generator's layer, then 2 steps
        ({"method": "amortised", "refine_steps": 0}, "amortised", 0),
    ],
)
def test_the_presets_method_and_refine_steps_are_the_default(tmp_path, tiny, monkeypatch, fields, method, steps):
    from tests.support.tinylayers import write_preset

    folder = tmp_path / "layers"
    shutil.copytree(tiny, folder)
    write_preset(folder, "shading", **fields)
    monkeypatch.setenv("LASAGNA_LAYERS", str(folder))
    result = edit(PHOTO, "shading", "left")
    settings = result.stack.document.layer("shading-left").settings
    assert (settings["method"], settings["optimize"]) == (method, steps)
    assert result.stack.document.layer("shading-left").generator is None if method == "per-image" else True
    # an explicit choice still wins over the preset's
    other = edit(PHOTO, "shading", "left", generator="free" if method == "amortised" else "amortised", optimize=1)
    assert other.stack.document.layer("shading-left").settings["method"] != method


def test_a_preset_asking_for_amortised_without_a_generator_runs_per_image(tmp_path, tiny, monkeypatch):
    from tests.support.tinylayers import write_preset

    folder = tmp_path / "layers"
    shutil.copytree(tiny, folder)
    shutil.rmtree(folder / "shading" / "generator")
    write_preset(folder, "shading", method="amortised", refine_steps=3)
    monkeypatch.setenv("LASAGNA_LAYERS", str(folder))
    settings = edit(PHOTO, "shading", "left").stack.document.layer("shading-left").settings
    assert (settings["method"], settings["optimize"]) == ("per-image", STEPS)


def test_render_writes_all_or_nothing(tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    assert run(capsys, "edit", PHOTO, "--condition", "left", "-o", out)[0] == 0
    _strip_learned_pixels(out)  # render now writes the layer's PNG, stack.json and the composite
    before = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    import lasagna.atomic

    real = lasagna.atomic._write

    def fail_on_composite(path, data):  # the disk fills up while the composite is written
        if "composite.png" in path.name:
            raise OSError(28, "No space left on device")
        return real(path, data)

    monkeypatch.setattr(lasagna.atomic, "_write", fail_on_composite)
    code, _, err = run(capsys, "render", out, "--all")
    assert code == 2 and len(err.splitlines()) == 1 and "composite.png" in err
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()} == before  # nothing changed
    assert not [p for p in out.iterdir() if "lasagna-" in p.name]  # and no temporaries


def test_render_refuses_a_tampered_generator(tmp_path, capsys):
    out = tmp_path / "out"
    assert run(capsys, "edit", PHOTO, "--condition", "left", "-o", out)[0] == 0
    weights = out / "generators" / "shading-left" / "model.safetensors"
    data = bytearray(weights.read_bytes())
    data[-1] ^= 1
    weights.write_bytes(bytes(data))
    before = (out / "stack.json").read_bytes()
    code, _, err = run(capsys, "render", out, "--all")
    assert code == 2 and "do not match the recorded sha256" in err and len(err.splitlines()) == 1
    assert (out / "stack.json").read_bytes() == before


# ---- bad input ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--layer", "nope", "--condition", "left"], "no preset named 'nope'"),
        (
            ["--condition", "sideways"],
            "expected one of left, right, top, bottom, top-left, top-right, bottom-left, bottom-right",
        ),
        (["--condition", "left", "--max-pixels", "100"], "over the limit of 100"),
        (["--condition", "left", "--on", "ghost"], "no layer with id 'ghost'; expected one of base"),
        (["--condition", "left", "--optimize", "2", "--steps", "3"], "optimize 2 and steps 3 differ"),
        (["--condition", "left", "--generator", "free", "--optimize", "0"], "0 steps would leave the identity edit"),
        (["--condition", "left", "--optimize", "-1"], "expected a non-negative integer"),
        (["--layer", "../shading", "--condition", "left"], "is not a name"),
        (["--layer", "color", "--condition", "natural", "--generator", "amortised"], "has no amortised generator yet"),
        (["--condition", "left", "--guidance", "-1", "--generator", "free"], "guidance"),
    ],
)
def test_bad_edit_input_is_one_line_and_writes_nothing(tmp_path, capsys, argv, message):
    out = tmp_path / "out"
    code, _, err = run(capsys, "edit", PHOTO, "-o", out, *argv)
    assert code == 2 and message in err, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert not out.exists() and _no_leftovers(tmp_path) == []


def test_bad_inputs_and_outputs(tmp_path, capsys):
    (tmp_path / "file").write_bytes(b"x")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "notes.txt").write_text("mine")
    (tmp_path / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    (tmp_path / "text.jpg").write_text("not an image")
    cases = [
        (["edit", PHOTO, "--condition", "left", "-o", tmp_path / "file"], "exists and is not a folder"),
        (["edit", PHOTO, "--condition", "left", "-o", tmp_path / "full"], "is not empty"),
        (["edit", PHOTO, "--condition", "left", "-o", tmp_path / "full", "--force"], "holds no stack.json"),
        (["edit", PHOTO, "--condition", "left", "-o", tmp_path / "file" / "sub"], "not a writable folder"),
        (["edit", tmp_path / "missing.png", "--condition", "left", "-o", tmp_path / "o"], "does not exist"),
        (["edit", tmp_path / "broken.png", "--condition", "left", "-o", tmp_path / "o"], "broken.png"),
        (["edit", tmp_path / "text.jpg", "--condition", "left", "-o", tmp_path / "o"], "cannot decode"),
        (["render", tmp_path / "missing"], "missing"),
    ]
    for argv, message in cases:
        code, _, err = run(capsys, *argv)
        assert code == 2 and message in err and len(err.splitlines()) == 1, (argv, err)
    assert (tmp_path / "file").read_bytes() == b"x" and (tmp_path / "full" / "notes.txt").read_text() == "mine"
    assert not (tmp_path / "o").exists() and _no_leftovers(tmp_path) == []


def test_linear_stack_is_refused(tmp_path, capsys):
    folder = shutil.copytree(ROOT / "examples" / "stacks" / "linear", tmp_path / "linear")
    code, _, err = run(capsys, "edit", folder, "--condition", "left", "-o", tmp_path / "o")
    assert code == 2 and "blend_space is 'linear'" in err


def test_prior_without_the_label_is_refused(tmp_path, tiny):
    cat_dir = tmp_path / "layers"
    shutil.copytree(tiny, cat_dir)
    preset = json.loads((cat_dir / "shading" / "preset.json").read_text())
    preset["vocabulary"] = ["left", "sunset"]
    (cat_dir / "shading" / "preset.json").write_text(json.dumps(preset))
    with pytest.raises(
        LasagnaError,
        match="label 'sunset' of preset 'shading' is not one prior 'relight-32' was "
        "trained on; expected one of left, right, top",
    ):
        edit(PHOTO, "shading", "sunset", generator="free", catalogue_dirs=[cat_dir])


def test_a_failure_while_writing_leaves_nothing(tmp_path, monkeypatch):
    import lasagna.export.ora as ora

    result = edit(PHOTO, "shading", "left")
    monkeypatch.setattr(ora, "encode_ora", lambda *a, **k: (_ for _ in ()).throw(OSError("disk full")))
    with pytest.raises(OSError, match="disk full"):
        result.save(tmp_path / "out")
    assert not (tmp_path / "out").exists() and list(tmp_path.iterdir()) == []


def test_force_replaces_a_stack_folder_as_a_whole(tmp_path, capsys):
    out = tmp_path / "out"
    assert run(capsys, "edit", PHOTO, "--condition", "left", "-o", out)[0] == 0
    (out / "stale.txt").write_text("old")
    code, _, err = run(capsys, "edit", PHOTO, "--condition", "right", "-o", out, "--force")
    assert code == 0, err
    assert not (out / "stale.txt").exists() and [layer["id"] for layer in _stack_json(out)["layers"]] == [
        "base",
        "shading-right",
    ]
    assert _no_leftovers(tmp_path) == []


# ---- train-layer, layers, demo ------------------------------------------------------------------------


def test_train_layer_and_install(tmp_path, capsys, tiny, monkeypatch):
    cat_dir = shutil.copytree(tiny, tmp_path / "layers")
    shutil.rmtree(cat_dir / "shading" / "generator")
    monkeypatch.setenv("LASAGNA_LAYERS", str(cat_dir))
    code, stdout, err = run(
        capsys,
        "train-layer",
        "--preset",
        "shading",
        "--out",
        tmp_path / "run",
        "--steps",
        "2",
        "--batch-size",
        "2",
        "--channels",
        "4,8",
        "--ema-warmup",
        "--install",
    )
    assert code == 0, err
    line = json.loads(stdout.strip().splitlines()[-1])
    assert line["step"] == 2 and line["installed"] == str(cat_dir / "shading" / "generator")
    config = json.loads((tmp_path / "run" / "train_config.json").read_text())
    defaults = json.loads((ROOT / "layers" / "shading" / "preset.json").read_text(encoding="utf-8"))["distill"]
    assert (config["loss"], config["guidance"]) == (defaults["loss"], defaults["guidance"])  # the preset's defaults
    assert config["weights"]["reg"] == {"start": 1.0, "end": 0.0, "steps": 500, "shape": "cosine"}  # --reg-final 0
    if config["loss"] == "lmc-sds":
        assert config["corrective"].endswith("relight-32-spectral")
    else:
        assert config["corrective"] is None  # only LMC-SDS uses the corrective
    assert config["ema_decay"] == 0.999 and config["ema_warmup"] is True
    result = edit(PHOTO, "shading", "left", catalogue_dirs=[cat_dir])
    assert result.settings["method"] == "amortised"


def test_train_layer_install_goes_to_the_users_catalogue(tmp_path, capsys, tiny, monkeypatch):
    """``--install`` never writes into the catalogue the preset came from (the package's, in a wheel): the
    generator and a copy of the preset go to the user's catalogue, and one there or shipped is replaced only
    with ``--force`` (issue 27)."""
    from lasagna import catalogue as cat
    from lasagna.document.preset import user_catalogue
    from tests.support.tinylayers import fingerprint

    package = shutil.copytree(tiny, tmp_path / "site-packages" / "lasagna" / "_layers")
    assert (package / "shading" / "generator" / "config.json").is_file()  # a shipped generator
    before = fingerprint(package)
    monkeypatch.delenv("LASAGNA_LAYERS", raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    monkeypatch.setattr(cat, "default_catalogues", lambda: [user_catalogue(), package])
    train = ["train-layer", "--preset", "shading", "--steps", "1", "--batch-size", "2", "--channels", "4,8"]

    code, _, err = run(capsys, *train, "--out", tmp_path / "run", "--install")
    assert code == 2 and "already has a generator" in err and "--force" in err and err.count("\n") == 1
    assert not (tmp_path / "run").exists()  # refused before training

    code, stdout, err = run(capsys, *train, "--out", tmp_path / "run", "--install", "--force")
    assert code == 0, err
    user = user_catalogue() / "shading"
    assert json.loads(stdout.strip().splitlines()[-1])["installed"] == str(user / "generator")
    assert fingerprint(package) == before  # the package's catalogue untouched
    assert (user / "preset.json").is_file() and cat.resolve("shading").generator == user / "generator"
    assert edit(PHOTO, "shading", "left").settings["method"] == "amortised"

    code, _, err = run(capsys, *train, "--out", tmp_path / "run2", "--install")
    assert code == 2 and str(user / "generator") in err  # the user's own generator is kept too


@pytest.mark.parametrize("supervised", [False, True])
def test_train_layer_trains_on_the_presets_task(tmp_path, capsys, tiny, supervised):
    """The relight preset's layer is a ratio onto an image already lit (``"task": "relit"``), not the shading
    of an albedo its blend (multiply) would say: its generator trains on that task, supervised or not."""
    from lasagna.document.preset import load_preset

    preset = load_preset(ROOT / "layers" / "relight" / "preset.json")
    assert preset.world_task == "relit" and load_preset(ROOT / "layers" / "shading" / "preset.json").world_task == (
        "relight"
    )
    flags = ["--supervised"] if supervised else []
    code, _, err = run(
        capsys,
        "train-layer",
        "--preset",
        "relight",
        "--out",
        tmp_path / "run",
        "--steps",
        "1",
        "--batch-size",
        "2",
        "--channels",
        "4,8",
        "--resolution",
        "8",
        *flags,
    )
    assert code == 0, err
    config = json.loads((tmp_path / "run" / "train_config.json").read_text())
    assert config["task"] == "relit" and config["supervised"] is supervised


def test_train_layer_on_another_split(tmp_path, capsys):
    """--split/--world-seed/--eval-split reach the run's config (an in-family oracle); a held-out split at the
    benchmarks' own world seed 0, an unknown split and a negative seed are refused in one line, before any run."""
    common = ["train-layer", "--preset", "shading", "--supervised", "--steps", "1", "--batch-size", "2"]
    common += ["--channels", "4,8", "--resolution", "8"]
    code, _, err = run(capsys, *common, "--out", tmp_path / "run", "--split", "heldout", "--world-seed", "1")
    assert code == 0, err
    config = json.loads((tmp_path / "run" / "train_config.json").read_text())
    assert (config["split"], config["world_seed"], config["eval_split"]) == ("heldout", 1, "val")
    for flags, needle in (
        (["--split", "far"], "--world-seed: training on far scenes of world seed 0"),
        (["--split", "nope"], "--split: unknown split 'nope'; expected one of train, val, heldout, far"),
        (["--eval-split", "nope"], "--eval-split: unknown split 'nope'"),
        (["--world-seed", "-1"], "--world-seed: expected an integer in [0, 2**63), got -1"),
    ):
        code, _, err = run(capsys, *common, "--out", tmp_path / "bad", *flags)
        assert code == 2 and needle in err and len(err.strip().splitlines()) == 1, err
        assert not (tmp_path / "bad").exists()


def test_train_layer_bad_input(tmp_path, capsys):
    code, _, err = run(capsys, "train-layer", "--preset", "nope", "--out", tmp_path / "run")
    assert code == 2 and "no preset named 'nope'" in err
    code, _, err = run(capsys, "train-layer", "--preset", "shading", "--out", tmp_path / "run", "--channels", "a,b")
    assert code == 2 and "--channels" in err and not (tmp_path / "run").exists()


def test_layers_lists_the_catalogue(capsys, tiny):
    code, stdout, _ = run(capsys, "layers", "--json")
    found = json.loads(stdout)
    assert code == 0 and found["catalogues"][0] == str(tiny) and "relight-32" in found["prior"]
    assert found["status"]["shading"]["method"] == "amortised" and found["status"]["color"]["usable"]
    code, stdout, _ = run(capsys, "layers")
    assert code == 0 and "  shading: ready (amortised" in stdout and "  color: ready (per-image" in stdout


def test_demo_end_to_end(tmp_path, capsys):
    out = tmp_path / "demo"
    code, stdout, err = run(capsys, "demo", "-o", out)
    assert code == 0, err
    sheet = out / "sheet.png"
    assert f"wrote the sheet {sheet}" in stdout
    with Image.open(sheet) as im:
        assert im.mode == "RGB" and im.width > 1000 and im.height > 600
    stacks = sorted(p.name for p in (out / "stacks").iterdir())
    assert "coffee-left" in stacks and "heldout-s0-000000-color" in stacks and len(stacks) == 38
    assert {"coffee-relit-right", "chelsea-relit-az135-el40", "heldout-s0-000001-relit-right"} <= set(stacks)
    assert {
        "heldout-s0-000000-warm-light",
        "heldout-s0-000001-cool-light",
        "coffee-warm-light",
        "helmet-cool-light",
    } <= set(stacks)
    # the world scene's light is added on top of the scene as rendered (albedo × shading, both visible)
    lit = _stack_json(out / "stacks" / "heldout-s0-000000-warm-light")
    assert [(layer["id"], layer.get("visible", True)) for layer in lit["layers"]][:2] == [
        ("albedo", True),
        ("shading", True),
    ]
    assert lit["layers"][-1]["blend"] == "plus" and len(lit["layers"]) == 3
    for name in ("heldout-s0-000000-left", "coffee-color", "coffee-warm-light"):
        code, _, err = run(capsys, "validate", out / "stacks" / name)
        assert code == 0, err
    code, _, err = run(capsys, "demo", "-o", out)  # a second run replaces its own stacks
    assert code == 0, err


def test_the_demo_s_inputs_from_the_package_alone_are_the_checkout_s_bit_for_bit(tmp_path):
    """Outside a checkout the demo renders its world scenes and copies the photographs the package ships
    (``lasagna.demo.packaged_examples``): every file it reads is the committed ``examples/`` file, byte for byte."""
    from lasagna.demo import PACKAGED_PHOTOS, PHOTOS, packaged_examples

    made = packaged_examples(tmp_path / "examples")

    def files(folder: Path) -> dict[str, bytes]:
        return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}

    committed = {k: v for k, v in files(ROOT / "examples" / "world").items() if k != "README.md"}
    assert files(made / "world") == committed and len(committed) == 4 * 6 + 1  # 4 scenes of 6 files, world.json
    for name in PHOTOS:
        shipped = (ROOT / "examples" / "photos" / f"{name}.png").read_bytes()
        assert (
            (made / "photos" / f"{name}.png").read_bytes() == (PACKAGED_PHOTOS / f"{name}.png").read_bytes() == shipped
        )
    # under lasagna/, so in the wheel (tests/test_wheel.py checks every data file there is declared package data)
    assert PACKAGED_PHOTOS.is_relative_to(ROOT / "lasagna")


def test_demo_runs_without_a_checkout(tmp_path, capsys, monkeypatch):
    """An installed wheel has no examples/: the demo makes its inputs from the package in a temporary folder,
    writes what it writes in a checkout, and leaves no temporary folder behind."""
    import tempfile

    import lasagna.demo

    monkeypatch.setattr(lasagna.demo, "examples_root", lambda: None)  # what an install outside a checkout finds
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    code, stdout, err = run(capsys, "demo", "-o", "out")
    assert code == 0, err
    assert stdout.startswith("demo: no examples/ here (not a checkout): rendering the world scenes")
    stacks = sorted(p.name for p in (tmp_path / "out" / "stacks").iterdir())
    assert len(stacks) == 38 and {"coffee-left", "helmet-cool-light", "heldout-s0-000001-relit-right"} <= set(stacks)
    assert (tmp_path / "out" / "sheet.png").is_file() and list((tmp_path / "tmp").iterdir()) == []


@pytest.mark.parametrize("checkout", [True, False])
def test_demo_falls_back_without_priors(tmp_path, capsys, monkeypatch, checkout):
    """In a checkout the fallback exports examples/stacks/basic; from the package alone, the first world scene."""
    if not checkout:
        import lasagna.demo

        monkeypatch.setattr(lasagna.demo, "examples_root", lambda: None)
    empty = tmp_path / "layers"
    for name in ("shading", "color", "light", "relight"):
        (empty / name).mkdir(parents=True)
        preset = json.loads((ROOT / "layers" / name / "preset.json").read_text())
        preset["prior"] = "missing-prior"
        if preset.get("surface"):  # a surface preset's estimator is missing too: nothing learned can run
            preset["surface"]["estimator"] = "missing-estimator"
        (empty / name / "preset.json").write_text(json.dumps(preset))
    monkeypatch.setenv("LASAGNA_LAYERS", str(empty))
    code, stdout, err = run(capsys, "demo", "-o", tmp_path / "demo")
    assert code == 0, err
    first = stdout.splitlines()[0]
    assert first.startswith(
        "demo: no learned layer can run (shading: its prior 'missing-prior' is not in the catalogue"
    )
    assert "compositing and exporting the example stack instead" in first and "Traceback" not in stdout + err
    stack = "basic" if checkout else "heldout-s0-000000"
    for name in ("composite.png", f"{stack}.ora", "layers/layers.json", "stack/stack.json"):
        assert (tmp_path / "demo" / name).is_file(), name


def test_render_uses_the_prior_the_layer_was_made_with(tmp_path, capsys, tiny, monkeypatch):
    cat_dir = shutil.copytree(tiny, tmp_path / "layers")
    monkeypatch.setenv("LASAGNA_LAYERS", str(cat_dir))
    out = tmp_path / "out"
    assert run(capsys, "edit", PHOTO, "--condition", "left", "--generator", "free", "-o", out)[0] == 0
    expected = (out / "layers" / "shading-left.png").read_bytes()
    preset = json.loads((cat_dir / "shading" / "preset.json").read_text())
    preset["prior"] = "renamed-prior"  # the catalogue moves on; the stack still names relight-32
    (cat_dir / "shading" / "preset.json").write_text(json.dumps(preset))
    code, _, err = run(capsys, "render", out, "--all")
    assert code == 0, err
    assert (out / "layers" / "shading-left.png").read_bytes() == expected
    doc = _stack_json(out)
    doc["layers"][1]["settings"]["prior"] = "gone-prior"  # a prior no catalogue has: the stored name is what counts
    (out / "stack.json").write_text(json.dumps(doc), encoding="utf-8")
    code, _, err = run(capsys, "render", out, "--all")
    assert (
        code == 2 and "no prior named 'gone-prior'" in err and "expected one of light-32, recolor-32, relight-32" in err
    )


def test_edit_api_example_runs(tmp_path, capsys):
    import runpy

    module = runpy.run_path(str(ROOT / "examples" / "edit_api.py"))
    module["main"](tmp_path)
    out = capsys.readouterr().out
    assert "re-rendered shading-left: max difference 0.00e+00" in out and "layer 'light-warm'" in out
    for name in ("coffee-left", "coffee-top", "coffee-warm"):
        code, _, err = run(capsys, "validate", tmp_path / name)
        assert code == 0, err
