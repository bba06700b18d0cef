"""The manifold corrective b̂_ψ, its loss L_k (LMC-SDS eq. 10) and its resumable training.

L_k is checked against a numpy float64 transcription of eq. 10; training on a closed-form "blur
prior" (x̂₀ = √ᾱ · box-blur(z_t), a t-dependent frequency bias like the one the paper describes); the
kill-and-resume test runs the real command in a subprocess and SIGKILLs it.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from lasagna.cli import main as cli_main
from lasagna.errors import ConditionError, LasagnaError
from lasagna.io import checkpoint as io
from lasagna.losses.corrective import (
    Corrective,
    CorrectiveConfig,
    TrivialCorrective,
    corrective_loss,
    lk_loss,
    normalize_by_std,
    rescale_to_target_std,
)
from lasagna.priors.base import NoiseSchedule, Prior
from lasagna.priors.unet import UNetConfig, UNetPrior
from lasagna.training import corrective as ct
from tests.support.bounded import HANG_SECONDS

ROOT = Path(__file__).resolve().parents[2]


def numpy_lk(b: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Eq. 10 per sample in float64: ‖ẑ − (σ(ẑ)/σ(b̂)(b̂ − μ(b̂)) + μ(b̂))‖² / n (population σ)."""
    out = []
    for bi, zi in zip(b.astype(np.float64), z.astype(np.float64)):
        bt = zi.std() / bi.std() * (bi - bi.mean()) + bi.mean()
        out.append(np.mean((zi - bt) ** 2))
    return np.array(out)


# -- a data source and a closed-form prior for training ------------------------------------------
def toy_source(batch: int, generator: torch.Generator):
    """Images in [0, 1] with flat colour, vertical stripes and noise (high frequencies to blur away);
    labels in {0, 1}; no conditioning image. Used in-process and by the subprocess (--source)."""
    base = torch.rand(batch, 3, 1, 1, generator=generator)
    stripes = (torch.arange(8).float() % 2).view(1, 1, 1, 8) * torch.rand(batch, 1, 1, 1, generator=generator)
    img = (0.3 * base + 0.5 * stripes + 0.2 * torch.rand(batch, 3, 8, 8, generator=generator)).clamp(0, 1)
    return img, torch.randint(0, 2, (batch,), generator=generator), None


class BlurPrior(Prior):
    """x̂₀ = √ᾱ_t · box3(z_t): a denoiser with a frequency bias, in closed form."""

    def __init__(self):
        super().__init__()
        self.schedule = NoiseSchedule(1000)
        self.vocabulary = ("a", "b")
        self.sample_shape = (3, 8, 8)

    def _eps(self, z_t, t, label_idx, image):
        ab = self.schedule.alpha_bar(t, z_t.dtype)[:, None, None, None]
        x0 = F.avg_pool2d(z_t, 3, 1, 1, count_include_pad=False) * ab.sqrt()
        return self.schedule.eps_from_x0(z_t, x0, t)


def toy_train_config(**kw) -> ct.CorrectiveTrainConfig:
    base = dict(
        corrective=CorrectiveConfig(channels=3, resolution=8, filters=(8, 16)),
        steps=150,
        batch_size=16,
        lr=3e-3,
        checkpoint_every=50,
        log_every=10,
        eval_batches=2,
        progress=False,
    )
    base.update(kw)
    return ct.CorrectiveTrainConfig(**base)


