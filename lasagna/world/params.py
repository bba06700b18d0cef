"""Scene parameters: everything needed to re-render a batch of scenes, and how they are sampled.

A scene is 1–3 objects (``MAX_OBJECTS`` slots, unused ones marked absent) before a wall at
z = ``WALL_Z``, a light label, and the parameters of a coloured point light used by the additive-light
task: a fill light in front of every object near the view axis (``GLOW_XY``, ``GLOW_Z``), so the
glow's shape follows from the visible geometry, with a colour drawn from its own label
(`lasagna.world.lighting.GLOW_VOCABULARY`: warm, cool, white). Scene ``index`` of a split is drawn from its own random stream (``splits.scene_rng``) with a
fixed layout — every slot consumes its draws whether present or not — so a scene's parameters do not
depend on the scenes around it.
"""
from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass, fields, replace
from typing import Any, Sequence

import numpy as np
import torch

from lasagna.errors import LasagnaError
from lasagna.world.lighting import GLOW_VOCABULARY, VOCABULARY, glow_rgb
from lasagna.world.shapes import MAX_BOUNDING_RADIUS, SHAPE_NAMES, SHAPES
from lasagna.world.splits import check_seed, get_split, scene_rng
from lasagna.world.textures import TEXTURE_NAMES, sample_params

MAX_OBJECTS = 3
WALL_Z = -0.85
"""The wall is the plane z = −0.85; objects are centred at z ∈ [−0.2, 0.2] with bounding radius ≤ 0.6, so none reaches it."""
_CENTRE_XY = 0.6
_CENTRE_Z = 0.2
assert -_CENTRE_Z - MAX_BOUNDING_RADIUS > WALL_Z
GLOW_XY = 0.35
"""The glow's point light sits at x, y ∈ [−0.35, 0.35]: near the view axis, so where it lights is
inferable from the image (a light anywhere would make the true layer a matter of luck)."""
GLOW_Z = (1.0, 1.4)
"""…and at z ∈ [1.0, 1.4], in front of every object (whose front is at most z = 0.2 + 0.6)."""
assert GLOW_Z[0] > _CENTRE_Z + MAX_BOUNDING_RADIUS

_SLOT_DRAWS = 24  # family 1, centre 3, rotation 3, size 4, colour 3, texture family 1, texture 8, floor 1
_WALL_DRAWS = 13  # colour 3, texture family 1, texture 8, floor 1
_GLOW_DRAWS = 8  # position 3, label and hue 1, saturation 1, intensity 1, halo intensity 1, halo radius 1
_DRAWS = 2 + MAX_OBJECTS * _SLOT_DRAWS + _WALL_DRAWS + _GLOW_DRAWS


