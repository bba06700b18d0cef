"""World stacks on disk: re-composited by the engine and by an independent reference, they give composite.png."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest
import torch

from lasagna.errors import LasagnaError
from lasagna.world.export import TASKS, write_world_stacks
from lasagna.world.lighting import LIGHTS
from lasagna.world.scene import generate
from tests.support.reference import composite_reference, read_png64

RES, COUNT, SEED = 16, 2, 4


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    root = tmp_path_factory.mktemp("world")
    return {task: write_world_stacks(root / task, "train", COUNT, SEED, RES, task, start=3) for task in TASKS}


@pytest.fixture(scope="module")
def scene():
    return generate("train", COUNT, SEED, RES, start=3, dtype=torch.float64)  # as the export renders


def codes(values: np.ndarray) -> np.ndarray:
    return np.rint(np.clip(values, 0, 1) * 255).astype(int)


@pytest.mark.parametrize("task", TASKS)
def test_engine_recomposite_equals_composite_png(written, task):
    render = pytest.importorskip(
        "lasagna.io.render", reason="the document engine (lasagna.io.render) is not importable"
    )
    from lasagna.io.stack import load_stack

    for folder in written[task]:
        image = render.render_stack(load_stack(folder), dtype=torch.float64).image.numpy()
        stored, _ = read_png64(folder / "composite.png")
        assert np.abs(codes(image) - codes(stored)).max() <= 1, folder
        assert np.abs(image - stored).max() <= 1 / 255


@pytest.mark.parametrize("task", TASKS)
def test_reference_recomposite_equals_composite_png(written, task):
    for folder in written[task]:
        stored, _ = read_png64(folder / "composite.png")
        assert np.abs(composite_reference(folder) - stored).max() <= 1 / 255, folder


def test_composite_png_is_the_rendered_image(written, scene):
    for i, folder in enumerate(written["shading"]):
        stored, _ = read_png64(folder / "composite.png")
        assert np.array_equal(codes(stored), codes(scene.image[i].double().numpy()))


def test_shading_stack_layers_and_ground_truth(written, scene):
    for i, folder in enumerate(written["shading"]):
        doc = json.loads((folder / "stack.json").read_text())
        assert doc["blend_space"] == "srgb"
        layers = {layer["id"]: layer for layer in doc["layers"]}
        assert [layer["id"] for layer in doc["layers"]] == ["albedo", "shading"]
        assert layers["shading"]["blend"] == "multiply" and layers["shading"]["range"] == [0.0, 2.0]
        shade, _ = read_png64(folder / layers["shading"]["source"])
        assert shade.shape == (1, RES, RES)
        np.testing.assert_allclose(2.0 * shade[0], scene.shading[i, 0].numpy(), atol=1.01 / 65535)
        albedo, _ = read_png64(folder / layers["albedo"]["source"])
        np.testing.assert_allclose(albedo, scene.albedo[i].numpy(), atol=0.51 / 65535)
        normals, _ = read_png64(folder / "normals.png")
        np.testing.assert_allclose(2 * normals - 1, scene.normals[i].numpy(), atol=1.01 / 65535)
        mask, _ = read_png64(folder / "mask.png")
        assert np.array_equal(mask[0], scene.mask[i, 0].numpy())
        meta = doc["metadata"]["lasagna.world"]
        assert meta["label"] == scene.label[i] and meta["light"] == list(LIGHTS[scene.label[i]])
        assert meta["condition"] == scene.label[i]
        assert meta["index"] == 3 + i and meta["scene"]["split"] == "train"


def test_task_layers(written):
    blends = {"color": ["normal", "normal"], "light": ["normal", "plus"]}
    for task, expected in blends.items():
        doc = json.loads((written[task][0] / "stack.json").read_text())
        assert [layer["blend"] for layer in doc["layers"]] == expected
    _, alpha = read_png64(written["color"][0] / "layers" / "color.png")
    assert alpha is not None and (alpha == 1).all()


def test_manifest(written):
    m = json.loads((written["light"][0].parent / "world.json").read_text())
    assert m["task"] == "light" and m["count"] == COUNT and m["start"] == 3
    assert [s["folder"] for s in m["scenes"]] == ["train-s4-000003", "train-s4-000004"]
    # the light task's condition is the glow's colour label, the same one its scene parameters record
    for entry in m["scenes"]:
        meta = json.loads((written["light"][0].parent / entry["folder"] / "stack.json").read_text())["metadata"][
            "lasagna.world"
        ]
        assert entry["condition"] == meta["condition"] == meta["scene"]["glow"]["label"]
        assert entry["condition"] in ("warm", "cool", "white")


def test_bad_task(tmp_path):
    with pytest.raises(LasagnaError, match="task: unknown task 'depth'; expected one of shading, color, light"):
        write_world_stacks(tmp_path, "train", 1, task="depth")


class TestCli:
    def parse(self, argv):
        from lasagna.cli.world import add_world_parser

        ap = argparse.ArgumentParser()
        add_world_parser(ap.add_subparsers())
        return ap.parse_args(argv)

    def test_writes_stacks(self, tmp_path, capsys):
        args = self.parse(
            [
                "world",
                "-o",
                str(tmp_path),
                "--split",
                "heldout",
                "--count",
                "1",
                "--seed",
                "2",
                "--resolution",
                "8",
                "--task",
                "color",
            ]
        )
        assert args.run(args) == 0
        assert (tmp_path / "heldout-s2-000000" / "composite.png").is_file()
        assert "wrote 1 color stacks (heldout, seed 2, 8x8)" in capsys.readouterr().out

    @pytest.mark.parametrize(
        "flag,value,message",
        [
            ("--count", "0", "--count: expected a positive integer"),
            ("--resolution", "0", "resolution: expected an integer"),
            ("--seed", "-3", "--seed: expected a non-negative integer"),
        ],
    )
    def test_bad_numbers(self, tmp_path, flag, value, message):
        argv = ["world", "-o", str(tmp_path), "--split", "train", "--count", "1", flag, value]
        args = self.parse(argv)
        with pytest.raises(LasagnaError, match=message):
            args.run(args)
        assert not any(tmp_path.iterdir())
