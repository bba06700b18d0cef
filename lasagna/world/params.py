"""Scene parameters: everything needed to re-render a batch of scenes, and how they are sampled.

A scene is 1–5 objects (``MAX_OBJECTS`` slots, unused ones marked absent; how many a split draws is
in `lasagna.world.splits`) before a wall at z = ``WALL_Z`` that may carry relief, each surface painted
with a texture in one colour and its shade or between two colours, a light label, and the parameters
of a coloured point light used by the additive-light task: a fill light in front of every object near
the view axis (``GLOW_XY``, ``GLOW_Z``), so the glow's shape follows from the visible geometry, with a
colour drawn from its own label (`lasagna.world.lighting.GLOW_VOCABULARY`: warm, cool, white). Scene
``index`` of a split is drawn from its own random stream (``splits.scene_rng``) with a fixed layout —
every slot consumes its draws whether present or not — so a scene's parameters do not depend on the
scenes around it.
"""

from __future__ import annotations

import colorsys
import math
from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np
import torch

from lasagna.errors import LasagnaError
from lasagna.world.lighting import GLOW_VOCABULARY, VOCABULARY, glow_rgb
from lasagna.world.relief import N_RELIEF_PARAMS, RELIEF_DRAWS, RELIEF_NAMES, RELIEFS
from lasagna.world.shapes import FACING_TILT, MAX_BOUNDING_RADIUS, SHAPE_NAMES, SHAPES
from lasagna.world.splits import MAX_OBJECTS, check_seed, get_split, scene_rng
from lasagna.world.textures import TEXTURE_NAMES, sample_params

WALL_Z = -0.85
"""The wall is the plane z = −0.85; objects are centred at z ∈ [−0.2, 0.2] with bounding radius ≤ 0.6:
none reaches it."""
_CENTRE_XY = 0.6
_CENTRE_Z = 0.2
assert -_CENTRE_Z - MAX_BOUNDING_RADIUS > WALL_Z
GLOW_XY = 0.35
"""The glow's point light sits at x, y ∈ [−0.35, 0.35]: near the view axis, so where it lights is
inferable from the image (a light anywhere would make the true layer a matter of luck)."""
GLOW_Z = (1.0, 1.4)
"""…and at z ∈ [1.0, 1.4], in front of every object (whose front is at most z = 0.2 + 0.6)."""
assert GLOW_Z[0] > _CENTRE_Z + MAX_BOUNDING_RADIUS

