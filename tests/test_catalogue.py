"""lasagna.catalogue: search order, each kind found by name, paths, loading, and errors that list what exists."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

from lasagna import catalogue as cat
from lasagna.components import check_generator
from lasagna.errors import ConditionError, LasagnaError
from lasagna.learned import choose_method
from tests.support.tinylayers import ROOT


def _preset_copy(folder: Path, name: str = "shading", **changes) -> Path:
    data = json.loads((ROOT / "layers" / "shading" / "preset.json").read_text(encoding="utf-8"))
    data.update(name=name, **changes)
    (folder / name).mkdir(parents=True, exist_ok=True)
    (folder / name / "preset.json").write_text(json.dumps(data), encoding="utf-8")
    return folder / name / "preset.json"


# ---- search order -----------------------------------------------------------------------------------


def test_env_folders_come_first_then_checkout(tmp_path, monkeypatch):
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir(), b.mkdir()
    monkeypatch.setenv(
        "LASAGNA_LAYERS", f"{a}{__import__('os').pathsep}{tmp_path / 'missing'}{__import__('os').pathsep}{b}"
    )
    found = cat.catalogues()
    assert found[:2] == [a, b]  # a folder that does not exist is left out
    assert (ROOT / "layers").resolve() in [p.resolve() for p in found[2:]]


def test_a_folder_reached_twice_is_listed_once(tmp_path, monkeypatch):
    monkeypatch.setenv("LASAGNA_LAYERS", str(ROOT / "layers"))
    resolved = [p.resolve() for p in cat.catalogues()]
    assert resolved.count((ROOT / "layers").resolve()) == 1


def test_first_catalogue_wins(tmp_path):
    first = _preset_copy(tmp_path / "one", description="first one")
    _preset_copy(tmp_path / "two", description="second one")
    assert cat.find("shading", catalogue_dirs=[tmp_path / "one", tmp_path / "two"]) == first
    assert cat.load_preset("shading", catalogue_dirs=[tmp_path / "two", tmp_path / "one"]).description == "second one"


def test_preset_shipped_in_a_stack_wins(tmp_path, tiny):
    shipped = _preset_copy(tmp_path / "stack" / "layers", description="shipped with the stack")
    assert cat.find("shading", stack_dir=tmp_path / "stack", catalogue_dirs=[tiny]) == shipped
    assert cat.find("shading", catalogue_dirs=[tiny]) == tiny / "shading" / "preset.json"


# ---- kinds ------------------------------------------------------------------------------------------


def test_available_lists_every_kind(tiny):
    assert cat.available(catalogue_dirs=[tiny]) == {
        "preset": ["color", "light", "relight", "shading"],
        "prior": ["light-32", "recolor-32", "relight-32", "relit-32"],
        "corrective": ["light-32-spectral", "recolor-32-spectral", "relight-32-bhat", "relight-32-spectral"],
        "generator": ["shading"],
        "estimator": ["surface-albedo-32", "surface-lit-32", "surface-lit-closeup-32", "surface-lit-told-32"],
    }


@pytest.mark.parametrize(
    "name, kind, relative",
    [
        ("shading", "preset", "shading/preset.json"),
        ("relight-32", "prior", "relight-32"),
        ("relight-32-bhat", "corrective", "relight-32-bhat"),
        ("relight-32-spectral", "corrective", "relight-32-spectral"),
        ("shading", "generator", "shading/generator"),
    ],
)
def test_find_each_kind(tiny, name, kind, relative):
    assert cat.find(name, kind, catalogue_dirs=[tiny]) == tiny / relative


def test_an_entry_of_another_kind_is_not_found(tiny):
    with pytest.raises(LasagnaError, match="no prior named 'relight-32-bhat'"):
        cat.find("relight-32-bhat", "prior", catalogue_dirs=[tiny])
    assert cat.locate("color", "generator", catalogue_dirs=[tiny]) is None  # the colour preset has no generator


def test_diffusers_folder_counts_as_a_prior(tmp_path):
    for sub in ("unet", "scheduler"):
        (tmp_path / "sd" / sub).mkdir(parents=True)
    assert cat.entry_kinds(tmp_path / "sd") == {"prior"}
    with pytest.raises(LasagnaError, match="needs the preset"):
        cat.load_prior("sd", catalogue_dirs=[tmp_path])


def test_unrelated_config_is_no_kind(tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "config.json").write_text('{"format": "something.else"}')
    (tmp_path / "y").mkdir()
    (tmp_path / "y" / "config.json").write_text("{not json")
    assert cat.entry_kinds(tmp_path / "x") == set() and cat.entry_kinds(tmp_path / "y") == set()
    assert cat.available(catalogue_dirs=[tmp_path]) == {k: [] for k in cat.KINDS}


# ---- errors -----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kind, listed",
    [
        ("preset", "color, light, relight, shading"),
        ("prior", "light-32, recolor-32, relight-32, relit-32"),
        ("corrective", "light-32-spectral, recolor-32-spectral, relight-32-bhat, relight-32-spectral"),
        ("generator", "shading"),
    ],
)
def test_unknown_name_lists_what_exists(tiny, kind, listed):
    with pytest.raises(LasagnaError) as err:
        cat.find("nope", kind, catalogue_dirs=[tiny])
    msg = str(err.value)
    assert msg.startswith(f"{kind}: no {kind} named 'nope' in {tiny}") and f"expected one of {listed}" in msg
    assert "\n" not in msg


def test_empty_catalogue_says_none_found(tmp_path):
    with pytest.raises(LasagnaError, match=r"expected one of \(none found\) \(train one: lasagna train-prior\)"):
        cat.find("relight-32", "prior", catalogue_dirs=[tmp_path])


@pytest.mark.parametrize("name", ["", "bad name", "-x", "con", "a" * 65])
def test_malformed_name(tiny, name):
    with pytest.raises(LasagnaError, match="ids match|reserved"):
        cat.find(name, catalogue_dirs=[tiny])


def test_unknown_kind(tiny):
    with pytest.raises(LasagnaError, match="unknown kind 'model'; expected one of preset, prior"):
        cat.find("shading", "model", catalogue_dirs=[tiny])  # type: ignore[arg-type]


def test_missing_path(tmp_path):
    with pytest.raises(LasagnaError, match="does not exist"):
        cat.find(tmp_path / "nowhere", "prior")


# ---- paths and resolution ---------------------------------------------------------------------------


def test_path_reference(tiny):
    assert cat.find(Path(tiny / "relight-32"), "prior") == tiny / "relight-32"
    assert cat.find("./shading", "preset", relative_to=tiny) == tiny / "shading" / "preset.json"


def test_resolve_names_every_part(tiny):
    parts = cat.resolve("shading", catalogue_dirs=[tiny])
    assert parts.preset.name == "shading" and parts.preset_file == tiny / "shading" / "preset.json"
    assert (parts.prior, parts.corrective, parts.generator) == (
        tiny / "relight-32",
        tiny / "relight-32-spectral",
        tiny / "shading" / "generator",
    )
    colour = cat.resolve("color", catalogue_dirs=[tiny])
    assert (
        colour.prior == tiny / "recolor-32"
        and colour.corrective == tiny / "recolor-32-spectral"
        and colour.generator is None
    )


def test_resolve_without_prior(tmp_path):
    _preset_copy(tmp_path)
    with pytest.raises(LasagnaError, match="no prior named 'relight-32'"):
        cat.resolve("shading", catalogue_dirs=[tmp_path])
    parts = cat.resolve("shading", catalogue_dirs=[tmp_path], need_prior=False)
    # Never an unresolved path: None, the reference, and the error a caller that needs the prior raises (#26).
    assert parts.prior is None and parts.prior_ref == "relight-32" and parts.corrective is None
    assert "no prior named 'relight-32'" in str(parts.missing["prior"])


def test_prior_path_relative_to_the_preset(tmp_path, tiny):
    _preset_copy(tmp_path, prior="./weights", corrective="./bhat")
    shutil.copytree(tiny / "relight-32", tmp_path / "shading" / "weights")
    shutil.copytree(tiny / "relight-32-spectral", tmp_path / "shading" / "bhat")
    parts = cat.resolve("shading", catalogue_dirs=[tmp_path])
    assert parts.prior == tmp_path / "shading" / "weights" and parts.corrective == tmp_path / "shading" / "bhat"
    prior = cat.load_prior(parts.prior)
    assert prior.sample_shape == (3, 8, 8)


# ---- loading ----------------------------------------------------------------------------------------


def test_load_each_kind(tiny):
    from lasagna.generators.unet import LayerGenerator
    from lasagna.losses.corrective import Corrective
    from lasagna.priors.unet import UNetPrior

    prior = cat.load_prior("relight-32", catalogue_dirs=[tiny])
    corrective = cat.load_corrective("relight-32-bhat", catalogue_dirs=[tiny])
    preset = cat.load_preset("shading", catalogue_dirs=[tiny])
    gen = cat.load_generator("shading", preset=preset, catalogue_dirs=[tiny])
    assert isinstance(prior, UNetPrior) and isinstance(corrective, Corrective) and isinstance(gen, LayerGenerator)
    assert not (prior.training or corrective.training or gen.training)
    from lasagna.losses.spectral import SpectralCorrective

    spectral = cat.load_corrective("relight-32-spectral", catalogue_dirs=[tiny])  # dispatched by its config's format
    assert isinstance(spectral, SpectralCorrective) and not spectral.training
    with torch.no_grad():
        y = gen(torch.rand(1, 3, 12, 20), ["left"])
    assert y.shape == (1, 1, 12, 20) and float(y.min()) >= 0.0 and float(y.max()) <= 2.0


def test_generator_for_another_preset_is_refused(tiny):
    colour = cat.load_preset("color", catalogue_dirs=[tiny])
    with pytest.raises(
        LasagnaError, match=r"expected the normal layer of 4 channel\(s\) in \[0.0, 1.0\] of preset 'color'"
    ):
        cat.load_generator("shading", preset=colour, catalogue_dirs=[tiny])


def test_generator_missing_labels_is_refused(tiny, tmp_path):
    from lasagna.generators.unet import LayerGenerator

    gen = LayerGenerator.from_pretrained(tiny / "shading" / "generator")
    preset = cat.load_preset("shading", catalogue_dirs=[tiny])
    small = preset.model_copy(update={"vocabulary": (*preset.vocabulary, "sunset")})
    with pytest.raises(LasagnaError, match="does not know label\\(s\\) sunset"):
        check_generator(gen, small, "here")
    with pytest.raises(ConditionError, match="unknown label 'sunset'"):
        gen(torch.rand(1, 3, 8, 8), ["sunset"])


def test_wrong_format_is_not_loaded_as_a_prior(tiny):
    with pytest.raises(LasagnaError, match="no prior named 'relight-32-bhat'"):
        cat.load_prior("relight-32-bhat", catalogue_dirs=[tiny])


# ---- readiness --------------------------------------------------------------------------------------


def test_preset_status(tmp_path, tiny):
    assert cat.preset_status("shading", catalogue_dirs=[tiny])["method"] == "amortised"
    colour = cat.preset_status("color", catalogue_dirs=[tiny])
    assert colour["usable"] and colour["method"] == "per-image"
    other = shutil.copytree(tiny, tmp_path / "layers")
    _preset_copy(other, method="per-image", layer_kind="free")  # asks for per-image: keeps it, generator or not
    st = cat.preset_status("shading", catalogue_dirs=[other])
    assert (other / "shading" / "generator").is_dir() and st["method"] == "per-image"
    assert st["amortised"]  # the generator stays one click away (the editor's "Add (amortised)")
    assert st["method"] == choose_method(cat.resolve("shading", catalogue_dirs=[other]), None)
    shutil.rmtree(other / "shading" / "generator")
    assert not cat.preset_status("shading", catalogue_dirs=[other])["amortised"]
    _preset_copy(other, vocabulary=["left", "warm"], layer_kind="free")  # a label the prior was never trained on
    st = cat.preset_status("shading", catalogue_dirs=[other])
    assert not st["usable"] and "was not trained on warm" in st["why"] and "\n" not in st["why"]
    # The shipped shading preset's default is a surface: usable when its estimator is there, and said so.
    _preset_copy(other)
    st = cat.preset_status("shading", catalogue_dirs=[other])
    assert st["usable"] and st["method"] == "surface" and "surface-albedo-32" in st["why"]
    shutil.rmtree(other / "surface-albedo-32")
    st = cat.preset_status("shading", catalogue_dirs=[other])
    assert not st["usable"] and "surface estimator 'surface-albedo-32' is not in the catalogue" in st["why"]
    _preset_copy(other, prior="missing-prior", layer_kind="free")
    assert (
        cat.preset_status("shading", catalogue_dirs=[other])["why"]
        == "its prior 'missing-prior' is not in the catalogue"
    )
    shutil.rmtree(other / "relight-32-spectral")
    lmc = {
        **json.loads((ROOT / "layers" / "shading" / "preset.json").read_text(encoding="utf-8"))["distill"],
        "loss": "lmc-sds",
        "guidance": 3.0,
    }
    _preset_copy(other, distill=lmc, layer_kind="free")  # LMC-SDS needs its corrective
    st = cat.preset_status("shading", catalogue_dirs=[other])
    assert not st["usable"] and "corrective 'relight-32-spectral' is not in the catalogue" in st["why"]
    _preset_copy(other, distill={**lmc, "loss": "sds", "guidance": 1.0}, layer_kind="free")  # SDS does not
    assert cat.preset_status("shading", catalogue_dirs=[other])["usable"]
    assert cat.preset_status("nope", catalogue_dirs=[other])["usable"] is False


@pytest.mark.parametrize("preset", [None, 3, ["shading"]])
def test_a_preset_that_is_not_a_name_or_path_is_one_line(preset):
    with pytest.raises(LasagnaError, match=r"^preset: got \w+; expected a catalogue name or the path of a preset"):
        cat.resolve(preset)


def test_a_preset_object_is_refused_with_how_to_use_it(tmp_path):
    """api.edit(preset=Preset) raised a raw TypeError; it is one line saying what to pass instead, and the
    way it names works."""
    from lasagna.document.preset import load_preset

    p = load_preset(ROOT / "layers" / "shading")
    with pytest.raises(LasagnaError, match="got Preset; expected a catalogue name"):
        cat.resolve(p)
    (tmp_path / "shading").mkdir()
    (tmp_path / "shading" / "preset.json").write_text(p.to_json(), encoding="utf-8")
    assert cat.resolve(tmp_path / "shading" / "preset.json", need_prior=False).preset == p


# ---- broken entries (issue #28, 15) ----------------------------------------------------------------------


@pytest.mark.parametrize(
    "config,why",
    [
        ('{"format": {}}', "format is {}; expected a string"),
        ('{"format": []}', "format is []; expected a string"),
        ("[1, 2]", "holds a JSON list; expected an object"),
        ("[" * 100_000 + "]" * 100_000, "nested more than"),
        ("{not json", "config.json"),
    ],
)
def test_a_broken_entry_is_one_line_and_the_rest_are_listed(tmp_path, tiny, monkeypatch, capsys, config, why):
    from lasagna.cli import main

    broken = tmp_path / "extra" / "broken"
    broken.mkdir(parents=True)
    (broken / "config.json").write_text(config)
    monkeypatch.setenv("LASAGNA_LAYERS", f"{tmp_path / 'extra'}{__import__('os').pathsep}{tiny}")
    assert "shading" in cat.available()["preset"] and "broken" not in cat.available()["prior"]
    (line,) = cat.problems()
    assert line.startswith(f"{broken / 'config.json'}: ") and why in line and "\n" not in line
    assert main(["layers"]) == 0
    out = capsys.readouterr().out
    assert f"broken entry: {line}" in out and "shading" in out
    assert main(["layers", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["broken"] == [line]


def test_a_prior_vocabulary_of_the_wrong_type_does_not_break_the_status(tmp_path, tiny):
    shutil.copytree(tiny, tmp_path / "layers")
    config = tmp_path / "layers" / "relight-32" / "config.json"
    doc = json.loads(config.read_text())
    doc["config"]["vocabulary"] = 5
    config.write_text(json.dumps(doc))
    status = cat.preset_status("relight", [tmp_path / "layers"])
    assert set(status) == {"usable", "method", "amortised", "why"}


@pytest.mark.parametrize(
    "change,why",
    [
        ({"channels": [2**40]}, r"channels must lie in \[1, 1024\]"),
        ({"res_blocks": 10**6}, "config.res_blocks"),
        ({"channels": [8, 32]}, "has shape"),
        ({"res_blocks": 2}, "weights do not match the config"),
    ],
)
def test_a_unet_config_that_does_not_match_its_weights_is_one_line(tmp_path, tiny, capsys, change, why):
    """A UNetPrior whose config.json disagrees with its weights (or asks for an absurd network) is one line,
    before anything of that size is allocated; the CLI exits 2."""
    from lasagna.cli import main

    shutil.copytree(tiny / "relight-32", tmp_path / "relight-32")
    config = tmp_path / "relight-32" / "config.json"
    doc = json.loads(config.read_text())
    doc["config"].update(change)
    config.write_text(json.dumps(doc))
    with pytest.raises(LasagnaError, match=why):
        cat.load_prior(tmp_path / "relight-32")
    image = tmp_path / "in.png"
    from PIL import Image

    Image.new("RGB", (8, 8)).save(image)
    argv = ["edit", image, "--layer", "relight", "--prior", tmp_path / "relight-32", "--condition", "left"]
    code = main([str(a) for a in [*argv, "-o", tmp_path / "out", "--steps", "1"]])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "internal error" not in err, err


# ---- prior add: bounded copies that follow no link (issue #28, 9) -------------------------------------


def _fake_diffusers(folder: Path) -> Path:
    folder.mkdir(parents=True)
    (folder / "model_index.json").write_text("{}")  # all add_prior needs to see a diffusers folder
    return folder


def _corrective(folder: Path) -> Path:
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps({"format": "lasagna.corrective", "version": 1, "config": {}}))
    (folder / "model.safetensors").write_bytes(b"\0" * 64)
    return folder


@pytest.mark.parametrize("link", ["self", "parent", "dev-zero"])
def test_prior_add_refuses_a_corrective_holding_links(tmp_path, tiny, capsys, link):
    """Two links to the folder itself grew the copy exponentially; a link to /dev/zero filled the disk. Links
    inside the folder are refused, one line, and the catalogue is left as it was."""
    from lasagna.cli import main

    sd = _fake_diffusers(tmp_path / "sd")
    bhat = _corrective(tmp_path / "bhat")
    if link == "self":
        (bhat / "a").symlink_to(bhat)
        (bhat / "b").symlink_to(bhat)
    elif link == "parent":
        (bhat / "sub").mkdir()
        (bhat / "sub" / "up").symlink_to("..")
    else:
        (bhat / "zero.bin").symlink_to("/dev/zero")
    code = main(
        ["prior", "add", str(sd), "--name", "mine", "--corrective", str(bhat), "--catalogue", str(tmp_path / "c")]
    )
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "is a symbolic link; expected only folders and regular files (links are not followed)" in err
    assert list((tmp_path / "c").iterdir()) == []  # nothing staged is left behind


def test_prior_add_refuses_special_files_and_caps_the_copy(tmp_path, tiny, monkeypatch):
    import os

    from lasagna import atomic
    from lasagna.errors import PathError

    sd = _fake_diffusers(tmp_path / "sd")
    bhat = _corrective(tmp_path / "bhat")
    os.mkfifo(bhat / "pipe")
    with pytest.raises(PathError, match=r"pipe: is a named pipe \(FIFO\); expected only folders and regular files"):
        cat.add_prior(sd, "mine", corrective=bhat, catalogue=tmp_path / "c")
    (bhat / "pipe").unlink()
    monkeypatch.setattr(atomic.copy_tree, "__kwdefaults__", {"max_bytes": 300, "max_files": 1000})  # the caps
    (bhat / "big.bin").write_bytes(b"\0" * 300)
    with pytest.raises(PathError, match=r"bhat: holds more than 300 B; expected a smaller folder"):
        cat.add_prior(sd, "mine", corrective=bhat, catalogue=tmp_path / "c")
    (bhat / "big.bin").unlink()
    written = cat.add_prior(sd, "mine", corrective=bhat, catalogue=tmp_path / "c")
    copied = written.parent.parent / "mine-corrective"
    assert sorted(p.name for p in copied.iterdir()) == ["config.json", "model.safetensors"]
    assert [p.name for p in (tmp_path / "c").iterdir() if p.name.startswith(".")] == []


def test_prior_add_on_a_link_loop_is_one_line(tmp_path, capsys):
    from lasagna.cli import main

    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    code = main(["prior", "add", str(tmp_path / "a"), "--name", "mine", "--catalogue", str(tmp_path / "c")])
    err = capsys.readouterr().err
    assert code == 2 and err.strip().splitlines() == [
        f"lasagna: error: {tmp_path / 'a'}: cannot be resolved (symlink loop); expected a folder (not a link loop)"
    ]


class TestFindPreset:
    """``find`` for a preset: the one lookup (the document tier's ``resolve_preset`` was a second statement of it)."""

    CATALOGUE = ROOT / "layers"

    def test_catalogue_name(self):
        assert cat.find("shading", catalogue_dirs=[self.CATALOGUE]) == self.CATALOGUE / "shading" / "preset.json"

    def test_stack_local_preset_wins(self, tmp_path):
        local = tmp_path / "layers" / "shading"
        local.mkdir(parents=True)
        shutil.copy(self.CATALOGUE / "shading" / "preset.json", local / "preset.json")
        assert cat.find("shading", "preset", tmp_path, [self.CATALOGUE]) == local / "preset.json"

    def test_path_reference_is_relative_to_the_stack_folder(self, tmp_path):
        (tmp_path / "p").mkdir()
        (tmp_path / "p" / "mine.json").write_text("{}", encoding="utf-8")
        assert cat.find("./p/mine.json", "preset", tmp_path) == tmp_path / "./p/mine.json"
        assert cat.preset_path("./p/mine.json", tmp_path) == tmp_path / "./p/mine.json"
        with pytest.raises(LasagnaError, match="needs the stack folder"):
            cat.find("./p/mine.json")

    def test_unknown_name_lists_what_exists(self, tmp_path):
        with pytest.raises(cat.NotFound, match=r"no preset named 'shadow' .*; expected one of .*shading"):
            cat.find("shadow", "preset", tmp_path, [self.CATALOGUE])
        assert cat.locate("shadow", "preset", tmp_path, [self.CATALOGUE]) is None
        with pytest.raises(LasagnaError, match="'my preset'"):
            cat.locate("my preset")

    def test_environment_catalogue(self, tmp_path, monkeypatch):
        mine = _preset_copy(tmp_path, "mine")
        monkeypatch.setenv("LASAGNA_LAYERS", str(tmp_path))
        assert cat.find("mine") == mine
