"""Bring your own prior (issue #15), end to end on toy random Stable-Diffusion pipelines saved to disk as a
user's checkpoint would be (``tests.support.toydiffusers``; nothing is downloaded): ``lasagna edit --prior`` with
ControlNets, prompts and a control image, the API's ``edit(prior=…)``, ``lasagna train-corrective`` on a
diffusers folder and LMC-SDS with it, ``lasagna prior add`` then ``--layer NAME``, provenance and
``lasagna render``'s warning, aspect kept, and every bad input as one line with exit status 2.
"""

from __future__ import annotations

import json
import os
import sys

import numpy as np
import pytest
import torch

pytest.importorskip("diffusers", reason="diffusers is not installed (optional extra lasagna-layers[diffusers])")

from lasagna.cli import main  # noqa: E402
from lasagna.io.png import write_png  # noqa: E402
from tests.support.toydiffusers import controlnet_for, save_controlnet, save_pipeline, sd_parts, sdxl_parts  # noqa: E402

STEPS = "2"


def run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def disk(tmp_path_factory):
    """A user's disk: an SD 1.x-style folder, two ControlNets, an SDXL-style folder, a 24×16 photo."""
    root = tmp_path_factory.mktemp("models")
    parts = sd_parts()
    sd = save_pipeline(root / "sd", parts)
    cn1 = save_controlnet(root / "cn-a", parts["controlnet"])
    cn2 = save_controlnet(root / "cn-b", controlnet_for(parts["unet"], seed=5))
    xl = save_pipeline(root / "sdxl", sdxl_parts())
    rng = np.random.default_rng(0)
    photo = root / "photo.png"
    write_png(photo, rng.uniform(0.1, 0.9, (3, 16, 24)).astype(np.float32))
    depth = root / "depth.png"
    write_png(depth, np.linspace(0, 1, 48 * 32, dtype=np.float32).reshape(1, 32, 48).repeat(3, 0))
    photos = root / "photos"
    photos.mkdir()
    for i in range(3):
        write_png(photos / f"{i}.png", rng.uniform(0, 1, (3, 20, 20)).astype(np.float32))
    return dict(root=root, sd=sd, cn1=cn1, cn2=cn2, xl=xl, photo=photo, depth=depth, photos=photos)


@pytest.fixture(autouse=True)
def user_catalogue(tmp_path, monkeypatch):
    """A user catalogue of this test's own (nothing written to the real home)."""
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")


def stack_layer(out) -> dict:
    doc = json.loads((out / "stack.json").read_text())
    return doc["layers"][-1]


class TestEditWithOwnPrior:
    def test_cli_two_controlnets_prompts_control_image_non_square(self, disk, tmp_path, capsys):
        out = tmp_path / "out"
        code, stdout, err = run(
            capsys,
            "edit", disk["photo"], "--prior", disk["sd"],
            "--controlnet", disk["cn1"], "--controlnet", disk["cn2"],
            "--controlnet-scale", "0.5", "--controlnet-scale", "1.5",
            "--control-image", disk["depth"],
            "--prompt", "dramatic rim light", "--negative-prompt", "blurry",
            "--optimize", STEPS, "--t-min", "0.1", "--t-max", "0.9", "--no-ora", "-o", out,
        )  # fmt: skip
        assert code == 0, err
        layer = stack_layer(out)
        assert layer["condition"] == {"label": "prompt", "prompt": "dramatic rim light", "negative_prompt": "blurry"}
        s = layer["settings"]
        assert s["prior"] == str(disk["sd"].resolve()) and s["distill"]["loss"] == "sds"  # no corrective: SDS
        assert [c["scale"] for c in s["controlnets"]] == [0.5, 1.5]
        assert (s["distill"]["t_min"], s["distill"]["t_max"], s["distill"]["aspect"]) == (0.1, 0.9, "letterbox")
        names = set(s["weights"])
        assert {"prior/unet/diffusion_pytorch_model.safetensors", "prior/text_encoder/model.safetensors"} <= names
        assert {"controlnet0/diffusion_pytorch_model.safetensors", "controlnet1/config.json"} <= names
        assert s["control_image"] == f"controls/{layer['id']}.png" and (out / s["control_image"]).is_file()
        from lasagna.io.png import read_png

        assert read_png(out / layer["source"]).color.shape[-2:] == (16, 24)  # the photo's size and aspect

    def test_api_prior_and_an_sdxl_folder(self, disk):
        from lasagna.api import edit

        res = edit(disk["photo"], "shading", prior=disk["xl"], prompt="warm glow", optimize=1)
        assert res.layer.shape == (1, 16, 24) and torch.isfinite(res.layer).all()
        assert res.settings["diffusers"]["torch_dtype"] == "auto"
        assert "prior/text_encoder_2/model.safetensors" in res.settings["weights"]

    def test_labels_fill_the_template_without_a_prompt(self, disk):
        from lasagna.api import edit

        res = edit(disk["photo"], "shading", "top", prior=disk["sd"], optimize=1, aspect="stretch")
        assert res.layer_id == "shading-top" and res.settings["distill"]["aspect"] == "stretch"

    def test_lmc_sds_after_train_corrective(self, disk, tmp_path, capsys):
        runs = tmp_path / "b"
        code, stdout, err = run(
            capsys,
            "train-corrective", "--kind", "spectral", "--prior", disk["sd"], "--controlnet", disk["cn1"],
            "--images", disk["photos"], "--out", runs, "--batches", "1", "--buckets", "2",
            "--batch-size", "2", "--eval-batches", "1",
        )  # fmt: skip
        assert code == 0, err
        assert json.loads(stdout)["kind"] == "spectral" and (runs / "corrective" / "config.json").is_file()
        out = tmp_path / "lmc"
        code, _, err = run(
            capsys,
            "edit", disk["photo"], "--prior", disk["sd"], "--controlnet", disk["cn1"],
            "--corrective", runs / "corrective", "--condition", "left", "--optimize", STEPS, "--no-ora", "-o", out,
        )  # fmt: skip
        assert code == 0, err
        s = stack_layer(out)["settings"]
        assert s["distill"]["loss"] == "lmc-sds"  # the shading preset's loss, now that a corrective is given
        assert s["corrective"] == str((runs / "corrective").resolve())
        assert "corrective/model.safetensors" in s["weights"]


