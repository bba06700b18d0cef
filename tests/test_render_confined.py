"""``lasagna render`` follows only what a stack may ask for (#16): per-image steps bounded by
MAX_DISTILL_STEPS, a prior or corrective by catalogue name or inside the stack folder (the same message
whether a path outside exists or not), the generator's config.json under config_sha256 and its shape
bounded. Stacks are made once by ``lasagna edit`` on the tiny catalogue, then hand-edited."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from lasagna.cli import main
from lasagna.limits import MAX_DISTILL_STEPS


@pytest.fixture(scope="module")
def made(tmp_path_factory, tiny) -> dict[str, Path]:
    """A per-image stack (settings.prior written) and an amortised one (a generator folder), 16×16."""
    root = tmp_path_factory.mktemp("confined")
    catalogue = tiny
    image = root / "img.png"
    Image.fromarray(np.random.default_rng(0).integers(0, 256, (16, 16, 3)).astype(np.uint8)).save(image)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("LASAGNA_LAYERS", str(catalogue))
        edit = ["edit", str(image), "--condition", "left", "--no-ora", "-o"]
        assert main([*edit, str(root / "free"), "--generator", "free", "--optimize", "2"]) == 0
        assert main([*edit, str(root / "amortised")]) == 0
    return {"free": root / "free", "amortised": root / "amortised", "layers": catalogue}


@pytest.fixture(autouse=True)
def _catalogue(made, monkeypatch):
    monkeypatch.setenv("LASAGNA_LAYERS", str(made["layers"]))


def _copy(made, kind: str, tmp_path: Path) -> Path:
    return shutil.copytree(made[kind], tmp_path / kind)


def _edit_layer(folder: Path, change) -> None:
    doc = json.loads((folder / "stack.json").read_text(encoding="utf-8"))
    change(doc["layers"][1])
    (folder / "stack.json").write_text(json.dumps(doc), encoding="utf-8")


def _render(capsys, folder: Path) -> tuple[int, str]:
    before = (folder / "layers" / "shading-left.png").read_bytes()
    code = main(["render", str(folder), "--all"])
    err = capsys.readouterr().err
    if code != 0:
        assert (folder / "layers" / "shading-left.png").read_bytes() == before  # nothing written
    return code, err


def _refused(capsys, folder: Path, *parts: str) -> str:
    code, err = _render(capsys, folder)
    errors = [line for line in err.splitlines() if "error:" in line]
    assert code == 2 and len(errors) == 1, err
    assert "internal error" not in err and "Traceback" not in err, err
    for part in parts:
        assert part in errors[0], (part, err)
    return errors[0]


def test_the_made_stacks_render(made, tmp_path, capsys):
    for kind in ("free", "amortised"):
        code, err = _render(capsys, _copy(made, kind, tmp_path))
        assert code == 0, err


@pytest.mark.parametrize(
    "path, value",
    [
        (("settings", "optimize"), 10**9),
        (("settings", "distill", "early_stop", "min_steps"), 10**9),
        (("settings", "distill", "steps"), MAX_DISTILL_STEPS + 1),
        (("settings", "distill", "patches", "per_step"), 10**6),
    ],
)
def test_steps_past_the_limit_are_refused(made, tmp_path, capsys, path, value):
    folder = _copy(made, "free", tmp_path)

    def change(layer):
        node = layer
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value

    _edit_layer(folder, change)
    _refused(capsys, folder, path[-1], "less than or equal to")


def test_steps_at_the_limit_are_accepted_by_the_document(made, tmp_path):
    from lasagna.learned import LayerSettings

    LayerSettings.model_validate({"method": "per-image", "optimize": MAX_DISTILL_STEPS})
    with pytest.raises(ValueError):
        LayerSettings.model_validate({"method": "per-image", "optimize": MAX_DISTILL_STEPS + 1})


def test_priors_outside_the_stack_folder_are_refused_alike(made, tmp_path, capsys):
    real_prior = made["layers"] / "relight-32"
    assert real_prior.is_dir()
    refs = ["/etc", "../x", str(real_prior), "/no/such/prior", "..\\x", "C:/prior", "sub/../../x"]
    messages = {}
    for n, ref in enumerate(refs):
        folder = _copy(made, "free", tmp_path / str(n))
        _edit_layer(folder, lambda layer: layer["settings"].__setitem__("prior", ref))
        message = _refused(capsys, folder, "settings.prior", "expected")
        messages[ref] = message.replace(repr(ref), "REF").replace(str(folder), "FOLDER")
    # One message for all: a refusal that depended on the path existing would tell what is outside.
    assert len(set(messages.values())) == 1, messages
    assert "is not a catalogue name or a relative path inside the stack folder" in messages["/etc"]


def test_a_reordered_vocabulary_is_refused(made, tmp_path, capsys):
    folder = _copy(made, "amortised", tmp_path)
    config_file = folder / "generators" / "shading-left" / "config.json"
    config = json.loads(config_file.read_text())
    assert len(config["config"]["vocabulary"]) > 1
    config["config"]["vocabulary"] = config["config"]["vocabulary"][::-1]
    config_file.write_text(json.dumps(config))
    _refused(capsys, folder, "config.json does not match the recorded config_sha256", "generator.config_sha256")


def test_a_huge_generator_config_is_one_line(made, tmp_path, capsys):
    folder = _copy(made, "amortised", tmp_path)
    config_file = folder / "generators" / "shading-left" / "config.json"
    config = json.loads(config_file.read_text())
    config["config"]["channels"] = [100000]
    config_file.write_text(json.dumps(config))
    _edit_layer(folder, lambda layer: layer["generator"].pop("config_sha256"))
    message = _refused(capsys, folder)
    assert "channels" in message or "widths" in message, message