# The stream's layout. The first world's draws come first, unchanged (so ``heldout``, which keeps
# the first world's families, renders the same scenes bit for bit); everything added since is drawn
# after them.
_SLOT_DRAWS = 24  # family 1, centre 3, rotation 3, size 4, colour 3, texture family 1, texture 8, floor 1
_WALL_DRAWS = 13  # colour 3, texture family 1, texture 8, floor 1
_GLOW_DRAWS = 8  # position 3, label and hue 1, saturation 1, intensity 1, halo intensity 1, halo radius 1
_V1_OBJECTS = 3
_DRAWS = 2 + _V1_OBJECTS * _SLOT_DRAWS + _WALL_DRAWS + _GLOW_DRAWS
_TONE_DRAWS = 4  # second colour: used? 1, hue/saturation/value 3
_EXTRA_DRAWS = (MAX_OBJECTS - _V1_OBJECTS) * _SLOT_DRAWS + (MAX_OBJECTS + 1) * _TONE_DRAWS + 2 + RELIEF_DRAWS


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
    color_delta: torch.Tensor  # (B, K, 3) second colour − lo·colour (0: a one-colour pattern), see textures
    wall_color_delta: torch.Tensor  # (B, 3)
    relief: torch.Tensor  # (B,) int64 index into RELIEF_NAMES, −1 for a flat wall
    relief_params: torch.Tensor  # (B, N_RELIEF_PARAMS), layout in lasagna.world.relief

    @property
    def glow_color(self) -> torch.Tensor:
        """(B, 3) float64 RGB of each glow, max component 1: ``glow_rgb(label, *tone)``."""
        rows = [glow_rgb(GLOW_VOCABULARY[int(k)], *tone) for k, tone in zip(self.glow_label, self.glow_tone.tolist())]
        return torch.tensor(rows, dtype=torch.float64).reshape(len(self), 3)

    def __len__(self) -> int:
        return int(self.index.shape[0])

    def select(self, idx: slice | Sequence[int] | torch.Tensor) -> SceneParams:
        """The scenes at ``idx`` (a slice or index list), as a new batch."""
        if not isinstance(idx, slice):
            idx = torch.as_tensor(idx, dtype=torch.int64).reshape(-1)
        kw = {f.name: getattr(self, f.name) for f in fields(self)}
        for name, v in kw.items():
            if isinstance(v, torch.Tensor):
                kw[name] = v[idx]
        return SceneParams(**kw)

    def walls_only(self) -> SceneParams:
        """The same scenes with no objects and a flat wall: textured walls whose true shading is one constant."""
        return replace(self, present=torch.zeros_like(self.present), relief=torch.full_like(self.relief, -1))

    def resting(self, sink: float | torch.Tensor) -> SceneParams:
        """The same scenes with every object's centre ``sink`` bounding radii in front of the wall (z = ``WALL_Z`` +
        sink·radius; ``sink`` one number or one per scene, (B,)): the objects rest on the wall — sunk into it for
        sink < 1 — as a photograph's objects stand on what lies behind them, so their cast shadows are attached and
        a height field above the wall describes the scene (the world as sampled floats them: ``_CENTRE_Z``)."""
        sink = torch.as_tensor(sink, dtype=self.center.dtype).reshape(-1, 1)
        center = self.center.clone()
        center[..., 2] = WALL_Z + sink * self.radius.to(center.dtype)
        return replace(self, center=center)

    def darkened(self, wall_gain: torch.Tensor, object_gain: torch.Tensor) -> SceneParams:
        """The same scenes with darker paint: the wall's albedo times ``wall_gain`` (B,) and each object's times
        ``object_gain`` (B, K), exactly (a surface's albedo is linear in its colour and colour delta, both scaled) —
        the low-key paint of photographs (a dark backdrop, a black coat), which the world as sampled never draws
        (wall and object colours have HSV value ≥ 0.55), so an estimator that never saw it reads every dark
        region as a face turned from the light."""
        wall = torch.as_tensor(wall_gain, dtype=self.wall_color.dtype).reshape(-1, 1)
        obj = torch.as_tensor(object_gain, dtype=self.color.dtype).reshape(len(self), -1, 1)
        return replace(
            self,
            wall_color=self.wall_color * wall,
            wall_color_delta=self.wall_color_delta * wall,
            color=self.color * obj,
            color_delta=self.color_delta * obj,
        )

    def _names(self, labels: str | Sequence[str], what: str) -> list[str]:
        """One label for all scenes, or one per scene."""
        names = [labels] * len(self) if isinstance(labels, str) else list(labels)
        if len(names) != len(self):
            raise LasagnaError(f"expected 1 or {len(self)} {what}, got {len(names)}", where="labels")
        return names

    def with_labels(self, labels: str | Sequence[str] | None) -> SceneParams:
        """The same scenes under other light labels (one label for all, or one per scene)."""
        if labels is None:
            return self
        from lasagna.world.lighting import label_index

        idx = [label_index(n) for n in self._names(labels, "labels")]
        return replace(self, label=torch.tensor(idx, dtype=torch.int64))

    def with_glow_labels(self, labels: str | Sequence[str] | None) -> SceneParams:
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
            objects.append(
                {
                    "shape": SHAPE_NAMES[int(self.shape[i, k])],
                    "center": self.center[i, k].tolist(),
                    "rotation": self.rotation[i, k].tolist(),
                    "size": self.size[i, k].tolist(),
                    "color": self.color[i, k].tolist(),
                    "texture": TEXTURE_NAMES[int(self.texture[i, k])],
                    "texture_params": self.texture_params[i, k].tolist(),
                    "texture_seed": int(self.texture_seed[i, k]),
                    "color_delta": self.color_delta[i, k].tolist(),
                }
            )
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
                "color_delta": self.wall_color_delta[i].tolist(),
                "relief": RELIEF_NAMES[int(self.relief[i])] if int(self.relief[i]) >= 0 else None,
                "relief_params": self.relief_params[i].tolist(),
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
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _hsv(h: float, s: float, v: float) -> list[float]:
    return list(colorsys.hsv_to_rgb(h, s, v))


def _lerp(u: float, lo: float, hi: float) -> float:
    return lo + (hi - lo) * float(u)


def _pick(u: float, names: Sequence[str]) -> str:
    return names[min(int(u * len(names)), len(names) - 1)]


def _facing(u: np.ndarray) -> np.ndarray:
    """A rotation that keeps local +z within ``FACING_TILT`` of the camera: a spin about z by 2π·u₂,
    then a tilt by FACING_TILT·u₀ about an in-plane axis at angle 2π·u₁."""
    spin, tilt, axis = 2 * math.pi * u[2], FACING_TILT * u[0], 2 * math.pi * u[1]
    cz, sz = math.cos(spin), math.sin(spin)
    rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    k = np.array([math.cos(axis), math.sin(axis), 0.0])
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    tilt_m = np.eye(3) + math.sin(tilt) * kx + (1 - math.cos(tilt)) * (kx @ kx)  # Rodrigues
    return tilt_m @ rz


def _slot(s: np.ndarray, shapes: Sequence[str], textures: Sequence[str], floor: tuple[float, float]) -> dict[str, Any]:
    """One object slot from its ``_SLOT_DRAWS`` uniforms."""
    family = _pick(s[0], shapes)
    size = SHAPES[family].sample_size(s[7:11])
    tex = _pick(s[14], textures)
    return {
        "shape": SHAPE_NAMES.index(family),
        "center": [
            _lerp(s[1], -_CENTRE_XY, _CENTRE_XY),
            _lerp(s[2], -_CENTRE_XY, _CENTRE_XY),
            _lerp(s[3], -_CENTRE_Z, _CENTRE_Z),
        ],
        "rotation": _facing(s[4:7]) if SHAPES[family].facing else _rotation(s[4:7]),
        "size": size,
        "radius": SHAPES[family].bounding_radius(np.asarray(size)),
        "color": _hsv(s[11], _lerp(s[12], 0.25, 0.9), _lerp(s[13], 0.55, 0.95)),
        "texture": TEXTURE_NAMES.index(tex),
        "texture_params": sample_params(tex, s[15:23], lo=_lerp(s[23], *floor)),
    }