# -- L_k -------------------------------------------------------------------------------------------
class TestLk:
    def test_reference_values(self):
        g = torch.Generator().manual_seed(0)
        b, z = torch.randn(4, 3, 5, 5, generator=g) * 0.7 + 0.2, torch.randn(4, 3, 5, 5, generator=g)
        np.testing.assert_allclose(lk_loss(b, z, reduction="none").numpy(), numpy_lk(b.numpy(), z.numpy()), rtol=1e-5)
        assert lk_loss(b, z).item() == pytest.approx(numpy_lk(b.numpy(), z.numpy()).mean(), rel=1e-5)
        assert corrective_loss is lk_loss

    def test_rescale_keeps_mean_takes_target_std(self):
        g = torch.Generator().manual_seed(1)
        b, z = torch.randn(2, 3, 4, 4, generator=g) + 3.0, torch.randn(2, 3, 4, 4, generator=g) * 0.1
        bt = rescale_to_target_std(b, z).double()
        torch.testing.assert_close(bt.mean(dim=(1, 2, 3)), b.double().mean(dim=(1, 2, 3)), atol=1e-5, rtol=0)
        torch.testing.assert_close(
            bt.std(dim=(1, 2, 3), unbiased=False), z.double().std(dim=(1, 2, 3), unbiased=False), atol=1e-6, rtol=1e-5
        )
        n = normalize_by_std(z).double()
        torch.testing.assert_close(
            n.std(dim=(1, 2, 3), unbiased=False), torch.ones(2, dtype=torch.float64), atol=1e-5, rtol=0
        )

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.bfloat16, torch.float16])
    def test_constant_images_are_finite(self, dtype):
        """σ(b̂) = 0 (and σ(ẑ) = 0): finite loss, and a finite gradient where the dtype's range allows
        σ(ẑ)/STD_EPS (not float16, whose max is 65504)."""
        b = torch.full((2, 3, 4, 4), 0.5, dtype=dtype, requires_grad=True)
        z = torch.randn(2, 3, 4, 4, generator=torch.Generator().manual_seed(0)).to(dtype)
        loss = lk_loss(b, z)
        loss.backward()
        assert torch.isfinite(loss) and loss.dtype == (torch.float64 if dtype == torch.float64 else torch.float32)
        if dtype != torch.float16:
            assert torch.isfinite(b.grad).all()
        # b̂ constant ⇒ b̃ = μ(b̂): the loss is the mean of (ẑ − 0.5)², independently computed.
        assert loss.item() == pytest.approx(((z.double() - 0.5) ** 2).mean().item(), rel=1e-5)
        assert lk_loss(torch.zeros(1, 3, 4, 4, dtype=dtype), torch.zeros(1, 3, 4, 4, dtype=dtype)).item() == 0.0

    def test_gradcheck_float64(self):
        b = torch.randn(2, 2, 3, 3, dtype=torch.float64, requires_grad=True)
        z = torch.randn(2, 2, 3, 3, dtype=torch.float64)
        assert torch.autograd.gradcheck(lambda x: lk_loss(x, z), (b,))

    def test_nan_is_not_hidden(self):
        b, z = torch.randn(2, 3, 4, 4), torch.randn(2, 3, 4, 4)
        b[0, 0, 0, 0] = float("nan")
        per = lk_loss(b, z, reduction="none")
        assert torch.isnan(per[0]) and torch.isfinite(per[1])

    def test_exceptions(self):
        with pytest.raises(ValueError, match="equal shapes"):
            lk_loss(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 5))
        with pytest.raises(ValueError, match="reduction"):
            lk_loss(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 4), reduction="sum")

    @settings(max_examples=25, deadline=None)
    @given(seed=st.integers(0, 2**16), a=st.floats(0.05, 20.0), shift=st.floats(-3.0, 3.0))
    def test_invariances(self, seed, a, shift):
        """L_k ignores b̂'s contrast about its own mean, and any contrast of the target itself scores 0."""
        g = torch.Generator().manual_seed(seed)
        b, z = (
            torch.randn(2, 3, 4, 4, generator=g, dtype=torch.float64),
            torch.randn(2, 3, 4, 4, generator=g, dtype=torch.float64),
        )
        mu = b.mean(dim=(1, 2, 3), keepdim=True)
        torch.testing.assert_close(lk_loss(mu + a * (b - mu), z), lk_loss(b, z), atol=1e-10, rtol=1e-9)
        zm = z.mean(dim=(1, 2, 3), keepdim=True)
        assert lk_loss(zm + a * (z - zm), z).item() < 1e-12
        assert lk_loss(b + shift, z).item() >= 0.0