@dataclass(frozen=True)
class SceneParams:
    """Parameters of B scenes (float64 / int64 tensors on the CPU); K = ``MAX_OBJECTS`` slots.

    Indices into the registries: ``shape`` → ``SHAPE_NAMES``, ``texture`` and ``wall_texture`` →
    ``TEXTURE_NAMES``, ``label`` → ``VOCABULARY``. ``rotation`` maps object-local to camera
    coordinates (p_camera = R·p_local + centre).
    """

    split: str
    seed: int
    index: torch.Tensor  # (B,) int64: the scene's index within (split, seed)
    label: torch.Tensor  # (B,) int64
    present: torch.Tensor  # (B, K) bool
    shape: torch.Tensor  # (B, K) int64
    center: torch.Tensor  # (B, K, 3)
    rotation: torch.Tensor  # (B, K, 3, 3)
    size: torch.Tensor  # (B, K, 3) family-specific, see lasagna.world.shapes
    radius: torch.Tensor  # (B, K) bounding radius (for culling)
    color: torch.Tensor  # (B, K, 3) RGB in [0, 1]
    texture: torch.Tensor  # (B, K) int64
    texture_params: torch.Tensor  # (B, K, N_PARAMS), layout in lasagna.world.textures
    texture_seed: torch.Tensor  # (B, K) int64
    wall_color: torch.Tensor  # (B, 3)
    wall_texture: torch.Tensor  # (B,) int64
    wall_texture_params: torch.Tensor  # (B, N_PARAMS)
    wall_texture_seed: torch.Tensor  # (B,) int64
    glow_position: torch.Tensor  # (B, 3) the additive point light, in front of the scene
    glow_label: torch.Tensor  # (B,) int64 index into GLOW_VOCABULARY
    glow_tone: torch.Tensor  # (B, 2) where in its label's (hue, saturation) ranges the colour lies
    glow_intensity: torch.Tensor  # (B,)
    halo_intensity: torch.Tensor  # (B,)
    halo_radius: torch.Tensor  # (B,)

    @property
    def glow_color(self) -> torch.Tensor:
        """(B, 3) float64 RGB of each glow, max component 1: ``glow_rgb(label, *tone)``."""
        rows = [glow_rgb(GLOW_VOCABULARY[int(k)], *tone) for k, tone in zip(self.glow_label, self.glow_tone.tolist())]
        return torch.tensor(rows, dtype=torch.float64).reshape(len(self), 3)

    def __len__(self) -> int:
        return int(self.index.shape[0])

    def select(self, idx: slice | Sequence[int] | torch.Tensor) -> "SceneParams":
        """The scenes at ``idx`` (a slice or index list), as a new batch."""
        if not isinstance(idx, slice):
            idx = torch.as_tensor(idx, dtype=torch.int64).reshape(-1)
        kw = {f.name: getattr(self, f.name) for f in fields(self)}
        for name, v in kw.items():
            if isinstance(v, torch.Tensor):
                kw[name] = v[idx]
        return SceneParams(**kw)

    def _names(self, labels: str | Sequence[str], what: str) -> list[str]:
        """One label for all scenes, or one per scene."""
        names = [labels] * len(self) if isinstance(labels, str) else list(labels)
        if len(names) != len(self):
            raise LasagnaError(f"expected 1 or {len(self)} {what}, got {len(names)}", where="labels")
        return names

    def with_labels(self, labels: str | Sequence[str] | None) -> "SceneParams":
        """The same scenes under other light labels (one label for all, or one per scene)."""
        if labels is None:
            return self
        from lasagna.world.lighting import label_index

        idx = [label_index(n) for n in self._names(labels, "labels")]
        return replace(self, label=torch.tensor(idx, dtype=torch.int64))

    def with_glow_labels(self, labels: str | Sequence[str] | None) -> "SceneParams":
        """The same scenes with glows of other labels (same tone within the new label's ranges)."""
        if labels is None:
            return self
        from lasagna.world.lighting import glow_label_index

        idx = [glow_label_index(n) for n in self._names(labels, "glow labels")]
        return replace(self, glow_label=torch.tensor(idx, dtype=torch.int64))

    def describe(self, i: int) -> dict[str, Any]:
        """Scene ``i`` as a JSON-ready dict (family names, plain floats): enough to re-render it."""
        objects = []
        for k in range(MAX_OBJECTS):
            if not bool(self.present[i, k]):
                continue
            objects.append({
                "shape": SHAPE_NAMES[int(self.shape[i, k])],
                "center": self.center[i, k].tolist(),
                "rotation": self.rotation[i, k].tolist(),
                "size": self.size[i, k].tolist(),
                "color": self.color[i, k].tolist(),
                "texture": TEXTURE_NAMES[int(self.texture[i, k])],
                "texture_params": self.texture_params[i, k].tolist(),
                "texture_seed": int(self.texture_seed[i, k]),
            })
        return {
            "split": self.split,
            "seed": self.seed,
            "index": int(self.index[i]),
            "label": VOCABULARY[int(self.label[i])],
            "objects": objects,
            "wall": {
                "z": WALL_Z,
                "color": self.wall_color[i].tolist(),
                "texture": TEXTURE_NAMES[int(self.wall_texture[i])],
                "texture_params": self.wall_texture_params[i].tolist(),
                "texture_seed": int(self.wall_texture_seed[i]),
            },
            "glow": {
                "position": self.glow_position[i].tolist(),
                "label": GLOW_VOCABULARY[int(self.glow_label[i])],
                "color": self.glow_color[i].tolist(),
                "intensity": float(self.glow_intensity[i]),
                "halo_intensity": float(self.halo_intensity[i]),
                "halo_radius": float(self.halo_radius[i]),
            },
        }


def _rotation(u: np.ndarray) -> np.ndarray:
    """A uniformly random rotation from three uniforms (Shoemake 1992, "Uniform random rotations")."""
    a, b = math.sqrt(1.0 - u[0]), math.sqrt(u[0])
    x, y = a * math.sin(2 * math.pi * u[1]), a * math.cos(2 * math.pi * u[1])
    z, w = b * math.sin(2 * math.pi * u[2]), b * math.cos(2 * math.pi * u[2])
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _hsv(h: float, s: float, v: float) -> list[float]:
    return list(colorsys.hsv_to_rgb(h, s, v))


def _lerp(u: float, lo: float, hi: float) -> float:
    return lo + (hi - lo) * float(u)


def _pick(u: float, names: Sequence[str]) -> str:
    return names[min(int(u * len(names)), len(names) - 1)]


