"""LayerTensors: validation, statistics, and their cache (computed once, invalidated by edits)."""

from __future__ import annotations

import pytest
import torch

from lasagna.compose import layer as layer_mod
from lasagna.compose.layer import LayerTensors
from lasagna.errors import LasagnaError


class CountingAminmax:
    """Counts full statistics passes (the cached computations call torch.aminmax on whole tensors)."""

    def __init__(self, monkeypatch, full: int):
        self.calls = 0
        real = torch.aminmax

        def counted(t, *args, **kwargs):
            if t.numel() == full:  # not the sparse sample grid (16x16 per channel)
                self.calls += 1
            return real(t, *args, **kwargs)

        monkeypatch.setattr(layer_mod.torch, "aminmax", counted)


def test_shapes_and_properties():
    lt = LayerTensors(torch.rand(2, 3, 5, 7), torch.rand(1, 1, 5, 7), torch.rand(1, 5, 7))
    assert (lt.height, lt.width, lt.channels, tuple(lt.batch_shape)) == (5, 7, 3, (2,))
    assert not lt.requires_grad
    assert LayerTensors(torch.rand(1, 2, 2, requires_grad=True)).requires_grad


@pytest.mark.parametrize(
    "kwargs, where, match",
    [
        ({"color": torch.rand(4, 5, 5)}, "LayerTensors.color", "C in \\{1, 3\\}"),
        ({"color": torch.rand(5, 5)}, "LayerTensors.color", "got \\(5, 5\\)"),
        ({"color": torch.zeros(3, 5, 5, dtype=torch.uint8)}, "LayerTensors.color", "floating-point"),
        ({"color": torch.rand(3, 5, 5), "alpha": torch.rand(3, 5, 5)}, "LayerTensors.alpha", "\\(..., 1, h, w\\)"),
        (
            {"color": torch.rand(3, 5, 5), "mask": torch.rand(1, 4, 5)},
            "LayerTensors.mask",
            "is 4x5 but the colour is 5x5",
        ),
        ({"color": torch.rand(2, 3, 5, 5), "alpha": torch.rand(3, 1, 5, 5)}, "LayerTensors", "do not broadcast"),
    ],
)
def test_exceptions(kwargs, where, match):
    with pytest.raises(LasagnaError, match=match) as info:
        LayerTensors(**kwargs)
    assert str(info.value).startswith(where + ":")


def test_reassigning_a_field_is_validated():
    lt = LayerTensors(torch.rand(3, 4, 4))
    with pytest.raises(LasagnaError, match="LayerTensors.alpha"):
        lt.alpha = torch.rand(1, 3, 3)


def test_from_rgba():
    rgba = torch.rand(4, 3, 3)
    lt = LayerTensors.from_rgba(rgba)
    assert torch.equal(lt.color, rgba[:3]) and torch.equal(lt.alpha, rgba[3:])
    with pytest.raises(LasagnaError, match="from_rgba"):
        LayerTensors.from_rgba(torch.rand(3, 3, 3))


@pytest.mark.parametrize(
    "blend, value, identity",
    [
        ("multiply", 1.0, True),
        ("plus", 0.0, True),
        ("screen", 0.0, True),
        ("normal", 0.0, False),
        ("multiply", 0.5, False),
        ("plus", 0.25, False),
    ],
)
def test_identity_by_neutral_colour(blend, value, identity):
    assert LayerTensors(torch.full((1, 4, 4), value)).is_identity(blend) is identity


def test_identity_by_transparency_including_alpha_times_mask():
    alpha = torch.zeros(1, 4, 4)
    alpha[..., :2] = 1.0
    mask = torch.zeros(1, 4, 4)
    mask[..., 2:] = 1.0  # alpha × mask is 0 everywhere although neither is
    lt = LayerTensors(torch.rand(3, 4, 4), alpha, mask)
    assert lt.is_transparent() and lt.is_identity("normal")
    assert not LayerTensors(torch.rand(3, 4, 4), alpha).is_identity("normal")


def test_transparent_layer_with_nan_colour_is_not_identity():
    color = torch.rand(3, 4, 4)
    color[0, 1, 1] = float("nan")
    assert not LayerTensors(color, torch.zeros(1, 4, 4)).is_identity("normal")


def test_identity_needs_every_pixel_not_just_the_sample():
    color = torch.ones(1, 64, 64)
    color[0, 1, 1] = 0.5  # off the 16x16 sample grid (stride 4)
    assert not LayerTensors(color).is_identity("multiply")


def test_opaque():
    assert LayerTensors(torch.rand(3, 4, 4)).is_opaque()
    assert LayerTensors(torch.rand(3, 4, 4), torch.ones(1, 4, 4), torch.ones(1, 4, 4)).is_opaque()
    alpha = torch.ones(1, 64, 64)
    alpha[0, 1, 1] = 0.99
    assert not LayerTensors(torch.rand(3, 64, 64), alpha).is_opaque()


def test_statistics_are_cached_until_an_in_place_edit(monkeypatch):
    counter = CountingAminmax(monkeypatch, full=32 * 32)
    lt = LayerTensors(torch.ones(1, 32, 32))
    assert lt.is_identity("multiply") and lt.color_range() == (1.0, 1.0)
    first = counter.calls
    assert first >= 1
    for _ in range(3):
        assert lt.is_identity("multiply")
    assert counter.calls == first  # no pixel read again
    lt.color[0, 5, 5] = 2.0  # in place: _version changes
    assert not lt.is_identity("multiply")
    assert lt.color_range() == (1.0, 2.0)


def test_statistics_follow_views_of_an_edited_base():
    base = torch.ones(2, 1, 8, 8)
    lt = LayerTensors(base[0])
    assert lt.is_identity("multiply")
    base[0, 0, 3, 3] = 0.0  # a view shares its base's version counter
    assert not lt.is_identity("multiply")


def test_statistics_follow_a_replaced_tensor():
    lt = LayerTensors(torch.zeros(3, 8, 8))
    assert lt.is_identity("plus")
    lt.color = torch.full((3, 8, 8), 0.5)
    assert not lt.is_identity("plus")


def test_recycled_ids_do_not_fool_the_cache():
    lt = LayerTensors(torch.zeros(3, 8, 8))
    assert lt.color_range() == (0.0, 0.0)
    for _ in range(10):  # CPython reuses a freed tensor's id at once: the cache must not be fooled
        lt.color = torch.full((3, 8, 8), 0.25)
        assert lt.color_range() == (0.25, 0.25)
        lt.color = torch.zeros(3, 8, 8)
        assert lt.color_range() == (0.0, 0.0)


def test_decoded_colour_is_cached_and_invalidated():
    lt = LayerTensors(torch.full((3, 2, 2), 0.5, dtype=torch.float64))
    d1 = lt.decoded_color()
    assert lt.decoded_color() is d1
    assert float(d1[0, 0, 0]) == pytest.approx(0.21404114048223255)
    lt.color.fill_(1.0)
    assert float(lt.decoded_color()[0, 0, 0]) == 1.0
