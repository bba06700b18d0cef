"""Pattern fills (``compose/pattern.py``), kornia's template: smoke, shapes, exceptions, a numpy float64 reference
(Pillow's bilinear resampling written out as its triangle filter, and tiling pixel by pixel; not our code), Pillow
itself, NaN behaviour, gradcheck in float64; the layer kind's validation, round trip and ``lasagna validate``."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from PIL import Image

from lasagna.compose.pattern import pattern_fill, resample_tile
from lasagna.document import Document
from lasagna.errors import DocumentError, LasagnaError
from lasagna.io.png import read_png_header
from lasagna.io.render import render_stack
from lasagna.io.stack import Stack, load_stack
from lasagna.limits import MAX_PATTERN_PIXELS


def reference_resample(tile: np.ndarray, scale: float) -> np.ndarray:
    """Pillow's BILINEAR resize (``ImagingResample``), one axis then the other, in float64: output pixel i of n from
    m inputs has centre (i + ½)·m/n; the triangle filter's support is max(1, m/n) input pixels, its weights
    normalised over the inputs it reaches."""

    def axis(x: np.ndarray, n: int) -> np.ndarray:  # resample the last axis of x to n
        m = x.shape[-1]
        ratio = m / n
        support = max(1.0, ratio)
        out = np.zeros((*x.shape[:-1], n))
        for i in range(n):
            centre = (i + 0.5) * ratio
            js = np.arange(m)
            w = np.maximum(0.0, 1.0 - np.abs((js + 0.5 - centre) / support))
            out[..., i] = (x * w).sum(-1) / w.sum()
        return out

    h, w = tile.shape[-2:]
    sh, sw = max(1, int(h * (scale / 100.0))), max(1, int(w * (scale / 100.0)))
    return axis(axis(tile, sw).swapaxes(-1, -2), sh).swapaxes(-1, -2)


def reference_fill(tile: np.ndarray, scale: float, origin, viewport) -> np.ndarray:
    """Pixel by pixel: canvas pixel (x, y) of ``viewport`` reads the resampled tile at ((y − oy) mod th, (x − ox) mod
    tw)."""
    t = reference_resample(tile, scale)
    th, tw = t.shape[-2:]
    out = np.empty((tile.shape[0], viewport[3] - viewport[1], viewport[2] - viewport[0]))
    for j in range(out.shape[1]):
        for i in range(out.shape[2]):
            out[:, j, i] = t[:, (viewport[1] + j - origin[1]) % th, (viewport[0] + i - origin[0]) % tw]
    return out


def _tile(h=5, w=7, channels=4, seed=0) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    return torch.from_numpy(rng.integers(0, 256, (channels, h, w)) / 255.0)


class TestPatternFill:
    def test_smoke_and_shapes(self):
        t = _tile()
        color, alpha = pattern_fill(t[:3], t[3:], 100.0, (0, 0), (0, 0, 9, 4), (2, 1, 9, 4))
        assert color.shape == (3, 3, 7) and alpha.shape == (1, 3, 7) and color.dtype == torch.get_default_dtype()
        color, alpha = pattern_fill(t[:3], None, 250.0, (0, 0), (0, 0, 9, 4), (0, 0, 9, 4), torch.float64)
        assert color.shape == (3, 4, 9) and alpha is None and color.dtype == torch.float64

    @pytest.mark.parametrize("scale", [100.0, 87.0, 29.0, 170.0, 333.0, 1.0])
    @pytest.mark.parametrize("phase,anchor", [((0, 0), (0, 0, 30, 20)), ((3, -4), (5, 2, 17, 11))])
    def test_matches_the_reference(self, scale, phase, anchor):
        t = _tile(seed=int(scale))
        viewport = (4, 1, 31, 19)
        color, alpha = pattern_fill(t[:3], t[3:], scale, phase, anchor, viewport, torch.float64)
        origin = (anchor[0] + phase[0], anchor[1] + phase[1])
        ref = reference_fill(t.numpy(), scale, origin, viewport)
        assert np.abs(torch.cat([color, alpha]).numpy() - ref).max() < 1e-12

    @pytest.mark.parametrize("scale", [87.0, 170.0, 41.0])
    def test_resampling_is_pillows_bilinear(self, scale):
        # What psd-tools calls (``_resize_panel``): Pillow's float32 'F' resize, channel by channel.
        t = _tile(9, 13, 3, seed=1)
        ours = resample_tile(t, scale).numpy()
        sh, sw = ours.shape[-2:]
        pil = np.stack([np.asarray(Image.fromarray(c.astype(np.float32), "F").resize((sw, sh), Image.BILINEAR))
                        for c in t.numpy()])  # fmt: skip
        assert np.abs(ours - pil).max() < 1e-6

    def test_exceptions(self):
        t = _tile()
        with pytest.raises(LasagnaError, match="scale"):
            pattern_fill(t[:3], None, 0.0, (0, 0), (0, 0, 4, 4), (0, 0, 4, 4))
        with pytest.raises(LasagnaError, match="expected \\(C, th, tw\\)"):
            pattern_fill(t[:3, 0], None, 100.0, (0, 0), (0, 0, 4, 4), (0, 0, 4, 4))
        big = torch.zeros(3, 1, 1).expand(3, 4096, 4097)
        with pytest.raises(LasagnaError, match=f"at most {MAX_PATTERN_PIXELS} pixels"):
            pattern_fill(big, None, 100.0, (0, 0), (0, 0, 4, 4), (0, 0, 4, 4))
        with pytest.raises(LasagnaError, match="tile at 1000 %"):
            pattern_fill(torch.zeros(3, 500, 500), None, 1000.0, (0, 0), (0, 0, 4, 4), (0, 0, 4, 4))

    def test_nan_in_the_tile_stays_where_it_is_tiled(self):
        t = _tile()[:3].clone()
        t[:, 1, 2] = float("nan")
        color, _ = pattern_fill(t, None, 100.0, (0, 0), (0, 0, 14, 10), (0, 0, 14, 10), torch.float64)
        assert torch.isnan(color).any(dim=0).nonzero().tolist() == [[1, 2], [1, 9], [6, 2], [6, 9]]

    def test_gradcheck_in_the_tile(self):
        t = _tile(3, 4, 4).requires_grad_(True)

        def f(x):
            c, a = pattern_fill(x[:3], x[3:], 150.0, (1, 2), (0, 0, 7, 5), (0, 0, 7, 5), torch.float64)
            return torch.cat([c, a])

        assert torch.autograd.gradcheck(f, (t,))


W, H = 12, 9


def _doc(*layers) -> dict:
    base = {"id": "bg", "kind": "solid", "color": [0.5, 0.5, 0.5]}
    return {"format": "lasagna.stack", "version": 1, "canvas": {"width": W, "height": H}, "layers": [base, *layers]}


class TestPatternLayer:
    def _stack(self, **pattern) -> Stack:
        stack = Stack(Document.from_dict(_doc()))
        tile = (_tile(4, 5, 4, seed=2).numpy().transpose(1, 2, 0) * 255).round().astype(np.uint8)
        mask = np.random.default_rng(3).integers(0, 256, (6, 7), dtype=np.uint8)
        stack.add_pattern("p", tile, pattern, size=(7, 6), offset=(2, 1), mask=mask, blend="multiply", opacity=0.7)
        return stack

    @pytest.mark.parametrize("align", [True, False])
    def test_a_layer_composites_its_fill_with_mask_opacity_and_blend(self, align):
        stack = self._stack(scale=140.0, phase=[2, -1], align=align)
        image = render_stack(stack, dtype=torch.float64).image.numpy()
        t = stack.tensors["p"]
        tile = torch.cat([t.color, t.alpha]).double().numpy()
        origin = (2 + 2, 1 - 1) if align else (2, -1)
        fill = reference_fill(tile, 140.0, origin, (2, 1, 9, 7))
        a = fill[3:] * t.mask.double().numpy() * 0.7
        expected = 0.5 + a * (0.5 * fill[:3] - 0.5)
        assert np.abs(image[:, 1:7, 2:9] - expected).max() < 1e-6  # float32 tile resample, float64 blend
        assert (image[:, 0] == 0.5).all() and (image[:, :, :2] == 0.5).all()

    def test_saves_and_loads_bit_for_bit_inside_the_folder(self, tmp_path):
        stack = self._stack(scale=63.0, phase=[-3, 5])
        before = render_stack(stack, dtype=torch.float64).image
        stack.save(tmp_path / "s")
        loaded = load_stack(tmp_path / "s")
        assert sorted(p.relative_to(tmp_path / "s").as_posix() for p in (tmp_path / "s").rglob("*.png")) == [
            "layers/p.png", "masks/p.png"]  # fmt: skip
        layer = loaded.document.layer("p")
        assert (layer.kind, layer.source, layer.pattern.scale, tuple(layer.pattern.phase)) == (
            "pattern", "layers/p.png", 63.0, (-3, 5))  # fmt: skip
        assert torch.equal(render_stack(loaded, dtype=torch.float64).image, before)
        loaded.save()
        assert torch.equal(render_stack(load_stack(tmp_path / "s"), dtype=torch.float64).image, before)

    def test_a_sixteen_bit_tile_keeps_its_depth(self, tmp_path):
        stack = Stack(Document.from_dict(_doc()))
        tile = torch.rand(3, 4, 6, dtype=torch.float64)
        stack.add_pattern("p", tile, bit_depth=16)
        before = render_stack(stack, dtype=torch.float64).image
        stack.save(tmp_path / "s")
        assert read_png_header(tmp_path / "s" / "layers" / "p.png").bit_depth == 16
        loaded = load_stack(tmp_path / "s")
        assert loaded.bit_depths["p"] == 16
        assert torch.equal(render_stack(loaded, dtype=torch.float64).image, before)

    @pytest.mark.parametrize(
        "change,message",
        [({"scale": 0.0}, "scale"), ({"scale": float("nan")}, "scale"), ({"phase": [float("nan"), 0]}, "phase"),
         ({"phase": [0, 40_000]}, "phase"), ({"angle": 30.0}, "angle")],
    )  # fmt: skip
    def test_bad_parameters_are_one_line(self, change, message):
        layer = {"id": "p", "kind": "pattern", "source": "layers/p.png", "pattern": change}
        with pytest.raises(DocumentError, match=message) as err:
            Document.from_dict(_doc(layer))
        assert "\n" not in str(err.value)

    def test_add_pattern_refuses_a_gray_or_oversized_tile(self):
        stack = Stack(Document.from_dict(_doc()))
        with pytest.raises(LasagnaError, match="expected an RGB or RGBA tile"):
            stack.add_pattern("p", np.zeros((4, 4), dtype=np.uint8))
        with pytest.raises(LasagnaError, match="tile at 1000 %"):
            stack.add_pattern("p", np.zeros((600, 600, 3), dtype=np.uint8), {"scale": 1000.0})
        assert stack.document.ids == ("bg",)

    def test_validate_refuses_bad_parameters_in_one_line_exit_2(self, tmp_path, capsys):
        from lasagna.cli import main

        (tmp_path / "layers").mkdir()
        Image.new("RGB", (600, 500)).save(tmp_path / "layers" / "p.png")
        Image.new("L", (4, 4)).save(tmp_path / "layers" / "g.png")
        cases = [
            ({"scale": 0}, "layers[1].pattern.scale", "p"),
            ({"phase": [0.5, "NaN"]}, "layers[1].pattern.phase", "p"),
            ({"scale": 1000.0}, "tile at 1000 %", "p"),
            ({}, "expected an RGB or RGBA PNG", "g"),
        ]
        for pattern, message, name in cases:
            layer = {"id": "p", "kind": "pattern", "source": f"layers/{name}.png", "pattern": pattern}
            (tmp_path / "stack.json").write_text(json.dumps(_doc(layer)))
            assert main(["validate", str(tmp_path)]) == 2
            err = capsys.readouterr().err.strip()
            assert "\n" not in err and message in err, err
