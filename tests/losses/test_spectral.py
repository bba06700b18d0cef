"""The spectral corrective b̂ (a per-t linear frequency response fitted in closed form).

References are numpy float64 FFTs; the fit is checked to recover known filters exactly and, on the
closed-form blur prior of test_corrective, to lower L_k below the trivial b̂ = z.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from lasagna.catalogue import load_corrective
from lasagna.cli import main as cli_main
from lasagna.losses import LMCSDS
from lasagna.losses.lmc_sds import identity_corrective
from lasagna.losses.spectral import SpectralCorrective, SpectralCorrectiveConfig, fit_spectral_corrective
from lasagna.priors.base import Condition
from lasagna.priors.unet import UNetConfig, UNetPrior
from lasagna.training import corrective as ct
from tests.losses.test_corrective import BlurPrior, toy_source

CFG = SpectralCorrectiveConfig(channels=3, height=8, width=8, buckets=4, num_timesteps=1000)


def random_gains(seed: int = 0, config: SpectralCorrectiveConfig = CFG) -> SpectralCorrective:
    model = SpectralCorrective(config)
    g = torch.Generator().manual_seed(seed)
    model.gain_real.copy_(torch.rand(model.gain_real.shape, generator=g) * 1.5)
    model.gain_imag.copy_(torch.randn(model.gain_imag.shape, generator=g) * 0.3)
    return model.eval()


def numpy_apply(model: SpectralCorrective, z: np.ndarray, t: np.ndarray) -> np.ndarray:
    """irfft2(H[bucket] · rfft2(z)) in float64, the bucket computed independently."""
    c = model.config
    out = []
    for zi, ti in zip(z.astype(np.float64), t):
        k = min(int(ti) * c.buckets // c.num_timesteps, c.buckets - 1)
        h = model.gain_real[k].double().numpy() + 1j * model.gain_imag[k].double().numpy()
        out.append(np.fft.irfft2(h * np.fft.rfft2(zi), s=(c.height, c.width)))
    return np.stack(out)


def circular_filter(z: torch.Tensor, kernel: np.ndarray) -> torch.Tensor:
    """z circularly convolved with a 3×3 kernel per channel (numpy float64, then float32)."""
    zn = z.double().numpy()
    out = np.zeros_like(zn)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            out += kernel[dy + 1, dx + 1] * np.roll(zn, (dy, dx), axis=(-2, -1))
    return torch.from_numpy(out).float()


class TestSpectralCorrective:
    def test_reference_values(self):
        model = random_gains()
        z = torch.randn(5, 3, 8, 8)
        t = torch.tensor([0, 249, 250, 999, 600])
        torch.testing.assert_close(
            model(z, t), torch.from_numpy(numpy_apply(model, z.numpy(), t.numpy())).float(), atol=1e-5, rtol=1e-5
        )

    def test_unfitted_is_the_trivial_corrective(self):
        z = torch.randn(2, 3, 8, 8)
        torch.testing.assert_close(SpectralCorrective(CFG)(z, torch.tensor([3, 990])), z, atol=1e-6, rtol=0)

    def test_buckets(self):
        m = SpectralCorrective(CFG)
        assert m.bucket(torch.tensor([0, 249, 250, 499, 500, 999, 5000])).tolist() == [0, 0, 1, 1, 2, 3, 3]

    def test_condition_is_ignored(self):
        model, z, t = random_gains(), torch.randn(2, 3, 8, 8), torch.tensor([10, 900])
        torch.testing.assert_close(
            model(z, t, cond_image=torch.rand(2, 3, 8, 8), label_idx=torch.tensor([0, 1])), model(z, t)
        )

    @settings(max_examples=25, deadline=None)
    @given(a=st.floats(-3, 3), b=st.floats(-3, 3), dy=st.integers(0, 7), dx=st.integers(0, 7), seed=st.integers(0, 100))
    def test_linear_and_shift_equivariant(self, a, b, dy, dx, seed):
        model = random_gains(seed)
        g = torch.Generator().manual_seed(seed)
        z1, z2 = torch.randn(2, 3, 8, 8, generator=g), torch.randn(2, 3, 8, 8, generator=g)
        t = torch.randint(0, 1000, (2,), generator=g)
        torch.testing.assert_close(model(a * z1 + b * z2, t), a * model(z1, t) + b * model(z2, t), atol=1e-4, rtol=1e-4)
        torch.testing.assert_close(
            model(z1.roll((dy, dx), (-2, -1)), t), model(z1, t).roll((dy, dx), (-2, -1)), atol=1e-5, rtol=1e-5
        )

    def test_exceptions(self):
        with pytest.raises(ValueError, match=r"expected \(B, 3, 8, 8\)"):
            SpectralCorrective(CFG)(torch.randn(1, 3, 16, 16), torch.tensor([1]))
        with pytest.raises(ValueError, match="outside bucket"):
            fit_spectral_corrective(
                CFG, lambda k: (torch.randn(2, 3, 8, 8), torch.tensor([999, 999]), torch.randn(2, 3, 8, 8)), 1
            )

    def test_save_load_and_catalogue_dispatch(self, tmp_path):
        model = random_gains(3)
        model.save_pretrained(tmp_path / "spec")
        assert json.loads((tmp_path / "spec" / "config.json").read_text())["format"] == "lasagna.spectral_corrective"
        loaded = load_corrective(tmp_path / "spec")
        assert isinstance(loaded, SpectralCorrective) and loaded.config == model.config
        z, t = torch.randn(2, 3, 8, 8), torch.tensor([5, 700])
        torch.testing.assert_close(loaded(z, t), model(z, t), atol=0, rtol=0)


class TestFit:
    def test_recovers_known_filters_per_bucket(self):
        """ẑ = (a per-bucket circular 3×3 filter of z) exactly: the fit returns that filter's response."""
        kernels = [
            np.full((3, 3), 1 / 9),
            np.eye(3) / 3,
            np.array([[0, 0, 0], [0, 0, 1.0], [0, 0, 0]]),
            np.diag([0.2, 0.5, 0.3])[::-1],
        ]
        gen = torch.Generator().manual_seed(0)

        def draw(k):
            z = torch.randn(6, 3, 8, 8, generator=gen)
            t = torch.randint(k * 250, (k + 1) * 250, (6,), generator=gen)
            return z, t, circular_filter(z, kernels[k])

        model = fit_spectral_corrective(CFG, draw, batches=2)
        assert model.config.fit_images == 12
        z, t = torch.randn(4, 3, 8, 8), torch.tensor([10, 300, 600, 900])
        want = torch.stack([circular_filter(z[i : i + 1], kernels[i])[0] for i in range(4)])
        torch.testing.assert_close(model(z, t), want, atol=1e-4, rtol=1e-4)

    def test_frequencies_no_image_excites_keep_the_identity(self):
        def flat(k):
            return (
                torch.ones(2, 3, 8, 8) * torch.tensor([1.0, -2.0]).view(2, 1, 1, 1),
                torch.full((2,), k * 250),
                torch.ones(2, 3, 8, 8) * 0.5 * torch.tensor([1.0, -2.0]).view(2, 1, 1, 1),
            )

        model = fit_spectral_corrective(CFG, flat, batches=1)
        assert torch.allclose(model.gain_real[:, :, 0, 0], torch.full((4, 3), 0.5))  # DC: fitted
        assert torch.equal(
            model.gain_real[:, :, 1:, :], torch.ones_like(model.gain_real[:, :, 1:, :])
        )  # the rest: identity
        assert torch.equal(model.gain_imag, torch.zeros_like(model.gain_imag))

    def test_blur_prior_lowers_lk_and_writes_the_run(self, tmp_path):
        res = ct.fit_spectral(
            BlurPrior(), toy_source, tmp_path / "run", batch_size=16, batches=4, buckets=5, eval_batches=2
        )
        assert res.ratio < 0.5, (res.lk_trained, res.lk_trivial)  # a box blur IS a linear filter: most of L_k goes
        metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
        assert metrics["kind"] == "spectral" and metrics["ratio"] == pytest.approx(res.ratio)
        assert metrics["fit_images_per_bucket"] == 64
        loaded = load_corrective(tmp_path / "run" / "corrective")
        assert isinstance(loaded, SpectralCorrective) and loaded.config.buckets == 5 and loaded.config.fit_images == 64

    def test_zero_batches_is_refused(self, tmp_path):
        from lasagna.errors import LasagnaError

        with pytest.raises(LasagnaError, match="batches is 0; expected at least 1"):
            ct.fit_spectral(BlurPrior(), toy_source, tmp_path / "run", batches=0)
        assert not (tmp_path / "run").exists()

    def test_cli(self, tmp_path, capsys):
        UNetPrior(UNetConfig(channels=(4, 8), resolution=8, norm_groups=4, vocabulary=("a", "b"))).save_pretrained(
            tmp_path / "p"
        )
        code = cli_main(
            [
                "train-corrective",
                "--kind",
                "spectral",
                "--prior",
                str(tmp_path / "p"),
                "--source",
                "tests.losses.test_corrective:toy_source",
                "--out",
                str(tmp_path / "o"),
                "--batches",
                "1",
                "--buckets",
                "2",
                "--batch-size",
                "4",
                "--eval-batches",
                "1",
            ]
        )
        captured = capsys.readouterr()
        assert code == 0, captured.err
        out = json.loads(captured.out.strip().splitlines()[-1])
        assert out["kind"] == "spectral" and out["lk_trivial"] > 0
        assert (tmp_path / "o" / "corrective" / "model.safetensors").is_file()