class TestPriorAdd:
    def test_add_then_layer_then_render_warns_on_changed_weights(self, disk, tmp_path, capsys, monkeypatch):
        catalogue = tmp_path / "cat"
        monkeypatch.setenv("LASAGNA_LAYERS", str(catalogue))
        sd = tmp_path / "sd-copy"
        import shutil

        shutil.copytree(disk["sd"], sd)
        code, stdout, err = run(
            capsys, "prior", "add", sd, "--name", "my-sd", "--controlnet", disk["cn1"], "--vocabulary", "left,right"
        )
        assert code == 0, err
        assert "lasagna edit IMAGE --layer my-sd" in stdout
        preset = json.loads((catalogue / "my-sd" / "preset.json").read_text())
        assert preset["prior"] == "my-sd" and preset["vocabulary"] == ["left", "right"]
        assert preset["distill"]["loss"] == "sds" and preset["method"] == "per-image"
        code, _, err = run(capsys, "prior", "add", sd, "--name", "my-sd")
        assert code == 2 and "already exist" in err and err.count("\n") == 1
        out = tmp_path / "out"
        code, _, err = run(capsys, "edit", disk["photo"], "--layer", "my-sd", "--condition", "right",
                           "--optimize", STEPS, "--no-ora", "-o", out)  # fmt: skip
        assert code == 0, err
        s = stack_layer(out)["settings"]
        assert s["prior"] == "my-sd" and "controlnet0/diffusion_pytorch_model.safetensors" in s["weights"]
        code, _, err = run(capsys, "render", out, "--all")
        assert code == 0 and "warning" not in err
        weights = sd / "unet" / "diffusion_pytorch_model.safetensors"
        weights.write_bytes(weights.read_bytes())  # same bytes: no warning
        with open(sd / "scheduler" / "scheduler_config.json", "a") as fh:
            fh.write("\n")  # a changed file
        code, _, err = run(capsys, "render", out, "--all")
        assert code == 0, err
        lines = [line for line in err.splitlines() if "warning" in line]
        assert len(lines) == 1 and "prior/scheduler/scheduler_config.json differs" in lines[0]

    def test_add_a_unet_prior_is_refused(self, tmp_path, capsys):
        from pathlib import Path

        unet_prior = Path(__file__).resolve().parents[1] / "layers" / "relight-32"
        code, _, err = run(capsys, "prior", "add", unet_prior, "--name", "x", "--catalogue", tmp_path)
        assert code == 2 and "expected a diffusers folder" in err