# -- the network ------------------------------------------------------------------------------------
class TestCorrective:
    def test_starts_as_the_trivial_corrective(self):
        model = Corrective(CorrectiveConfig(channels=3, resolution=8, filters=(8, 16, 32)))
        z = torch.randn(2, 3, 8, 8)
        assert torch.equal(model(z, torch.tensor([5, 900])), TrivialCorrective()(z, torch.tensor([5, 900])))

    @pytest.mark.parametrize("filters, size", [((8,), 5), ((8, 16), 8), ((8, 16, 32), 16), ((8, 16, 32, 64), 32)])
    def test_shapes_and_tanh_bound(self, filters, size):
        model = Corrective(
            CorrectiveConfig(channels=4, resolution=size if len(filters) > 1 else 8, filters=filters, output_scale=0.5)
        )
        with torch.no_grad():
            for p in model.parameters():
                p.normal_(0, 1.0)
        z = torch.randn(3, 4, size, size)
        out = model(z, torch.tensor([0, 500, 999]))
        assert out.shape == z.shape and torch.isfinite(out).all()
        assert (out - z).abs().max() <= 0.5 + 1e-6  # b̂ − z = scale · tanh(·)

    def test_t_and_condition_are_inputs(self):
        cfg = CorrectiveConfig(
            channels=3, resolution=8, filters=(8, 16), sees_condition=True, cond_channels=3, vocabulary=("a", "b")
        )
        model = Corrective(cfg)
        torch.nn.init.normal_(model.head.weight, std=0.5)
        z, img = torch.randn(1, 3, 8, 8), torch.rand(1, 3, 8, 8)

        def run(t, lab, im):
            return model(z, torch.tensor([t]), cond_image=im, label_idx=torch.tensor([lab]))

        base = run(100, 0, img)
        assert not torch.allclose(base, run(800, 0, img))
        assert not torch.allclose(base, run(100, 1, img))
        assert not torch.allclose(base, run(100, 2, img))  # the null label has its own embedding
        assert not torch.allclose(base, run(100, 0, 1 - img))
        # A latent-resolution z with a pixel-resolution image: the image is area-resized.
        assert run(1, 0, torch.rand(1, 3, 32, 32)).shape == z.shape
        # Without sees_condition the condition is not an input.
        plain = Corrective(CorrectiveConfig(channels=3, resolution=8, filters=(8, 16)))
        torch.nn.init.normal_(plain.head.weight, std=0.5)
        torch.testing.assert_close(
            plain(z, torch.tensor([9])), plain(z, torch.tensor([9]), cond_image=img, label_idx=torch.tensor([1]))
        )

    def test_exceptions(self):
        model = Corrective(
            CorrectiveConfig(channels=3, resolution=8, filters=(8, 16), sees_condition=True, cond_channels=3)
        )
        lab = torch.tensor([0])
        with pytest.raises(ConditionError, match="needs an image"):
            model(torch.randn(1, 3, 8, 8), torch.tensor([1]), label_idx=lab)
        with pytest.raises(ConditionError, match="needs label_idx"):
            model(torch.randn(1, 3, 8, 8), torch.tensor([1]), cond_image=torch.rand(1, 3, 8, 8))
        with pytest.raises(ConditionError, match=r"expected \(B, 3, H, W\)"):
            model(torch.randn(1, 4, 8, 8), torch.tensor([1]), torch.rand(1, 3, 8, 8), lab)
        with pytest.raises(ConditionError, match="divisible by 2"):
            model(torch.randn(1, 3, 7, 7), torch.tensor([1]), torch.rand(1, 3, 7, 7), lab)
        with pytest.raises(ValidationError, match="divisible"):
            CorrectiveConfig(resolution=30, filters=(8, 16, 32))
        with pytest.raises(ValidationError, match="Extra inputs"):
            CorrectiveConfig(levels=3)

    def test_save_load_round_trip(self, tmp_path):
        cfg = CorrectiveConfig(
            channels=3, resolution=8, filters=(8, 16), sees_condition=True, cond_channels=3, vocabulary=("a", "b")
        )
        model = Corrective(cfg)
        torch.nn.init.normal_(model.head.weight, std=0.3)
        model.save_pretrained(tmp_path / "c")
        loaded = Corrective.from_pretrained(tmp_path / "c")
        assert (
            loaded.config == cfg
            and json.loads((tmp_path / "c" / "config.json").read_text())["format"] == "lasagna.corrective"
        )
        z, img = torch.randn(2, 3, 8, 8), torch.rand(2, 3, 8, 8)
        args = (z, torch.tensor([3, 700]), img, torch.tensor([0, 1]))
        torch.testing.assert_close(loaded(*args), model(*args), atol=0, rtol=0)
        with pytest.raises(LasagnaError, match="expected 'lasagna.unet_prior'"):
            UNetPrior.from_pretrained(tmp_path / "c")


