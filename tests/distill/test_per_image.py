"""Per-image distillation on closed-form Gaussian priors: convergence to the known optimum, early
stopping, seeded reproducibility, the patch strategy, batching, checkpoints and resume, settings."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from lasagna.distill import DistillSettings, EarlyStop, PatchConfig, Weights, distill_image, resolve_settings
from lasagna.distill.per_image import converged
from lasagna.document.preset import load_preset
from lasagna.errors import LasagnaError
from lasagna.generators import LayerGenerator, LayerGeneratorConfig, LayerSpec, composite
from lasagna.losses.lmc_sds import identity_corrective
from lasagna.priors import GaussianPrior

from .conftest import SHADING, gaussian_for

LAYERS = Path(__file__).resolve().parents[2] / "layers"
PLAIN = DistillSettings(layer=SHADING, loss="sds", weights=Weights(), early_stop=None)  # no L2, no early stop


class TestConvergence:
    def test_multiplier_reaches_the_target_shading(self, shading_problem):
        base, shading, prior = shading_problem
        r = distill_image(base, PLAIN, prior, condition="x", steps=200, lr=0.05, lr_final=0.05, seed=0)
        start = (1.0 - shading).abs().max()
        assert float((r.layer[0] - shading).abs().max()) < 2e-3 < 0.01 * float(start)
        assert torch.allclose(r.composite[0], (base * shading).clamp(0, 1), atol=3e-3)
        assert r.stopped_reason == "steps" and r.steps == 200 and len(r.history) == 200

    def test_callback_sees_every_step_before_its_update(self, shading_problem):
        base, shading, prior = shading_problem
        seen = []
        r = distill_image(
            base,
            PLAIN,
            prior,
            condition="x",
            steps=30,
            lr=0.05,
            seed=0,
            callback=lambda step, layer: seen.append((step, layer.clone())),
        )
        assert [s for s, _ in seen] == list(range(30))
        assert torch.equal(seen[0][1], torch.ones_like(seen[0][1]))  # the identity edit, before any update
        first, last = ((y[0] - shading).abs().mean() for y in (seen[1][1], seen[-1][1]))
        assert last < first  # it traces the optimisation, which approaches the target
        assert not torch.equal(seen[-1][1], r.layer)  # the result includes the last update; the trace does not

    def test_regulariser_alone_keeps_the_identity(self, shading_problem):
        base, _, prior = shading_problem
        only_l2 = Weights(score=dict(start=0.0, end=0.0), reg=dict(start=1.0, end=1.0))
        r = distill_image(base, PLAIN, prior, condition="x", steps=20, weights=only_l2)
        assert torch.equal(r.layer, torch.ones_like(r.layer))

    def test_batch_of_different_problems(self):
        """B images optimised at once each reach their own optimum (one prior label per image)."""
        g = torch.Generator().manual_seed(3)
        base = 0.3 + 0.6 * torch.rand(2, 3, 4, 4, generator=g)
        shading = 0.4 + torch.rand(2, 1, 4, 4, generator=g)
        mus = {lab: (base[i] * shading[i] * 2 - 1).double().reshape(-1) for i, lab in enumerate(("a", "b"))}
        prior = GaussianPrior((3, 4, 4), mus, {"a": 1e-3, "b": 1e-3}, unconditional=(mus["a"], 1e-3))
        r = distill_image(base, PLAIN, prior, condition=["a", "b"], steps=200, lr=0.05, lr_final=0.05)
        assert float((r.layer - shading).abs().max()) < 5e-3

    @pytest.mark.parametrize("loss", ["sds", "lmc-sds", "dds", "nfsd", "ms-sds"])
    def test_every_loss_runs(self, shading_problem, loss):
        base, _, prior = shading_problem
        r = distill_image(
            base, PLAIN, prior, identity_corrective, condition="x", negative="x", loss=loss, steps=3, guidance=2.0
        )
        assert r.layer.shape == (1, 1, 4, 4) and torch.isfinite(r.layer).all() and len(r.history) == 3


class TestEarlyStopping:
    def test_stops_on_a_converged_problem(self, shading_problem):
        base, shading, prior = shading_problem
        rule = EarlyStop(window=10, min_steps=20, rtol=0.0)
        r = distill_image(base, PLAIN, prior, condition="x", steps=600, lr=0.05, lr_final=1.0, early_stop=rule)
        assert r.stopped_reason == "converged" and 40 <= r.steps < 600
        assert float((r.layer[0] - shading).abs().max()) < 0.05
        assert converged(r.history, rule, "whole")

    def test_rule_on_synthetic_histories(self):
        rule = EarlyStop(window=3, min_steps=0, rtol=0.1)
        rec = lambda g, c: {"phase": "whole", "grad_norm": g, "layer_change": c}  # noqa: E731
        falling = [rec(10 - i, 10 - i) for i in range(6)]
        flat = [rec(1.0, 1.0)] * 6
        half = [rec(1.0, 10 - i) for i in range(6)]  # gradient flat, layer still moving
        assert (
            not converged(falling, rule, "whole")
            and converged(flat, rule, "whole")
            and not converged(half, rule, "whole")
        )
        assert not converged(flat[:5], rule, "whole")  # needs 2 windows
        assert not converged(flat, EarlyStop(window=3, min_steps=7), "whole")
        assert not converged(flat, rule, "patch")  # only the given phase counts

    def test_off_runs_every_step(self, shading_problem):
        base, _, prior = shading_problem
        r = distill_image(base, PLAIN, prior, condition="x", steps=80, lr=0.05, early_stop=False)
        assert r.steps == 80 and r.settings.early_stop is None


class TestReproducibility:
    def test_same_seed_same_result(self, shading_problem):
        base, _, prior = shading_problem
        a = distill_image(base, PLAIN, prior, condition="x", steps=15, seed=7)
        b = distill_image(base, PLAIN, prior, condition="x", steps=15, seed=7)
        c = distill_image(base, PLAIN, prior, condition="x", steps=15, seed=8)
        assert torch.equal(a.layer, b.layer) and not torch.equal(a.layer, c.layer)
        assert [h["t_mean"] for h in a.history] == [h["t_mean"] for h in b.history]

    def test_given_generator_is_not_modified(self, shading_problem):
        base, _, prior = shading_problem
        torch.manual_seed(0)
        gen = LayerGenerator(LayerGeneratorConfig(layer=SHADING, vocabulary=("x",), channels=(8, 8)))
        before = {k: v.clone() for k, v in gen.state_dict().items()}
        r = distill_image(base, PLAIN, prior, condition="x", steps=5, generator=gen, lr=1e-2)
        assert all(torch.equal(before[k], v) for k, v in gen.state_dict().items())
        assert isinstance(r.model, LayerGenerator) and not torch.equal(r.layer, torch.ones_like(r.layer))


class TestPatches:
    def test_whole_then_patches_on_a_larger_image(self):
        """An 8×8 image and a 4×4 prior: the first 30 % of the steps see the downsampled image, then crops;
        a uniform target (every view has the same optimum) is reached at every pixel."""
        base = torch.tensor([0.5, 0.7, 0.3]).view(3, 1, 1).expand(3, 8, 8).contiguous()
        prior = gaussian_for(base[:, :4, :4] * 0.6)
        r = distill_image(
            base,
            PLAIN,
            prior,
            condition="x",
            steps=200,
            lr=0.05,
            lr_final=0.05,
            patches=PatchConfig(whole_fraction=0.3, per_step=2),
        )
        phases = [h["phase"] for h in r.history]
        assert phases == ["whole"] * 60 + ["patch"] * 140
        assert r.layer.shape == (1, 1, 8, 8) and float((r.layer - 0.6).abs().max()) < 5e-3

    def test_generator_fully_convolutional_on_patches(self):
        base = torch.rand(1, 3, 12, 8)
        prior = gaussian_for(torch.rand(3, 4, 4))
        gen = LayerGenerator(LayerGeneratorConfig(layer=SHADING, vocabulary=("x",), channels=(8, 8)))
        r = distill_image(base, PLAIN, prior, condition="x", steps=4, generator=gen)
        assert [h["phase"] for h in r.history] == ["whole"] * 2 + ["patch"] * 2 and r.layer.shape == (1, 1, 12, 8)

    def test_smaller_than_the_prior_uses_the_whole_view(self):
        prior = gaussian_for(torch.rand(3, 4, 4))
        r = distill_image(torch.rand(3, 3, 3), PLAIN, prior, condition="x", steps=3)
        assert {h["phase"] for h in r.history} == {"whole"} and r.layer.shape == (1, 1, 3, 3)


class TestCheckpoints:
    class Killer:
        """A prior that dies at its n-th call (a kill mid-run), delegating to a real prior."""

        def __init__(self, prior, n):
            self.prior, self.n = prior, n

        def __getattr__(self, name):
            return getattr(self.prior, name)

        def predict_many(self, *args, **kwargs):
            self.n -= 1
            if self.n < 0:
                raise KeyboardInterrupt("killed")
            return self.prior.predict_many(*args, **kwargs)

    def test_resume_after_kill_equals_uninterrupted(self, shading_problem, tmp_path):
        base, _, prior = shading_problem
        kw = dict(
            condition="x",
            steps=30,
            seed=3,
            checkpoint_every=8,
            early_stop=EarlyStop(window=4, min_steps=10_000, rtol=0.0),
        )
        full = distill_image(base, PLAIN, prior, **kw)
        with pytest.raises(KeyboardInterrupt):
            distill_image(base, PLAIN, self.Killer(prior, 21), checkpoint_dir=tmp_path, **kw)
        assert (tmp_path / "checkpoint.safetensors").is_file()
        resumed = distill_image(base, PLAIN, prior, checkpoint_dir=tmp_path, **kw)
        assert torch.equal(resumed.layer, full.layer) and resumed.steps == 30
        strip = lambda h: {k: v for k, v in h.items() if k != "time_s"}  # noqa: E731
        assert [strip(h) for h in resumed.history] == [strip(h) for h in full.history]
        again = distill_image(base, PLAIN, prior, checkpoint_dir=tmp_path, **kw)  # finished: nothing to do
        assert torch.equal(again.layer, full.layer)

    def test_other_inputs_refuse_the_folder(self, shading_problem, tmp_path):
        base, _, prior = shading_problem
        distill_image(base, PLAIN, prior, condition="x", steps=2, checkpoint_dir=tmp_path)
        with pytest.raises(LasagnaError, match="different base_sha256"):
            distill_image(base * 0.5, PLAIN, prior, condition="x", steps=2, checkpoint_dir=tmp_path)
        with pytest.raises(LasagnaError, match="different lr"):
            distill_image(base, PLAIN, prior, condition="x", steps=2, lr=0.1, checkpoint_dir=tmp_path)


class TestSettings:
    def test_from_preset_with_overrides(self):
        preset = load_preset(LAYERS / "shading")
        s = resolve_settings(preset, steps=7, guidance=3.0, lr=None)
        assert s.layer == LayerSpec.from_preset(preset) and s.steps == 7 and s.guidance == 3.0
        assert s.loss == preset.distill.loss and s.lr == preset.distill.lr
        assert s.resolved_weights().reg.steps == 2  # steps // 3

    def test_whole_fraction_comes_from_the_preset(self, shading_problem):
        # shading refines detail on native-resolution crops (measured +0.35 dB at 64²); light stays on the
        # whole image (crops cost it 2.6 dB: a 32² prior shown a zoomed crop lights it like a whole scene)
        assert resolve_settings(load_preset(LAYERS / "shading")).patches.whole_fraction == 0.4
        light = load_preset(LAYERS / "light")
        assert resolve_settings(light).patches.whole_fraction == 1.0
        base, _, prior = shading_problem
        big = torch.nn.functional.interpolate(base, scale_factor=2)  # larger than the prior: patches possible
        whole = load_preset(LAYERS / "shading").model_copy(deep=True)
        whole = type(whole).model_validate(
            {**whole.model_dump(), "distill": {**whole.distill.model_dump(), "whole_fraction": 1.0}}
        )
        r = distill_image(big, resolve_settings(whole, steps=4, loss="sds"), prior, condition="x", early_stop=False)
        assert [h["phase"] for h in r.history] == ["whole"] * 4

    def test_defaults_and_errors(self):
        assert DistillSettings(layer=SHADING).loss == "lmc-sds"
        with pytest.raises(LasagnaError, match="settings.guidance"):
            resolve_settings(PLAIN, guidance=-1.0)
        with pytest.raises(LasagnaError, match="settings.bogus"):
            resolve_settings(PLAIN, bogus=1)
        with pytest.raises(LasagnaError, match="expected a Preset or DistillSettings"):
            resolve_settings({"steps": 3})

    def test_input_errors(self, shading_problem):
        base, _, prior = shading_problem
        with pytest.raises(LasagnaError, match=r"expected \[0, 1\]"):
            distill_image(base * 3, PLAIN, prior, condition="x", steps=1)
        with pytest.raises(LasagnaError, match="NaN"):
            distill_image(base * float("nan"), PLAIN, prior, condition="x", steps=1)
        with pytest.raises(LasagnaError, match="2 labels for a batch of 1"):
            distill_image(base, PLAIN, prior, condition=["x", "x"], steps=1)
        with pytest.raises(LasagnaError, match="corrective"):
            distill_image(base, PLAIN, prior, condition="x", loss="lmc-sds", steps=1)
        other = LayerGenerator(
            LayerGeneratorConfig(layer=LayerSpec(blend="plus", channels=3), vocabulary=("x",), channels=(8,))
        )
        with pytest.raises(LasagnaError, match="settings' layer"):
            distill_image(base, PLAIN, prior, condition="x", generator=other, steps=1)

    def test_composite_is_clamped_output(self):
        prior = gaussian_for(torch.ones(3, 4, 4))  # pulls towards white: a multiplier > 1 overshoots on bright pixels
        base = torch.full((3, 4, 4), 0.9)
        r = distill_image(base, PLAIN, prior, condition="x", steps=60, lr=0.1)
        assert float(r.layer.max()) > 1.0 and float(r.composite.max()) <= 1.0
        assert torch.equal(r.composite, composite(base[None], r.layer, SHADING).clamp(0, 1))


class TestFreeStart:
    """The free layer starts at an identity edit; an alpha layer at the base's own colour, opaque."""

    def test_alpha_layer_starts_opaque_at_the_base_colour(self):
        from lasagna.distill.per_image import _make_model

        spec = LayerSpec(blend="normal", channels=4)
        base = torch.rand(2, 3, 6, 5, generator=torch.Generator().manual_seed(0))
        model = _make_model("free", DistillSettings(layer=spec), base)
        layer = model()
        assert torch.all(layer[:, 3] == 1.0)
        # colour = base up to the sigmoid's end clamp (numerics.LOGIT_EPS) and float32 rounding
        torch.testing.assert_close(composite(base, layer, spec), base, atol=2e-6, rtol=0)
        # and, unlike at α = 0, the colour receives the composite's gradient in full
        g = torch.randn(base.shape, generator=torch.Generator().manual_seed(1))
        (composite(base, layer, spec) * g).sum().backward()
        assert float(model.u.grad[:, :3].abs().sum()) > 0

    def test_other_layers_start_at_their_identity_value(self):
        from lasagna.distill.per_image import _make_model

        base = torch.rand(1, 3, 4, 4, generator=torch.Generator().manual_seed(0))
        for spec, value in ((SHADING, 1.0), (LayerSpec(blend="plus", channels=3), 0.0)):
            assert torch.all(_make_model("free", DistillSettings(layer=spec), base)() == value)


