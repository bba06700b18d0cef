"""The split table, the per-scene random streams, and the sampled parameters' ranges."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lasagna.errors import LasagnaError
from lasagna.world.params import MAX_OBJECTS, WALL_Z, sample_scenes
from lasagna.world.relief import RELIEF_NAMES
from lasagna.world.shapes import MAX_BOUNDING_RADIUS, SHAPE_NAMES, SHAPES
from lasagna.world.splits import SPLIT_NAMES, SPLITS, get_split, scene_rng
from lasagna.world.textures import TEXTURE_NAMES

N = 150


@pytest.fixture(scope="module")
def params():
    return {name: sample_scenes(name, 0, range(N)) for name in SPLIT_NAMES}


def _fingerprints(p) -> set[bytes]:
    return {p.center[i].numpy().tobytes() + p.wall_color[i].numpy().tobytes() for i in range(len(p))}


class TestTable:
    def test_names(self):
        assert SPLIT_NAMES == ("train", "val", "heldout", "far", "select", "wide")

    def test_val_shares_train_families(self):
        t, v = SPLITS["train"], SPLITS["val"]
        assert (t.shapes, t.object_textures, t.wall_textures) == (v.shapes, v.object_textures, v.wall_textures)

    @pytest.mark.parametrize("held", ["heldout", "far", "select"])
    def test_held_families_are_new(self, held):
        t, h = SPLITS["train"], SPLITS[held]
        assert not set(h.shapes) & set(t.shapes) and not h.textures & t.textures
        assert not set(h.reliefs) & set(t.reliefs)
        assert len(t.shapes) >= 5 and len(t.textures) >= 9 and len(h.shapes) >= 2 and len(h.textures) >= 2

    @pytest.mark.parametrize("a, b", [("far", "heldout"), ("select", "heldout"), ("select", "far")])
    def test_held_splits_share_nothing(self, a, b):
        # select chooses defaults, heldout is reported, far is the final measurement: each new to the others.
        x, y = SPLITS[a], SPLITS[b]
        assert not set(x.shapes) & set(y.shapes) and not x.textures & y.textures
        assert not set(x.reliefs) & set(y.reliefs)

    def test_every_family_is_registered(self):
        for s in SPLITS.values():
            assert set(s.shapes) <= set(SHAPES) and s.textures <= set(TEXTURE_NAMES)

    def test_unknown(self):
        with pytest.raises(LasagnaError, match="split: unknown split 'tset'"):
            get_split("tset")


class TestSampledScenes:
    @pytest.mark.parametrize("split", SPLIT_NAMES)
    def test_families_stay_in_their_split(self, params, split):
        p, spec = params[split], SPLITS[split]
        shapes = {SHAPE_NAMES[i] for i in p.shape[p.present].tolist()}
        obj_tex = {TEXTURE_NAMES[i] for i in p.texture[p.present].tolist()}
        wall_tex = {TEXTURE_NAMES[i] for i in p.wall_texture.tolist()}
        # Every family of the split is used in 150 scenes, and nothing else is.
        assert shapes == set(spec.shapes)
        assert obj_tex == set(spec.object_textures) and wall_tex == set(spec.wall_textures)
        reliefs = {RELIEF_NAMES[i] for i in p.relief.tolist() if i >= 0}
        assert reliefs == set(spec.reliefs)
        if spec.reliefs:  # relief on a quarter of the walls: 150 draws, 4σ bounds
            assert abs(float((p.relief >= 0).double().mean()) - spec.relief_probability) < 4 * (0.25 * 0.75 / N) ** 0.5

    @pytest.mark.parametrize("held", ["heldout", "far", "select"])
    def test_held_families_never_in_train(self, params, held):
        held = SPLITS[held]
        for name in ("train", "val", "wide"):
            p = params[name]
            assert not {SHAPE_NAMES[i] for i in p.shape[p.present].tolist()} & set(held.shapes)
            used = {TEXTURE_NAMES[i] for i in p.texture[p.present].tolist() + p.wall_texture.tolist()}
            assert not used & held.textures

    def test_splits_share_no_scene(self, params):
        prints = {name: _fingerprints(p) for name, p in params.items()}
        assert all(len(v) == N for v in prints.values())  # no repeats inside a split either
        assert not prints["train"] & prints["val"]
        for a in SPLIT_NAMES:
            for b in SPLIT_NAMES:
                assert a == b or not prints[a] & prints[b]

    def test_seeds_share_no_scene(self, params):
        assert not _fingerprints(params["train"]) & _fingerprints(sample_scenes("train", 1, range(N)))

    def test_ranges(self, params):
        for name, p in params.items():
            n = p.present.sum(1)
            lo, hi = SPLITS[name].objects
            assert set(n.tolist()) == set(range(lo, hi + 1)) and hi <= MAX_OBJECTS
            assert not p.present[:, hi:].any()
            # Two-colour paint: about half of the surfaces of broadened splits, none elsewhere.
            deltas = torch.cat([p.color_delta.reshape(-1, 3), p.wall_color_delta]).abs().sum(1) > 0
            share = float(deltas.double().mean())
            assert abs(share - SPLITS[name].two_tone) < 0.1
            albedo_lo = [
                c * lo + d
                for c, d, lo in zip(
                    p.color.reshape(-1, 3), p.color_delta.reshape(-1, 3), p.texture_params[..., 8].reshape(-1)
                )
            ]
            assert all(float(a.min()) >= -1e-12 and float(a.max()) <= 1 + 1e-12 for a in albedo_lo)
            assert (p.radius[p.present] <= MAX_BOUNDING_RADIUS).all()
            # Every object stays in front of the wall.
            assert ((p.center[..., 2] - p.radius)[p.present] > WALL_Z).all()
            eye = torch.eye(3, dtype=torch.float64).expand_as(p.rotation)
            torch.testing.assert_close(p.rotation @ p.rotation.transpose(-1, -2), eye, atol=1e-12, rtol=0)
            assert (torch.linalg.det(p.rotation) > 0).all()
            assert p.color.min() >= 0 and p.color.max() <= 1 and p.wall_color.max() <= 1
            assert set(p.label.tolist()) == set(range(8))  # all labels drawn in 150 scenes

    def test_scene_is_independent_of_its_batch(self, params):
        one = sample_scenes("heldout", 0, [37])
        assert torch.equal(one.center[0], params["heldout"].center[37])
        assert torch.equal(one.texture_params[0], params["heldout"].texture_params[37])


class TestStreams:
    def test_reproducible(self):
        assert np.array_equal(scene_rng("train", 3, 9).random(5), scene_rng("train", 3, 9).random(5))

    def test_distinct(self):
        draws = {tuple(scene_rng(s, seed, i).random(2)) for s in SPLIT_NAMES for seed in (0, 1) for i in (0, 1)}
        assert len(draws) == 4 * len(SPLIT_NAMES)

    @pytest.mark.parametrize("seed", [-1, 1.0, "0", True, 2**63])
    def test_bad_seed(self, seed):
        with pytest.raises(LasagnaError, match="seed: expected an integer in"):
            scene_rng("train", seed, 0)

    def test_no_indices(self):
        with pytest.raises(LasagnaError, match="count: expected at least one scene"):
            sample_scenes("train", 0, [])
