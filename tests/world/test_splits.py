"""The split table, the per-scene random streams, and the sampled parameters' ranges."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from lasagna.errors import LasagnaError
from lasagna.world.params import MAX_OBJECTS, WALL_Z, sample_scenes
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
        assert SPLIT_NAMES == ("train", "val", "heldout")

    def test_val_shares_train_families(self):
        t, v = SPLITS["train"], SPLITS["val"]
        assert (t.shapes, t.object_textures, t.wall_textures) == (v.shapes, v.object_textures, v.wall_textures)

    def test_heldout_families_are_new(self):
        t, h = SPLITS["train"], SPLITS["heldout"]
        assert not set(h.shapes) & set(t.shapes) and not h.textures & t.textures
        assert len(t.shapes) >= 3 and len(h.shapes) >= 2 and len(h.textures) >= 2

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

    def test_heldout_families_never_in_train(self, params):
        held = SPLITS["heldout"]
        for name in ("train", "val"):
            p = params[name]
            assert not {SHAPE_NAMES[i] for i in p.shape[p.present].tolist()} & set(held.shapes)
            used = {TEXTURE_NAMES[i] for i in p.texture[p.present].tolist() + p.wall_texture.tolist()}
            assert not used & held.textures

    def test_splits_share_no_scene(self, params):
        prints = {name: _fingerprints(p) for name, p in params.items()}
        assert all(len(v) == N for v in prints.values())  # no repeats inside a split either
        assert not prints["train"] & prints["val"]
        assert not prints["train"] & prints["heldout"] and not prints["val"] & prints["heldout"]

    def test_seeds_share_no_scene(self, params):
        assert not _fingerprints(params["train"]) & _fingerprints(sample_scenes("train", 1, range(N)))

    def test_ranges(self, params):
        for p in params.values():
            n = p.present.sum(1)
            assert n.min() == 1 and n.max() == MAX_OBJECTS and set(n.tolist()) == {1, 2, 3}
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
        assert len(draws) == 12

    @pytest.mark.parametrize("seed", [-1, 1.0, "0", True, 2**63])
    def test_bad_seed(self, seed):
        with pytest.raises(LasagnaError, match="seed: expected an integer in"):
            scene_rng("train", seed, 0)

    def test_no_indices(self):
        with pytest.raises(LasagnaError, match="count: expected at least one scene"):
            sample_scenes("train", 0, [])
