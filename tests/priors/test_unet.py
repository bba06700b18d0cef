"""UNetPrior and its building blocks (lasagna.priors.nn) on toy random instances.

References are independent: numpy float64 for the embeddings and the schedule, and the closed form
of the untrained (zero-output) v-prior, x̂₀ = √ᾱ z_t.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from lasagna.errors import ConditionError
from lasagna.priors.base import Condition
from lasagna.priors.nn import frequency_encoding, timestep_embedding
from lasagna.priors.unet import ScheduleConfig, UNetConfig, UNetPrior

VOCAB = ("left", "right", "top")


def toy_config(**kw) -> UNetConfig:
    base = dict(channels=(8, 16), resolution=8, norm_groups=4, vocabulary=VOCAB, cond_channels=3)
    base.update(kw)
    return UNetConfig(**base)


def randomize(module: torch.nn.Module, seed: int = 0, scale: float = 0.2) -> torch.nn.Module:
    """Non-zero weights everywhere (the real init zeroes output convs, which would hide the inputs)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(torch.randn(p.shape, generator=g, dtype=p.dtype) * scale)
    return module


def numpy_alpha_bar(kind="linear", T=1000, b0=1e-4, b1=0.02) -> np.ndarray:
    if kind == "linear":
        betas = np.linspace(b0, b1, T, dtype=np.float64)
    else:
        betas = np.linspace(b0**0.5, b1**0.5, T, dtype=np.float64) ** 2
    return np.cumprod(1.0 - betas)


_SHARED: dict[str, UNetPrior] = {}


def shared_prior(prediction="v") -> UNetPrior:
    if prediction not in _SHARED:
        _SHARED[prediction] = randomize(UNetPrior(toy_config(prediction=prediction))).eval()
    return _SHARED[prediction]


class TestEmbeddings:
    def test_timestep_embedding_reference(self):
        t = torch.tensor([0, 7, 999])
        got = timestep_embedding(t, 8).double().numpy()
        freqs = np.exp(-math.log(10_000.0) * np.arange(4) / 4)
        args = np.array([0.0, 7.0, 999.0])[:, None] * freqs[None]
        np.testing.assert_allclose(got, np.concatenate([np.cos(args), np.sin(args)], 1), atol=2e-4)

    def test_frequency_encoding_reference(self):
        x = torch.tensor([0.0, 0.25, 1.0])
        got = frequency_encoding(x, 5).double().numpy()
        assert got.shape == (3, 10)  # the paper's 10-dim encoding
        args = np.array([0.0, 0.25, 1.0])[:, None] * (2.0 ** np.arange(5))[None] * np.pi
        np.testing.assert_allclose(got, np.concatenate([np.sin(args), np.cos(args)], 1), atol=1e-5)

    def test_exceptions(self):
        with pytest.raises(ValueError, match="even"):
            timestep_embedding(torch.tensor([1]), 7)
        with pytest.raises(ValueError, match="num_freqs"):
            frequency_encoding(torch.tensor([0.5]), 0)


class TestUNetConfig:
    def test_defaults_are_the_bundled_target(self):
        cfg = UNetConfig(vocabulary=VOCAB, cond_channels=3)
        n = sum(p.numel() for p in UNetPrior(cfg).parameters())
        assert 1_000_000 <= n <= 2_000_000, n  # ~1–2 M parameters at 32² (channels 32/64/128)
        assert cfg.prediction == "v"

    @pytest.mark.parametrize(
        "kw, match",
        [
            (dict(unknown=1), "Extra inputs"),
            (dict(channels=(8, 10)), "multiple of norm_groups"),
            (dict(resolution=6, channels=(8, 16, 32)), "divisible by 2"),
            (dict(vocabulary=("a", "a")), "unique"),
            (dict(vocabulary=("a", "")), "non-empty"),
            (dict(prediction="x0"), "prediction"),
            (dict(schedule=dict(kind="quadratic")), "kind"),
        ],
    )
    def test_invalid(self, kw, match):
        with pytest.raises(ValidationError, match=match):
            toy_config(**kw)