def _delta(t: np.ndarray, color: Sequence[float], lo: float, two_tone: float) -> list[float]:
    """The colour delta of a surface: second colour − lo·colour, or 0 (one colour) with probability 1 − two_tone."""
    if t[0] >= two_tone:
        return [0.0, 0.0, 0.0]
    second = _hsv(t[1], _lerp(t[2], 0.0, 0.9), _lerp(t[3], 0.05, 0.95))
    return [c2 - lo * c1 for c1, c2 in zip(color, second)]


def _sample_one(split: str, seed: int, index: int) -> dict[str, Any]:
    spec = get_split(split)
    rng = scene_rng(split, seed, index)
    u = rng.random(_DRAWS)
    seeds = rng.integers(0, 2**31, size=_V1_OBJECTS + 1)
    x = rng.random(_EXTRA_DRAWS)
    extra_seeds = rng.integers(0, 2**31, size=MAX_OBJECTS - _V1_OBJECTS)
    lo_n, hi_n = spec.objects
    n_objects = lo_n + min(int(u[0] * (hi_n - lo_n + 1)), hi_n - lo_n)
    slot_draws = [u[2 + k * _SLOT_DRAWS : 2 + (k + 1) * _SLOT_DRAWS] for k in range(_V1_OBJECTS)]
    slot_draws += [x[k * _SLOT_DRAWS : (k + 1) * _SLOT_DRAWS] for k in range(MAX_OBJECTS - _V1_OBJECTS)]
    slots = [_slot(s, spec.shapes, spec.object_textures, spec.object_floor) for s in slot_draws]
    out: dict[str, Any] = {key: [s[key] for s in slots] for key in slots[0]}
    out["label"] = min(int(u[1] * len(VOCABULARY)), len(VOCABULARY) - 1)
    out["present"] = np.arange(MAX_OBJECTS) < n_objects
    out["texture_seed"] = np.concatenate([seeds[:_V1_OBJECTS], extra_seeds])
    w = u[2 + _V1_OBJECTS * _SLOT_DRAWS :][:_WALL_DRAWS]
    wall_tex = _pick(w[3], spec.wall_textures)
    out["wall_color"] = _hsv(w[0], _lerp(w[1], 0.0, 0.35), _lerp(w[2], 0.55, 0.9))
    out["wall_texture"] = TEXTURE_NAMES.index(wall_tex)
    out["wall_texture_params"] = sample_params(wall_tex, w[4:12], lo=_lerp(w[12], *spec.wall_floor))
    out["wall_texture_seed"] = seeds[_V1_OBJECTS]
    g = u[2 + _V1_OBJECTS * _SLOT_DRAWS + _WALL_DRAWS :]
    out["glow_position"] = [_lerp(g[0], -GLOW_XY, GLOW_XY), _lerp(g[1], -GLOW_XY, GLOW_XY), _lerp(g[2], *GLOW_Z)]
    # One uniform picks the label (thirds of [0, 1)) and, rescaled, the hue within the label's range.
    tone = g[3] * len(GLOW_VOCABULARY)
    k = min(int(tone), len(GLOW_VOCABULARY) - 1)
    out["glow_label"] = k
    out["glow_tone"] = [tone - k, g[4]]
    out["glow_intensity"] = _lerp(g[5], 1.2, 2.0)
    out["halo_intensity"] = _lerp(g[6], 0.0, 0.2)
    out["halo_radius"] = _lerp(g[7], 0.1, 0.25)
    t = x[(MAX_OBJECTS - _V1_OBJECTS) * _SLOT_DRAWS :]
    tones = [t[i * _TONE_DRAWS : (i + 1) * _TONE_DRAWS] for i in range(MAX_OBJECTS + 1)]
    out["color_delta"] = [
        _delta(tones[i], s["color"], s["texture_params"][8], spec.two_tone) for i, s in enumerate(slots)
    ]
    out["wall_color_delta"] = _delta(
        tones[MAX_OBJECTS], out["wall_color"], out["wall_texture_params"][8], spec.two_tone
    )
    r = t[(MAX_OBJECTS + 1) * _TONE_DRAWS :]
    relief = -1
    out["relief_params"] = np.zeros(N_RELIEF_PARAMS)
    if spec.reliefs and r[0] < spec.relief_probability:
        name = _pick(r[1], spec.reliefs)
        relief = RELIEF_NAMES.index(name)
        out["relief_params"] = RELIEFS[name].sample(r[2:])
    out["relief"] = relief
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
        color_delta=stack("color_delta"),
        wall_color_delta=stack("wall_color_delta"),
        relief=stack("relief", torch.int64),
        relief_params=stack("relief_params"),
    )