# -- training ---------------------------------------------------------------------------------------
class TestTraining:
    def test_short_run_lowers_lk(self, tmp_path):
        result = ct.train_corrective(BlurPrior(), toy_source, toy_train_config(), tmp_path / "run")
        assert result.step == 150 and result.stopped == "done"
        assert result.ratio < 0.8, (result.lk_trained, result.lk_trivial)  # learned the blur
        metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
        assert metrics["ratio"] == pytest.approx(result.ratio)
        log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
        assert [r["step"] for r in log] == list(range(10, 151, 10))
        assert np.mean([r["lk"] for r in log[-3:]]) < np.mean([r["lk"] for r in log[:2]])
        assert Corrective.from_pretrained(tmp_path / "run" / "corrective").config == toy_train_config().corrective

    def test_triplets_use_the_unconditional_x0(self):
        """ẑ_t is the prior's x̂₀ of the null-label branch; b̂ is told the sample's own label."""
        prior, calls = BlurPrior(), []
        real = prior._eps
        prior._eps = lambda z_t, t, label_idx, image: (
            calls.append(label_idx.tolist()),
            real(z_t, t, label_idx, image),
        )[1]
        tr = ct.make_triplets(
            prior, toy_source, 4, torch.Generator().manual_seed(0), "uncond", 0.02, 0.98, torch.device("cpu")
        )
        assert calls == [[2] * 4]  # the denoiser ran once, on the null label
        assert tr.t.min() >= 20 and tr.t.max() <= 979
        # Re-derive ẑ_t from the same draws, independently of make_triplets.
        g = torch.Generator().manual_seed(0)
        images, labels, _ = toy_source(4, g)
        assert tr.label.tolist() == labels.tolist()
        u = 0.02 + 0.96 * torch.rand(4, generator=g)
        t = (u * 999).round().long()
        eps = torch.randn(4, 3, 8, 8, generator=g)
        ab = torch.from_numpy(np.cumprod(1 - np.linspace(1e-4, 0.02, 1000)))[t].float()[:, None, None, None]
        z = images * 2 - 1
        z_t = ab.sqrt() * z + (1 - ab).sqrt() * eps
        expected = ab.sqrt() * F.avg_pool2d(z_t, 3, 1, 1, count_include_pad=False)
        torch.testing.assert_close(tr.t, t)
        torch.testing.assert_close(tr.z_hat, expected, atol=2e-4, rtol=0)

    def test_time_budget_then_resume(self, tmp_path):
        first = ct.train_corrective(
            BlurPrior(), toy_source, toy_train_config(steps=40, max_minutes=1e-9), tmp_path / "run"
        )
        assert first.stopped == "time" and first.step < 40
        _, meta = io.load_tensors(tmp_path / "run" / "checkpoint.safetensors")
        assert int(meta["step"]) == first.step
        second = ct.train_corrective(BlurPrior(), toy_source, toy_train_config(steps=40), tmp_path / "run")
        assert second.stopped == "done" and second.step == 40

    def test_resume_reproduces_an_uninterrupted_run_with_ema(self, tmp_path):
        kw = dict(ema_decay=0.9, checkpoint_every=7)
        ct.train_corrective(BlurPrior(), toy_source, toy_train_config(steps=30, **kw), tmp_path / "ref")
        ct.train_corrective(BlurPrior(), toy_source, toy_train_config(steps=17, **kw), tmp_path / "split")
        ct.train_corrective(BlurPrior(), toy_source, toy_train_config(steps=30, **kw), tmp_path / "split")
        a, _ = io.load_tensors(tmp_path / "ref" / "checkpoint.safetensors")
        b, _ = io.load_tensors(tmp_path / "split" / "checkpoint.safetensors")
        assert set(a) == set(b) and any(k.startswith("ema.") for k in a)
        for k in a:
            torch.testing.assert_close(a[k], b[k], atol=1e-6, rtol=1e-5, msg=k)

    def test_refuses_a_different_run_in_the_same_folder(self, tmp_path):
        ct.train_corrective(BlurPrior(), toy_source, toy_train_config(steps=5), tmp_path / "run")
        with pytest.raises(LasagnaError, match="different batch_size, lr"):
            ct.train_corrective(
                BlurPrior(), toy_source, toy_train_config(steps=5, lr=1e-2, batch_size=8), tmp_path / "run"
            )

    def test_failed_checkpoint_write_keeps_the_previous_one(self, tmp_path, monkeypatch):
        calls = {"n": 0}
        real = io._st_save

        def flaky(tensors, metadata=None):
            calls["n"] += 1
            if calls["n"] == 2:
                raise OSError("disk full")
            return real(tensors, metadata=metadata)

        monkeypatch.setattr(io, "_st_save", flaky)
        with pytest.raises(OSError, match="disk full"):
            ct.train_corrective(
                BlurPrior(), toy_source, toy_train_config(steps=30, checkpoint_every=10), tmp_path / "run"
            )
        _, meta = io.load_tensors(tmp_path / "run" / "checkpoint.safetensors")
        assert meta["step"] == "10"
        assert sorted(p.name for p in (tmp_path / "run").iterdir()) == [
            "checkpoint.safetensors",
            "log.jsonl",
            "train_config.json",
        ]

    def test_mismatched_prior(self, tmp_path):
        cfg = toy_train_config(corrective=CorrectiveConfig(channels=4, resolution=8, filters=(8, 16)))
        with pytest.raises(LasagnaError, match="expected the prior's 3"):
            ct.train_corrective(BlurPrior(), toy_source, cfg, tmp_path / "run")