class TestParticles:
    """``particles`` = k: k free layers per image with their own noise draws, averaged at the end."""

    def test_the_layer_is_the_mean_of_k_independent_runs_in_one_batch(self, shading_problem):
        base, shading, prior = shading_problem
        one_image = base if base.dim() == 4 else base.unsqueeze(0)
        base2 = torch.cat([one_image, one_image.flip(-1)])
        seen = []
        r = distill_image(
            base2,
            PLAIN,
            prior,
            condition=["x", "x"],
            steps=12,
            lr=0.05,
            seed=3,
            particles=3,
            callback=lambda step, layer: seen.append(layer),
        )
        assert r.layer.shape == (2, 1, *base.shape[-2:]) and seen[0].shape == r.layer.shape
        assert r.settings.particles == 3
        with torch.no_grad():
            every = r.model(base2.repeat_interleave(3, dim=0))  # the 6 particle layers, image by image
        assert not torch.equal(every[0], every[1])  # particles differ: each has its own noise draws
        torch.testing.assert_close(r.layer, every.view(2, 3, *every.shape[1:]).mean(1))
        torch.testing.assert_close(r.composite, composite(base2, r.layer, SHADING).clamp(0, 1))
        again = distill_image(base2, PLAIN, prior, condition=["x", "x"], steps=12, lr=0.05, seed=3, particles=3)
        assert torch.equal(again.layer, r.layer)  # seeded
        one = distill_image(base2, PLAIN, prior, condition=["x", "x"], steps=12, lr=0.05, seed=3)
        assert not torch.equal(one.layer, r.layer)

    def test_a_given_start_is_every_particles_start(self, shading_problem):
        from lasagna.generators import FreeLayer

        base, _, prior = shading_problem
        start = FreeLayer.from_layer(SHADING, torch.full((1, 1, *base.shape[-2:]), 0.7))
        r = distill_image(base, PLAIN, prior, condition="x", steps=0 + 1, lr=1e-9, generator=start, particles=4)
        torch.testing.assert_close(r.layer, start(), atol=1e-6, rtol=0)  # a negligible step from the start
        assert start.u.shape[0] == 1  # the caller's layer is not modified

    def test_averaging_reduces_the_score_noise(self, shading_problem):
        """On a Gaussian prior whose optimum is known, the mean of 8 particles lands nearer it than one run
        after the same steps (the per-step noise of SDS averages out)."""
        base, shading, prior = shading_problem
        errs = {}
        for k in (1, 8):
            r = distill_image(base, PLAIN, prior, condition="x", steps=15, lr=0.05, lr_final=0.05, seed=0, particles=k)
            errs[k] = float((r.layer[0] - shading).pow(2).mean())
        assert errs[8] < errs[1]

    def test_a_mirror_ensemble_mirrors_each_particle_and_maps_it_back(self, shading_problem):
        """``particle_mirrors``: particle j sees the image mirrored by PARTICLE_MIRRORS[j % 4] and its light mirrored
        with it (left ↔ right, top-left ↔ bottom-right); mirroring is an involution, so the same map brings a
        particle's layer back; the layer is the mean of the particles mapped back; a condition that is not a light is
        refused in one line."""
        from lasagna.distill.per_image import PARTICLE_MIRRORS, _mirror_labels, _mirror_particles

        x = torch.rand(8, 1, 3, 5, generator=torch.Generator().manual_seed(1))
        once = _mirror_particles(x, 4)
        assert torch.equal(once[1], x[1].flip(-1)) and torch.equal(once[2], x[2].flip(-2))
        assert torch.equal(once[7], x[7].flip(-1, -2)) and torch.equal(once[4], x[4])
        assert torch.equal(_mirror_particles(once, 4), x)
        assert _mirror_labels(["top-left"] * 4, 4) == ["top-left", "top-right", "bottom-left", "bottom-right"]
        assert PARTICLE_MIRRORS[0] == (False, False)
        base, shading, _ = shading_problem
        prior = gaussian_for(base * shading, labels=("x", "left", "right"))
        settings = PLAIN.with_overrides(particle_mirrors=True)
        r = distill_image(base, settings, prior, condition="left", steps=6, lr=0.05, seed=3, particles=4)
        with torch.no_grad():
            every = r.model(base.expand(1, -1, -1, -1).repeat_interleave(4, dim=0))
        torch.testing.assert_close(r.layer, _mirror_particles(every, 4).mean(0, keepdim=True))
        with pytest.raises(LasagnaError, match="particle_mirrors"):
            distill_image(base, settings, prior, condition="x", steps=1, particles=4)

    @pytest.mark.parametrize("bad", [0, 17])
    def test_out_of_range_is_one_line(self, bad):
        with pytest.raises(LasagnaError, match="particles"):
            PLAIN.with_overrides(particles=bad)
        with pytest.raises(Exception, match="particles"):
            load_preset(LAYERS / "relight" / "preset.json").model_copy().model_validate(
                {**load_preset(LAYERS / "relight" / "preset.json").model_dump(), "distill": {"particles": bad}}
            )