class TestInLMCSDS:
    def test_unfitted_spectral_equals_the_identity_corrective(self):
        from tests.losses.conftest import ConvPrior

        prior = ConvPrior(shape=(3, 8, 8))
        z = torch.rand(2, 3, 8, 8) * 2 - 1
        cond = Condition(["a", "b"])
        spec = SpectralCorrective(
            SpectralCorrectiveConfig(channels=3, height=8, width=8, buckets=3, num_timesteps=prior.schedule.num_steps)
        )

        def g(c):
            return LMCSDS(c)(
                z.clone().requires_grad_(), prior, cond, 2.0, rng=torch.Generator().manual_seed(1)
            ).diagnostics.grad

        torch.testing.assert_close(g(spec), g(identity_corrective), atol=1e-5, rtol=1e-5)


class TestEdges:
    @pytest.mark.parametrize("u", [0.0, 0.02, 0.5, 0.98, 1.0])
    @pytest.mark.parametrize("image", ["constant", "zero", "one", "random"])
    def test_lmc_sds_gradient_is_finite(self, u, image):
        """The spectral b̂ in LMC-SDS at the ends of t and on flat images (σ = 0 in eq. 10): finite, no NaN."""
        from lasagna.losses.core import TimestepOptions
        from tests.losses.conftest import ConvPrior

        prior = ConvPrior(shape=(3, 8, 8))
        z = {
            "constant": torch.full((2, 3, 8, 8), 0.3),
            "zero": torch.full((2, 3, 8, 8), -1.0),
            "one": torch.ones(2, 3, 8, 8),
            "random": torch.rand(2, 3, 8, 8) * 2 - 1,
        }[image].requires_grad_()
        spec = random_gains(
            7,
            SpectralCorrectiveConfig(channels=3, height=8, width=8, buckets=4, num_timesteps=prior.schedule.num_steps),
        )
        loss = LMCSDS(spec, timesteps=TimestepOptions(t_min=u, t_max=u))
        out = loss(z, prior, Condition(["a", "b"]), 3.0, rng=torch.Generator().manual_seed(0))
        out.loss.backward()
        assert torch.isfinite(out.diagnostics.grad).all() and out.diagnostics.non_finite == 0
        assert torch.isfinite(z.grad).all()