class TestUNetPrior:
    def test_smoke_shapes(self):
        prior = shared_prior()
        z = torch.randn(2, 3, 8, 8)
        pred = prior.predict(z, torch.tensor([0, 999]), Condition(["left", "top"], image=torch.rand(2, 3, 8, 8)))
        assert set(pred.eps) == {"cond", "uncond"}
        for e in pred.eps.values():
            assert e.shape == (2, 3, 8, 8) and torch.isfinite(e).all()
        assert prior.sample_shape == (3, 8, 8)

    def test_one_batched_pass_equals_separate_calls(self):
        prior = shared_prior()
        calls = []
        handle = prior.net.register_forward_hook(lambda m, args, out: calls.append(args[0].shape[0]))
        try:
            z, t, img = torch.randn(2, 3, 8, 8), torch.tensor([10, 500]), torch.rand(2, 3, 8, 8)
            pred = prior.predict(z, t, Condition(["left", "right"], image=img), branches=("cond", "uncond"))
            assert calls == [4]  # cond and uncond in ONE network call
            with torch.no_grad():
                e_c = prior._eps(z, t, torch.tensor([0, 1]), img)
                e_u = prior._eps(z, t, torch.tensor([3, 3]), img)
        finally:
            handle.remove()
        torch.testing.assert_close(pred.eps["cond"], e_c, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(pred.eps["uncond"], e_u, atol=1e-5, rtol=1e-5)
        assert not torch.allclose(e_c, e_u)  # the label matters

    def test_condition_image_matters(self):
        prior = shared_prior()
        z, t = torch.randn(1, 3, 8, 8), torch.tensor([300])
        a = prior._eps(z, t, torch.tensor([0]), torch.zeros(1, 3, 8, 8))
        b = prior._eps(z, t, torch.tensor([0]), torch.ones(1, 3, 8, 8))
        assert (a - b).abs().max() > 1e-3

    def test_v_to_eps_reference(self):
        """ε = √ᾱ v + √(1−ᾱ) z_t with ᾱ from an independent numpy float64 schedule."""
        prior = shared_prior("v")
        z, t, img = torch.randn(3, 3, 8, 8), torch.tensor([0, 421, 999]), torch.rand(3, 3, 8, 8)
        lab = torch.tensor([0, 1, 3])
        with torch.no_grad():
            v = prior.raw(z, t, lab, img).double().numpy()
            eps = prior._eps(z, t, lab, img).double().numpy()
        ab = numpy_alpha_bar()[[0, 421, 999]][:, None, None, None]
        np.testing.assert_allclose(eps, np.sqrt(ab) * v + np.sqrt(1 - ab) * z.double().numpy(), atol=1e-5)

    def test_untrained_v_prior_closed_form(self):
        """The zero-initialised output predicts v = 0, so x̂₀ = √ᾱ z_t exactly (numpy float64 ᾱ)."""
        prior = UNetPrior(toy_config(schedule=ScheduleConfig(kind="scaled_linear", beta_start=0.00085, beta_end=0.012)))
        z, t = torch.randn(2, 3, 8, 8), torch.tensor([5, 900])
        with torch.no_grad():
            eps = prior._eps(z, t, torch.tensor([0, 3]), torch.rand(2, 3, 8, 8))
            x0 = prior.schedule.x0_from_eps(z, eps, t).double().numpy()
        ab = numpy_alpha_bar("scaled_linear", b0=0.00085, b1=0.012)[[5, 900]][:, None, None, None]
        np.testing.assert_allclose(x0, np.sqrt(ab) * z.double().numpy(), atol=1e-5)

    def test_exceptions(self):
        prior = shared_prior()
        z, t = torch.randn(1, 3, 8, 8), torch.tensor([1])
        with pytest.raises(ConditionError, match="expected one of left, right, top"):
            prior.predict(z, t, Condition("bottom", image=torch.rand(1, 3, 8, 8)))
        with pytest.raises(ConditionError, match="needs a conditioning image"):
            prior.predict(z, t, Condition("left"))
        with pytest.raises(ConditionError, match=r"expected \(B, 3, 8, 8\)"):
            prior.predict(z, t, Condition("left", image=torch.rand(1, 3, 4, 4)))
        with pytest.raises(ConditionError, match="z_t has shape"):
            prior.predict(torch.randn(1, 3, 4, 4), t, Condition("left", image=torch.rand(1, 3, 8, 8)))
        no_image = UNetPrior(toy_config(cond_channels=0))
        with pytest.raises(ConditionError, match="takes no conditioning image"):
            no_image.predict(z, t, Condition("left", image=torch.rand(1, 3, 8, 8)))

    def test_nan_propagates(self):
        prior = shared_prior()
        z = torch.randn(2, 3, 8, 8)
        z[0, 0, 0, 0] = float("nan")
        eps = prior._eps(z, torch.tensor([10, 10]), torch.tensor([0, 0]), torch.rand(2, 3, 8, 8))
        assert torch.isnan(eps[0]).any()  # a NaN input is not hidden …
        assert torch.isfinite(eps[1]).all()  # … and does not leak across the batch (GroupNorm is per sample)

    def test_dtypes(self):
        prior = UNetPrior(toy_config(prediction="epsilon"))
        randomize(prior)
        out32 = prior._eps(
            torch.randn(1, 3, 8, 8, dtype=torch.float64), torch.tensor([3]), torch.tensor([0]), torch.rand(1, 3, 8, 8)
        )
        assert out32.dtype == torch.float32  # computed in the prior's dtype
        prior.double()
        out64 = prior._eps(torch.randn(1, 3, 8, 8), torch.tensor([3]), torch.tensor([0]), torch.rand(1, 3, 8, 8))
        assert out64.dtype == torch.float64

    @pytest.mark.parametrize("attention", [False, True])
    def test_gradcheck_float64(self, attention):
        prior = randomize(UNetPrior(toy_config(resolution=4, attention=attention)), scale=0.3).double()
        z = torch.randn(1, 3, 4, 4, dtype=torch.float64, requires_grad=True)
        img = torch.rand(1, 3, 4, 4, dtype=torch.float64)
        assert torch.autograd.gradcheck(
            lambda x: prior._eps(x, torch.tensor([250]), torch.tensor([1]), img), (z,), eps=1e-6, atol=1e-5
        )

    @settings(max_examples=8, deadline=None)
    @given(b=st.integers(1, 4), seed=st.integers(0, 2**16), t=st.integers(0, 999))
    def test_batch_independence(self, b, seed, t):
        """A sample's prediction does not depend on the rest of the batch (per-sample norms)."""
        prior = shared_prior()
        g = torch.Generator().manual_seed(seed)
        z, img = torch.randn(b, 3, 8, 8, generator=g), torch.rand(b, 3, 8, 8, generator=g)
        lab = torch.randint(0, 4, (b,), generator=g)
        tt = torch.full((b,), t)
        with torch.no_grad():
            full = prior._eps(z, tt, lab, img)
            first = prior._eps(z[:1], tt[:1], lab[:1], img[:1])
        torch.testing.assert_close(full[:1], first, atol=1e-5, rtol=1e-5)


class TestTrainingLoss:
    def test_finite_and_seeded(self):
        prior = randomize(UNetPrior(toy_config()))
        x0 = torch.rand(4, 3, 8, 8) * 2 - 1
        lab, img = torch.tensor([0, 1, 2, 0]), torch.rand(4, 3, 8, 8)
        a = prior.training_loss(x0, lab, img, torch.Generator().manual_seed(1))
        b = prior.training_loss(x0, lab, img, torch.Generator().manual_seed(1))
        c = prior.training_loss(x0, lab, img, torch.Generator().manual_seed(2))
        assert torch.isfinite(a) and a.item() == b.item() and a.item() != c.item()
        a.backward()
        grads = [p.grad for p in prior.parameters()]
        assert all(g is not None and torch.isfinite(g).all() for g in grads)

    def test_p_uncond_routes_labels_to_null(self):
        prior = UNetPrior(toy_config())
        seen = []
        handle = prior.net.label_emb.register_forward_hook(lambda m, args, out: seen.append(args[0].clone()))
        x0, lab, img = torch.zeros(6, 3, 8, 8), torch.tensor([0, 1, 2, 0, 1, 2]), torch.rand(6, 3, 8, 8)
        prior.training_loss(x0, lab, img, torch.Generator().manual_seed(0), p_uncond=1.0)
        prior.training_loss(x0, lab, img, torch.Generator().manual_seed(0), p_uncond=0.0)
        handle.remove()
        assert seen[0].tolist() == [3] * 6 and seen[1].tolist() == lab.tolist()
        with pytest.raises(ValueError, match="p_uncond"):
            prior.training_loss(x0, lab, img, None, p_uncond=1.5)

    @pytest.mark.parametrize("prediction", ["epsilon", "v"])
    def test_target_matches_the_objective(self, prediction):
        """The untrained network outputs 0, so the loss is mean(target²). Replaying the generator's
        draws (t, then ε) and building the target in numpy float64 — ε, or v = √ᾱ ε − √(1−ᾱ) x₀
        (Salimans & Ho 2022) — gives the value independently."""
        prior = UNetPrior(toy_config(prediction=prediction))
        x0 = torch.rand(5, 3, 8, 8) * 2 - 1
        lab, img = torch.zeros(5, dtype=torch.long), torch.rand(5, 3, 8, 8)
        loss = prior.training_loss(x0, lab, img, torch.Generator().manual_seed(7))
        g = torch.Generator().manual_seed(7)
        t = torch.randint(0, 1000, (5,), generator=g).numpy()
        eps = torch.randn((5, 3, 8, 8), generator=g).double().numpy()
        ab = numpy_alpha_bar()[t][:, None, None, None]
        target = eps if prediction == "epsilon" else np.sqrt(ab) * eps - np.sqrt(1 - ab) * x0.double().numpy()
        assert loss.item() == pytest.approx(float(np.mean(target**2)), rel=1e-5)

    def test_overfits_one_batch(self):
        torch.manual_seed(0)
        prior = UNetPrior(toy_config())
        x0 = (torch.rand(8, 3, 8, 8) > 0.5).float() * 2 - 1
        lab, img = torch.randint(0, 3, (8,)), torch.rand(8, 3, 8, 8)
        opt = torch.optim.Adam(prior.parameters(), lr=3e-3)
        first = None
        for step in range(60):
            loss = prior.training_loss(x0, lab, img, torch.Generator().manual_seed(step % 4))
            first = loss.item() if first is None else first
            opt.zero_grad()
            loss.backward()
            opt.step()
        final = sum(prior.training_loss(x0, lab, img, torch.Generator().manual_seed(s)).item() for s in range(4)) / 4
        assert final < 0.7 * first, (first, final)


class TestDirections:
    """A prior conditioned on any light direction (issue #11): named labels are their unit vectors."""

    def _prior(self, seed: int = 0):
        from lasagna.priors.unet import UNetConfig, UNetPrior
        from lasagna.world import VOCABULARY

        torch.manual_seed(seed)
        cfg = UNetConfig(
            cond_channels=3,
            resolution=8,
            channels=(8, 16),
            norm_groups=4,
            vocabulary=tuple(VOCABULARY),
            directions=True,
        )
        prior = UNetPrior(cfg)
        with torch.no_grad():
            for p in prior.parameters():
                p.add_(0.05 * torch.randn_like(p))
        return prior.eval()

    def test_rows_are_the_unit_vectors_of_the_world(self):
        from lasagna.priors.unet import direction_rows
        from lasagna.world.lighting import LIGHTS, direction_vector

        rows = direction_rows(["left", "az=135,el=60", "az=10,el=35", None], dtype=torch.float64)
        assert torch.allclose(rows[0, :3], torch.tensor(LIGHTS["left"], dtype=torch.float64), atol=1e-15)
        assert torch.allclose(rows[1, :3], torch.tensor(LIGHTS["top-left"], dtype=torch.float64), atol=1e-15)
        assert torch.allclose(rows[2, :3], torch.tensor(direction_vector(10, 35), dtype=torch.float64), atol=1e-15)
        assert rows[:3, 3].tolist() == [0, 0, 0] and rows[3].tolist() == [0, 0, 0, 1]

    def test_a_named_label_and_its_angles_give_the_same_prediction(self):
        from lasagna.priors.base import Condition

        prior = self._prior()
        z, t, img = torch.randn(1, 3, 8, 8), torch.tensor([400]), torch.rand(1, 3, 8, 8)
        a = prior.predict(z, t, Condition(["top-left"], image=img)).eps["cond"]
        b = prior.predict(z, t, Condition(["az=135,el=60"], image=img)).eps["cond"]
        c = prior.predict(z, t, Condition(["az=150,el=60"], image=img)).eps["cond"]
        assert torch.allclose(a, b, atol=1e-6) and not torch.allclose(a, c, atol=1e-6)
        u = prior.predict(z, t, Condition([""], image=img)).eps["cond"]
        assert torch.allclose(u, prior.predict(z, t, Condition(["left"], image=img)).eps["uncond"], atol=1e-6)

    def test_label_dropout_uses_the_null_row_and_the_loss_trains(self):
        from lasagna.priors.unet import direction_rows

        prior = self._prior(1)
        rows = direction_rows(["left", "az=200,el=45"] * 4)
        x0 = torch.rand(8, 3, 8, 8) * 2 - 1
        img = torch.rand(8, 3, 8, 8)
        all_null = prior.training_loss(x0, rows, img, torch.Generator().manual_seed(0), p_uncond=1.0)
        null = prior.training_loss(x0, direction_rows([None] * 8), img, torch.Generator().manual_seed(0), p_uncond=0.0)
        assert torch.allclose(all_null, null)  # the same t, ε and the null rows
        opt = torch.optim.Adam(prior.parameters(), 1e-2)
        first = None
        for i in range(30):
            loss = prior.training_loss(x0, rows, img, torch.Generator().manual_seed(i % 2))
            first = first if first is not None else float(loss.detach())
            opt.zero_grad()
            loss.backward()
            opt.step()
        assert float(loss.detach()) < first

    def test_a_bad_direction_is_one_condition_error(self):
        from lasagna.errors import ConditionError

        with pytest.raises(ConditionError, match="condition.labels.*az=A,el=E"):
            self._prior().label_tensor(["az=10,el=99"])


def test_channels_last_is_the_same_network_to_rounding(tmp_path):
    """`UNetPrior.channels_last` (NHWC weights and activations, what `load_prior` gives a frozen prior on the CPU)
    predicts what the NCHW network does to float32 rounding, in the NCHW layout; `load_prior` lays a saved prior
    out so."""
    from lasagna.components import PriorSource, load_prior

    prior = randomize(UNetPrior(toy_config()).eval())
    g = torch.Generator().manual_seed(1)
    z, image = torch.randn(5, 3, 8, 8, generator=g), torch.rand(5, 3, 8, 8, generator=g)
    t, label = torch.randint(0, 1000, (5,), generator=g), prior.label_tensor(["left", "top", "right", "left", "top"])
    with torch.inference_mode():
        want = prior.raw(z, t, label, image)
        got = prior.channels_last().raw(z, t, label, image)
    assert prior.net.inp.weight.is_contiguous(memory_format=torch.channels_last)
    assert got.is_contiguous() and got.shape == want.shape
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    prior.save_pretrained(tmp_path / "p")
    loaded = load_prior(PriorSource(kind="unet", folder=tmp_path / "p"))
    assert loaded.net.inp.weight.is_contiguous(memory_format=torch.channels_last)