class TestOneLineErrors:
    @pytest.mark.parametrize(
        "extra, match",
        [
            (["--controlnet", "{cn1}"], "expected --prior PATH too"),
            (["--prior", "{root}/nope"], "prior path"),
            (["--prior", "{sd}", "--controlnet", "{root}/nope"], "expected a ControlNet folder"),
            (["--prior", "{sd}", "--loss", "lmc-sds"], "expected --corrective PATH"),
            (["--prior", "{sd}", "--control-image", "{photos}/0.png"], "expected the aspect"),
            (["--prior", "{sd}", "--variant", "fp16"], "cannot load the unet"),
            (["--prior", "{sd}", "--generator", "amortised"], "expected --generator free"),
            (["--prompt", "rim light"], "free text needs a text-conditioned"),
            (["--prior", "{sd}", "--device", "cuda"], "no CUDA device"),
        ],
    )
    def test_bad_input(self, disk, tmp_path, capsys, extra, match):
        if match == "no CUDA device" and torch.cuda.is_available():
            pytest.skip("this machine has CUDA")
        args = [a.format(**{k: str(v) for k, v in disk.items()}) for a in extra]
        code, _, err = run(capsys, "edit", disk["photo"], *args, "--optimize", "1", "-o", tmp_path / "o")
        assert code == 2, err
        assert match in err and err.count("\n") == 1 and "internal error" not in err
        assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_api_device_without_cuda_is_one_line(disk):
    from lasagna.api import edit
    from lasagna.errors import LasagnaError

    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    with pytest.raises(LasagnaError, match="device: 'cuda': this machine has no CUDA device"):
        edit(disk["photo"], "shading", prior=disk["sd"], device="cuda")


def test_letterbox_keeps_the_aspect():
    from lasagna.distill.objective import LETTERBOX_FILL, letterbox

    x = torch.rand(1, 3, 16, 32, requires_grad=True)
    y = letterbox(x, (16, 16))
    assert y.shape == (1, 3, 16, 16)
    assert torch.all(y[:, :, :4] == LETTERBOX_FILL) and torch.all(y[:, :, 12:] == LETTERBOX_FILL)
    y.sum().backward()
    assert torch.allclose(x.grad, torch.full_like(x.grad, 0.25))  # area-averaged 2×2: every pixel counts once
    assert os.environ.get("HF_HUB_OFFLINE") == "1"


class TestWithoutTheDiffusersExtra:
    """Without diffusers installed, every way to a diffusers prior is one line naming the extra (issue 27)."""

    @pytest.fixture(autouse=True)
    def no_diffusers(self, monkeypatch):
        for module in ("diffusers", "transformers"):  # None in sys.modules: find_spec gives None, import fails
            monkeypatch.setitem(sys.modules, module, None)

    @staticmethod
    def names_the_extra(code: int, err: str) -> bool:
        return code == 2 and "pip install 'lasagna-layers[diffusers]'" in err and err.count("\n") == 1

    def test_edit_prior(self, disk, tmp_path, capsys):
        out = tmp_path / "o"
        code, _, err = run(capsys, "edit", disk["photo"], "--prior", disk["sd"], "--optimize", "1", "-o", out)
        assert self.names_the_extra(code, err), err
        assert "internal error" not in err and not out.exists()

    def test_added_preset_is_not_ready_and_edit_names_the_extra(self, disk, tmp_path, capsys, monkeypatch):
        monkeypatch.setenv("LASAGNA_LAYERS", str(tmp_path / "cat"))
        code, _, err = run(capsys, "prior", "add", disk["sd"], "--name", "my-sd")
        assert code == 0, err
        code, stdout, err = run(capsys, "layers")
        assert code == 0, err
        line = next(line for line in stdout.splitlines() if line.strip().startswith("my-sd:"))
        assert "not usable" in line and "lasagna-layers[diffusers]" in line
        code, _, err = run(capsys, "edit", disk["photo"], "--layer", "my-sd", "--condition", "left",
                           "--optimize", "1", "-o", tmp_path / "o")  # fmt: skip
        assert self.names_the_extra(code, err), err

    def test_train_corrective_prior(self, disk, tmp_path, capsys):
        code, _, err = run(
            capsys, "train-corrective", "--kind", "spectral", "--prior", disk["sd"], "--images", disk["photos"],
            "--out", tmp_path / "b", "--batches", "1", "--buckets", "2", "--batch-size", "2",
        )  # fmt: skip
        assert self.names_the_extra(code, err), err

    def test_status_looks_without_importing(self, disk, tmp_path, monkeypatch):
        from lasagna import catalogue

        catalogue.add_prior(disk["sd"], name="mine", catalogue=tmp_path / "cat")
        status = catalogue.preset_status("mine", catalogue_dirs=[tmp_path / "cat"])
        assert not status["usable"] and "diffusers extra" in status["why"]
        monkeypatch.delitem(sys.modules, "diffusers")
        monkeypatch.setattr("importlib.util.find_spec", lambda name, package=None: object())  # installed after all
        assert catalogue.preset_status("mine", catalogue_dirs=[tmp_path / "cat"])["usable"]