class TestKillAndResume:
    """The real command in a subprocess: SIGKILL after its first checkpoint, start again, finish."""

    def _cmd(self, prior_dir: Path, out: Path, steps: int) -> list[str]:
        return [
            sys.executable,
            "-m",
            "lasagna.cli",
            "train-corrective",
            "--prior",
            str(prior_dir),
            "--source",
            "tests.losses.test_corrective:toy_source",
            "--out",
            str(out),
            "--steps",
            str(steps),
            "--batch-size",
            "4",
            "--filters",
            "4,8",
            "--lr",
            "1e-3",
            "--checkpoint-every",
            "20",
            "--log-every",
            "5",
            "--eval-batches",
            "1",
            "--no-progress",
        ]

    def test_sigkill_then_resume(self, tmp_path):
        prior_dir = tmp_path / "prior"
        UNetPrior(UNetConfig(channels=(4, 8), resolution=8, norm_groups=4, vocabulary=("a", "b"))).save_pretrained(
            prior_dir
        )
        env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
        steps, out = 80, tmp_path / "run"
        proc = subprocess.Popen(
            self._cmd(prior_dir, out, steps), cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE
        )
        ckpt = out / "checkpoint.safetensors"
        deadline = time.monotonic() + 60
        while not ckpt.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.005)
        proc.send_signal(signal.SIGKILL)
        _, err = proc.communicate()
        assert proc.returncode == -signal.SIGKILL, err.decode()[-2000:]
        _, meta = io.load_tensors(ckpt)  # complete and readable at the moment of the kill
        killed_at = int(meta["step"])
        assert 0 < killed_at < steps and killed_at % 20 == 0
        assert not (out / "metrics.json").exists()

        done = subprocess.run(
            self._cmd(prior_dir, out, steps), cwd=ROOT, env=env, capture_output=True, timeout=HANG_SECONDS
        )
        assert done.returncode == 0, done.stderr.decode()[-2000:]
        summary = json.loads(done.stdout.decode().strip().splitlines()[-1])
        assert summary["step"] == steps and summary["stopped"] == "done"
        _, meta = io.load_tensors(ckpt)
        assert int(meta["step"]) == steps
        log_steps = [json.loads(line)["step"] for line in (out / "log.jsonl").read_text().splitlines()]
        assert log_steps == list(range(5, steps + 1, 5))  # no gap and no duplicate across the kill
        assert not list(out.glob(".checkpoint.safetensors.*"))

        # The resumed run equals an uninterrupted one (one generator, checkpointed with the weights).
        threads = torch.get_num_threads()
        torch.set_num_threads(1)  # as the subprocesses ran (OMP_NUM_THREADS=1)
        try:
            assert (
                cli_main(self._cmd(prior_dir, tmp_path / "ref", steps)[3:]) == 0
            )  # in-process: same code, no start-up cost
        finally:
            torch.set_num_threads(threads)
        a, _ = io.load_tensors(out / "corrective" / "model.safetensors")
        b, _ = io.load_tensors(tmp_path / "ref" / "corrective" / "model.safetensors")
        for k in a:
            torch.testing.assert_close(a[k], b[k], atol=1e-6, rtol=1e-5, msg=k)

    def test_main_reports_errors_in_one_line(self, tmp_path, capsys):
        code = cli_main(
            [
                "train-corrective",
                "--prior",
                str(tmp_path / "none"),
                "--source",
                "x:y",
                "--out",
                str(tmp_path / "o"),
                "--no-progress",
            ]
        )
        err = capsys.readouterr().err.strip()
        assert code == 2 and err.count("\n") == 0 and "does not exist" in err and str(tmp_path / "none") in err
        UNetPrior(UNetConfig(channels=(4, 8), resolution=8, norm_groups=4)).save_pretrained(tmp_path / "p")
        code = cli_main(
            [
                "train-corrective",
                "--prior",
                str(tmp_path / "p"),
                "--source",
                "tests.losses.test_corrective:toy_source",
                "--out",
                str(tmp_path / "o"),
                "--steps",
                "0",
                "--no-progress",
            ]
        )
        err = capsys.readouterr().err.strip()
        assert code == 2 and err.count("\n") == 0 and "train-corrective.steps" in err
