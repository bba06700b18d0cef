"""Amortised training on toy world batches: the score falls, a killed run resumes to the same weights,
the supervised ceiling learns the true layer, and a 2-process torchrun equals the 1-process run."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from lasagna.distill import Weights
from lasagna.errors import LasagnaError
from lasagna.generators import LayerGenerator, LayerGeneratorConfig
from lasagna.losses.corrective import Corrective, CorrectiveConfig
from lasagna.priors import GaussianPrior
from lasagna.priors.unet import UNetConfig, UNetPrior
from lasagna.training import AmortisedConfig, read_log, task_batch, train_layer_generator
from lasagna.training.generator import chunking
from lasagna.world import VOCABULARY
from tests.distill.conftest import SHADING
from tests.support.bounded import HANG_SECONDS

ROOT = Path(__file__).resolve().parents[2]
GEN = LayerGeneratorConfig(layer=SHADING, vocabulary=tuple(VOCABULARY), channels=(8, 16), blocks=1)


def toy(**kw) -> AmortisedConfig:
    base = dict(
        generator=GEN,
        loss="sds",
        resolution=8,
        batch_size=8,
        steps=30,
        lr=3e-3,
        weights=Weights(),
        checkpoint_every=10,
        log_every=1,
        progress=False,
        eval_count=8,
        seed=1,
    )
    base.update(kw)
    return AmortisedConfig(**base)


def gray_prior(cls: type[GaussianPrior] = GaussianPrior) -> GaussianPrior:
    """Every label: images near a uniform 0.35 gray, so the generator must learn y = 0.35 / albedo."""
    mu = torch.full((3 * 8 * 8,), 0.35 * 2 - 1, dtype=torch.float64)
    labels = tuple(VOCABULARY)
    return cls((3, 8, 8), {lab: mu for lab in labels}, {lab: 1e-3 for lab in labels}, unconditional=(mu, 1e-3))


class TestTaskBatch:
    def test_relight_is_albedo_label_shading(self):
        g = torch.Generator().manual_seed(0)
        d = task_batch("relight", VOCABULARY, 3, g, resolution=8)
        from lasagna.world import generate

        assert (
            d.base.shape == (3, 3, 8, 8)
            and d.target.shape == (3, 1, 8, 8)
            and all(lab in VOCABULARY for lab in d.labels)
        )
        start = int(torch.randint(0, 2**30, (1,), generator=torch.Generator().manual_seed(0)))
        ref = generate("train", 3, 0, 8, start=start, labels=d.labels)
        assert torch.equal(d.base, ref.albedo) and torch.equal(d.target, ref.shading)

    def test_colorize_and_light(self):
        g = torch.Generator().manual_seed(0)
        col = task_batch("colorize", ("natural",), 2, g, resolution=8)
        assert (
            col.target.shape == (2, 4, 8, 8)
            and torch.equal(col.base[:, 0], col.base[:, 1])
            and col.labels == ["natural"] * 2
        )
        light = task_batch("light", ("warm", "cool"), 2, g, resolution=8)
        assert light.target.min() >= 0 and torch.all(light.base + light.target <= 1.0 + 1e-6)

    def test_light_glow_takes_the_drawn_labels_colour(self):
        from lasagna.world import additive_light, generate

        g = torch.Generator().manual_seed(1)
        d = task_batch("light", ("warm", "cool", "white"), 6, g, resolution=8)
        start = int(torch.randint(0, 2**30, (1,), generator=torch.Generator().manual_seed(1)))
        ref = additive_light(generate("train", 6, 0, 8, start=start), d.labels)
        assert torch.equal(d.target, ref.glow) and torch.equal(d.base, ref.base)
        # warm glows are redder than blue, cool ones bluer than red (on the lit pixels)
        for b, lab in enumerate(d.labels):
            r, bl = d.target[b, 0].sum(), d.target[b, 2].sum()
            if lab == "warm":
                assert r > bl
            if lab == "cool":
                assert bl > r

    def test_light_refuses_labels_that_are_not_glow_colours(self):
        with pytest.raises(LasagnaError, match="not glow colours"):
            task_batch("light", ("left",), 1, torch.Generator().manual_seed(0), resolution=8)

    def test_relight_refuses_unknown_directions(self):
        with pytest.raises(LasagnaError, match="not light directions"):
            task_batch("relight", ("sideways",), 1, torch.Generator().manual_seed(0), resolution=8)


class TestTrain:
    def test_score_falls_and_generator_is_saved(self, tmp_path):
        result = train_layer_generator(toy(steps=40), tmp_path, prior=gray_prior())
        log = read_log(tmp_path)
        first = sum(r["score"] for r in log[:8]) / 8
        last = sum(r["score"] for r in log[-8:]) / 8
        assert last < 0.5 * first
        back = LayerGenerator.from_pretrained(tmp_path / "generator")
        base = torch.rand(1, 3, 8, 8)
        assert torch.equal(back(base, "left"), result.generator(base, "left"))
        metrics = json.loads((tmp_path / "metrics.json").read_text())
        assert metrics["step"] == 40 and metrics["supervised"] is False and "layer_psnr" in metrics
        saved = AmortisedConfig.model_validate_json((tmp_path / "train_config.json").read_text())
        assert saved == toy(steps=40)

    def test_resume_after_kill_equals_uninterrupted(self, tmp_path):
        class Killer(GaussianPrior):
            calls = 0

            def predict_many(self, *args, **kwargs):
                Killer.calls += 1
                if Killer.calls == 16:  # mid-run, between the checkpoints at 10 and 20
                    raise KeyboardInterrupt("killed")
                return super().predict_many(*args, **kwargs)

        g, killer = gray_prior(), gray_prior(Killer)
        cfg = toy(steps=24, weights=Weights.lmc_network(12), ema_decay=0.9)
        full = train_layer_generator(cfg, tmp_path / "full", prior=g)
        with pytest.raises(KeyboardInterrupt):
            train_layer_generator(cfg, tmp_path / "killed", prior=killer)
        resumed = train_layer_generator(cfg, tmp_path / "killed", prior=g)
        assert resumed.step == 24
        for (k, a), (_, b) in zip(full.generator.state_dict().items(), resumed.generator.state_dict().items()):
            assert torch.equal(a, b), k
        assert [r["loss"] for r in read_log(tmp_path / "full")] == [r["loss"] for r in read_log(tmp_path / "killed")]

    def test_supervised_learns_the_true_layer(self, tmp_path):
        result = train_layer_generator(toy(supervised=True, steps=60, eval_count=16), tmp_path)
        m = result.metrics
        assert m["supervised"] is True and m["layer_mse"] < 0.3 * m["identity_mse"]
        log = read_log(tmp_path)
        assert "mse" in log[0] and log[-1]["mse"] < 0.3 * log[0]["mse"]

    def test_needs_a_prior_unless_supervised(self, tmp_path):
        with pytest.raises(LasagnaError, match="no prior"):
            train_layer_generator(toy(), tmp_path)

    def test_chunking(self):
        assert chunking(toy(batch_size=8), 2) == (4, 2)
        assert chunking(toy(batch_size=8, micro_batch=2), 2) == (2, 4)
        with pytest.raises(LasagnaError, match="do not split over 3"):
            chunking(toy(batch_size=8, micro_batch=4), 3)
        with pytest.raises(ValueError, match="multiple of micro_batch"):
            toy(batch_size=8, micro_batch=3)


def test_two_processes_equal_one(tmp_path):
    """torchrun --nproc_per_node=2 (gloo, DDP) against one process, same global batch, micro batch and seed."""
    torch.manual_seed(0)
    prior = UNetPrior(UNetConfig(cond_channels=3, resolution=8, channels=(8, 16), vocabulary=tuple(VOCABULARY)))
    with torch.no_grad():  # an untrained prior predicts 0 (zero-initialised head): give it an opinion
        prior.net.out.weight.normal_(0, 0.05)
    prior.save_pretrained(tmp_path / "prior")
    Corrective(CorrectiveConfig(channels=3, resolution=8, filters=(8, 16), num_timesteps=1000)).save_pretrained(
        tmp_path / "bhat"
    )
    cfg = toy(
        loss="lmc-sds",
        prior=str(tmp_path / "prior"),
        corrective=str(tmp_path / "bhat"),
        steps=4,
        batch_size=4,
        micro_batch=2,
        checkpoint_every=2,
        eval_count=4,
        weights=Weights.lmc_network(4),
    )
    (tmp_path / "config.json").write_text(cfg.model_dump_json())

    one = train_layer_generator(cfg, tmp_path / "one")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--nproc_per_node=2",
        "--standalone",
        "-m",
        "lasagna.cli.torchrun",
        "--config",
        str(tmp_path / "config.json"),
        "--out",
        str(tmp_path / "two"),
    ]
    done = subprocess.run(cmd, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=HANG_SECONDS)
    assert done.returncode == 0, done.stderr[-3000:]
    assert json.loads(done.stdout.strip().splitlines()[-1])["processes"] == 2
    two = LayerGenerator.from_pretrained(tmp_path / "two" / "generator")
    for (k, a), (_, b) in zip(one.generator.state_dict().items(), two.state_dict().items()):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-6), k  # measured: max |difference| 7.5e-9
    assert float(one.generator.head.weight.detach().abs().max()) > 1e-3  # the runs did train (the head starts at 0)
    log1, log2 = read_log(tmp_path / "one"), read_log(tmp_path / "two")
    assert len(log1) == len(log2) == 4
    assert all(abs(a["loss"] - b["loss"]) <= 1e-5 * max(1.0, abs(a["loss"])) for a, b in zip(log1, log2))


def test_the_example_config_validates_and_every_field_is_documented():
    """``examples/gen.json``, the README's torchrun config: an ``AmortisedConfig`` naming catalogue entries that
    exist (so the command runs as written, in a checkout or from a wheel), the shading preset's layer; and
    docs/ARCHITECTURE.md's table names every field of the model and of the models nested in it."""
    import re

    from lasagna import catalogue
    from lasagna.distill.schedules import Ramp
    from lasagna.generators.layer import LayerSpec
    from lasagna.training.loop import LoopConfig

    config = AmortisedConfig.model_validate_json((ROOT / "examples" / "gen.json").read_text(encoding="utf-8"))
    assert catalogue.find(config.prior, "prior").is_dir() and catalogue.find(config.corrective, "corrective").is_dir()
    assert config.generator == LayerGeneratorConfig.for_preset(catalogue.load_preset("shading"))
    assert "--config examples/gen.json" in (ROOT / "README.md").read_text(encoding="utf-8")
    docs = (ROOT / "docs" / "ARCHITECTURE.md").read_text(encoding="utf-8")
    section = docs[docs.index("### A generator's config (`gen.json`)") :]
    named = set(re.findall(r"`([a-z_]+)`", section))
    fields = {
        f
        for model in (AmortisedConfig, LoopConfig, LayerGeneratorConfig, LayerSpec, Weights, Ramp)
        for f in model.model_fields
    }
    assert sorted(fields - named) == []
