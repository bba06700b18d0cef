"""The decisions of issue 13 about learned layers, each tested: one method vocabulary (``free`` accepted as
``per-image``), the typed settings model (JSON identical to what a stack stores), one steps argument
(``optimize``; ``steps`` deprecated), and ``train-layer --guidance 0`` refused in one line, not replaced."""

from __future__ import annotations

import json

import pytest

from lasagna.cli import main
from lasagna.editing import edit
from lasagna.errors import DocumentError, LasagnaError
from lasagna.learned import METHODS, LayerSettings, canonical_method
from tests.support.tinylayers import ROOT

PHOTO = ROOT / "examples" / "photos" / "coffee.png"


@pytest.fixture(autouse=True)
def _catalogue(tiny, monkeypatch):
    monkeypatch.setenv("LASAGNA_LAYERS", str(tiny))


def test_one_method_vocabulary_with_free_as_an_alias():
    assert METHODS == ("amortised", "per-image")
    assert canonical_method("free") == "per-image" and canonical_method("per-image") == "per-image"
    with pytest.raises(LasagnaError, match="method is 'magic'; expected one of amortised, per-image"):
        canonical_method("magic")
    assert LayerSettings.parse({"method": "free"}, "layer 'x'").method == "per-image"


def test_settings_model_round_trips_the_stored_json(tmp_path):
    a = edit(PHOTO, "shading", "left", generator="per-image", optimize=2, seed=1)
    assert a.settings["method"] == "per-image" and list(a.settings) == [
        "method",
        "optimize",
        "prior",
        "prior_sha256",
        "corrective",
        "weights",
        "distill",
        "working_size",
    ]
    assert set(a.settings["weights"]) == {"prior/model.safetensors", "prior/config.json"}
    assert a.settings["weights"]["prior/model.safetensors"] == a.settings["prior_sha256"]
    assert LayerSettings.parse(a.settings, "here").to_json() == a.settings
    b = edit(PHOTO, "shading", "left")
    side = json.loads((ROOT / "layers" / "shading" / "preset.json").read_text(encoding="utf-8"))["working_size"]
    assert b.settings == {"method": "amortised", "optimize": 0, "working_size": side}
    assert LayerSettings.parse(b.settings, "here").to_json() == b.settings
    assert LayerSettings.parse({}, "here").to_json() == {"method": None, "optimize": None}


@pytest.mark.parametrize(
    "settings,where",
    [
        ({"method": "quick"}, "layer 'x': settings.method"),
        ({"optimize": -1}, "layer 'x': settings.optimize"),
        ({"optimize": True}, "layer 'x': settings.optimize"),
        ({"distill": 3}, "layer 'x': settings.distill"),
        ({"distill": {"guidance": 0}}, "layer 'x': settings.distill.layer"),  # the first of two errors
        ({"colour": "red"}, "layer 'x': settings.colour"),
    ],
)
def test_bad_settings_are_one_document_error_naming_the_field(settings, where):
    with pytest.raises(DocumentError) as err:
        LayerSettings.parse(settings, "layer 'x'")
    assert err.value.where == where and "\n" not in str(err.value)


def test_optimize_is_the_steps_argument_and_steps_is_deprecated():
    with pytest.warns(DeprecationWarning, match=r"edit\(steps=N\) is deprecated; use optimize=N"):
        old = edit(PHOTO, "shading", "top", generator="free", steps=2, seed=3)
    new = edit(PHOTO, "shading", "top", generator="free", optimize=2, seed=3)
    assert old.settings == new.settings and old.settings["optimize"] == 2 and len(new.history) <= 2
    with pytest.warns(DeprecationWarning), pytest.raises(LasagnaError, match="optimize 2 and steps 3 differ"):
        edit(PHOTO, "shading", "top", optimize=2, steps=3)


def test_train_layer_guidance_zero_is_refused_in_one_line(tmp_path, capsys):
    code = main(
        ["train-layer", "--preset", "shading", "--guidance", "0", "--steps", "1", "--out", str(tmp_path / "run")]
    )
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1
    assert err.startswith("lasagna: error: train-layer.guidance: got 0.0; expected greater than 0")
    assert not (tmp_path / "run").exists()


def test_train_layer_guidance_given_is_the_runs_omega(tmp_path, capsys):
    out = tmp_path / "run"
    code = main(
        [
            "train-layer",
            "--preset",
            "shading",
            "--guidance",
            "2.5",
            "--steps",
            "1",
            "--batch-size",
            "2",
            "--resolution",
            "8",
            "--channels",
            "4,8",
            "--out",
            str(out),
        ]
    )
    assert code == 0, capsys.readouterr().err
    assert json.loads((out / "train_config.json").read_text())["guidance"] == 2.5