def _sample_one(split: str, seed: int, index: int) -> dict[str, np.ndarray]:
    spec = get_split(split)
    rng = scene_rng(split, seed, index)
    u = rng.random(_DRAWS)
    seeds = rng.integers(0, 2**31, size=MAX_OBJECTS + 1)
    n_objects = 1 + min(int(u[0] * MAX_OBJECTS), MAX_OBJECTS - 1)
    out: dict[str, Any] = {
        "label": min(int(u[1] * len(VOCABULARY)), len(VOCABULARY) - 1),
        "present": np.arange(MAX_OBJECTS) < n_objects,
        "shape": [], "center": [], "rotation": [], "size": [], "radius": [], "color": [],
        "texture": [], "texture_params": [], "texture_seed": seeds[:MAX_OBJECTS],
    }
    for k in range(MAX_OBJECTS):
        s = u[2 + k * _SLOT_DRAWS: 2 + (k + 1) * _SLOT_DRAWS]
        family = _pick(s[0], spec.shapes)
        size = SHAPES[family].sample_size(s[7:11])
        tex = _pick(s[14], spec.object_textures)
        out["shape"].append(SHAPE_NAMES.index(family))
        out["center"].append([_lerp(s[1], -_CENTRE_XY, _CENTRE_XY), _lerp(s[2], -_CENTRE_XY, _CENTRE_XY),
                              _lerp(s[3], -_CENTRE_Z, _CENTRE_Z)])
        out["rotation"].append(_rotation(s[4:7]))
        out["size"].append(size)
        out["radius"].append(SHAPES[family].bounding_radius(np.asarray(size)))
        out["color"].append(_hsv(s[11], _lerp(s[12], 0.25, 0.9), _lerp(s[13], 0.55, 0.95)))
        out["texture"].append(TEXTURE_NAMES.index(tex))
        out["texture_params"].append(sample_params(tex, s[15:23], lo=_lerp(s[23], 0.2, 0.55)))
    w = u[2 + MAX_OBJECTS * _SLOT_DRAWS:][:_WALL_DRAWS]
    wall_tex = _pick(w[3], spec.wall_textures)
    out["wall_color"] = _hsv(w[0], _lerp(w[1], 0.0, 0.35), _lerp(w[2], 0.55, 0.9))
    out["wall_texture"] = TEXTURE_NAMES.index(wall_tex)
    out["wall_texture_params"] = sample_params(wall_tex, w[4:12], lo=_lerp(w[12], 0.45, 0.75))
    out["wall_texture_seed"] = seeds[MAX_OBJECTS]
    g = u[2 + MAX_OBJECTS * _SLOT_DRAWS + _WALL_DRAWS:]
    out["glow_position"] = [_lerp(g[0], -GLOW_XY, GLOW_XY), _lerp(g[1], -GLOW_XY, GLOW_XY), _lerp(g[2], *GLOW_Z)]
    # One uniform picks the label (thirds of [0, 1)) and, rescaled, the hue within the label's range.
    tone = g[3] * len(GLOW_VOCABULARY)
    k = min(int(tone), len(GLOW_VOCABULARY) - 1)
    out["glow_label"] = k
    out["glow_tone"] = [tone - k, g[4]]
    out["glow_intensity"] = _lerp(g[5], 1.2, 2.0)
    out["halo_intensity"] = _lerp(g[6], 0.0, 0.2)
    out["halo_radius"] = _lerp(g[7], 0.1, 0.25)
    return out


def sample_scenes(split: str, seed: int, indices: Sequence[int] | range) -> SceneParams:
    """Parameters of scenes ``indices`` of ``split`` under ``seed`` (each from its own stream)."""
    get_split(split)
    check_seed(seed)
    indices = [check_seed(i, where="index") for i in indices]
    if not indices:
        raise LasagnaError("expected at least one scene, got 0", where="count")
    rows = [_sample_one(split, seed, i) for i in indices]

    def stack(key: str, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        return torch.as_tensor(np.stack([np.asarray(r[key]) for r in rows]), dtype=dtype)

    return SceneParams(
        split=split,
        seed=int(seed),
        index=torch.tensor(indices, dtype=torch.int64),
        label=stack("label", torch.int64),
        present=stack("present", torch.bool),
        shape=stack("shape", torch.int64),
        center=stack("center"),
        rotation=stack("rotation"),
        size=stack("size"),
        radius=stack("radius"),
        color=stack("color"),
        texture=stack("texture", torch.int64),
        texture_params=stack("texture_params"),
        texture_seed=stack("texture_seed", torch.int64),
        wall_color=stack("wall_color"),
        wall_texture=stack("wall_texture", torch.int64),
        wall_texture_params=stack("wall_texture_params"),
        wall_texture_seed=stack("wall_texture_seed", torch.int64),
        glow_position=stack("glow_position"),
        glow_label=stack("glow_label", torch.int64),
        glow_tone=stack("glow_tone"),
        glow_intensity=stack("glow_intensity"),
        halo_intensity=stack("halo_intensity"),
        halo_radius=stack("halo_radius"),
    )


