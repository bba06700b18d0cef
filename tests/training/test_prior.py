"""The prior trainer on a toy config: the loss falls, a resumed run equals an uninterrupted one,
and the evaluation helpers measure what they claim (against closed forms)."""

from __future__ import annotations

import json
import math

import pytest
import torch

from lasagna.errors import LasagnaError
from lasagna.priors.evaluate import denoising_error, psnr, sample_quality
from lasagna.priors.unet import UNetPrior
from lasagna.training.prior import (
    PriorTrainConfig,
    prior_batch,
    run_unet_config,
    train_prior,
    unet_config_for,
    world_source,
)
from lasagna.world import VOCABULARY, generate


def toy(task="relight", **kw) -> PriorTrainConfig:
    base = dict(
        task=task,
        unet=unet_config_for(task, resolution=8, channels=(8, 16)),
        batch_size=8,
        steps=40,
        lr=3e-3,
        warmup_steps=5,
        ema_decay=0.9,
        checkpoint_every=10,
        log_every=1,
        progress=False,
        seed=3,
    )
    base.update(kw)
    return PriorTrainConfig(**base)


class TestTaskData:
    def test_relight_batch_is_image_label_albedo(self):
        scene = generate("train", 4, seed=1, resolution=8)
        x0, lab, cond = prior_batch("relight", scene)
        assert torch.equal(x0, scene.albedo * scene.shading)
        assert torch.equal(cond, scene.albedo)
        assert [VOCABULARY[i] for i in lab.tolist()] == scene.label

    def test_relit_batch_is_the_scene_under_b_conditioned_on_it_under_a(self):
        from lasagna.world.tasks import relight_sources, with_light

        scene = generate("train", 4, seed=1, resolution=8, dtype=torch.float64)
        x0, lab, cond = prior_batch("relit", scene)
        assert torch.equal(x0, scene.image)  # B: the scene's own label
        source = with_light(scene, relight_sources(scene.params))
        assert torch.equal(cond, source.image) and not torch.equal(cond, x0)
        assert [VOCABULARY[i] for i in lab.tolist()] == scene.label
        assert unet_config_for("relit").vocabulary == tuple(VOCABULARY)

    def test_relit_task_layer_maps_the_base_onto_the_target(self):
        from lasagna.training.tasks import task_batch

        b = task_batch("relit", VOCABULARY, 6, torch.Generator().manual_seed(3), resolution=8)
        assert b.target.shape == (6, 1, 8, 8) and float(b.target.min()) >= 0.25 - 1e-6 and float(b.target.max()) <= 4
        assert b.base.shape == (6, 3, 8, 8) and set(b.labels) <= set(VOCABULARY)

    def test_relit_ratio_times_the_lit_input_is_the_relit_scene(self):
        from lasagna.training.tasks import relit

        scene = generate("train", 5, seed=2, resolution=8, dtype=torch.float64)
        rel = relit(scene)
        assert torch.allclose(rel.base * rel.layer, rel.target, atol=1e-12)

    def test_colorize_condition_is_rec709_luma(self):
        scene = generate("train", 2, seed=1, resolution=8)
        x0, lab, cond = prior_batch("colorize", scene)
        r, g, b = scene.image[:, 0], scene.image[:, 1], scene.image[:, 2]
        assert torch.allclose(cond[:, 0], 0.2126 * r + 0.7152 * g + 0.0722 * b, atol=1e-6)
        assert cond.shape[1] == 1 and lab.tolist() == [0, 0]

    def test_light_batch_is_lit_image_glow_label_unlit_image(self):
        from lasagna.world import GLOW_VOCABULARY
        from lasagna.world.tasks import glow

        scene = generate("train", 6, seed=1, resolution=8, dtype=torch.float64)
        x0, lab, cond = prior_batch("light", scene)
        assert torch.equal(cond, scene.image)
        assert torch.equal(x0, scene.image + torch.minimum(glow(scene), 1 - scene.image))
        assert lab.tolist() == scene.params.glow_label.tolist()
        assert unet_config_for("light").vocabulary == tuple(GLOW_VOCABULARY) == ("warm", "cool", "white")
        assert unet_config_for("light").cond_channels == 3

    def test_source_depends_only_on_the_generator(self):
        src = world_source("relight", 8)
        a = src(3, torch.Generator().manual_seed(5))
        b = src(3, torch.Generator().manual_seed(5))
        assert all(torch.equal(x, y) for x, y in zip(a, b))


class TestTrainPrior:
    def test_loss_falls_and_weights_are_saved(self, tmp_path):
        train_prior(toy(steps=60), tmp_path)
        log = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
        first = sum(r["loss"] for r in log[:5]) / 5
        last = sum(r["loss"] for r in log[-5:]) / 5
        assert last < 0.8 * first
        prior = UNetPrior.from_pretrained(tmp_path / "prior")
        assert prior.vocabulary == tuple(VOCABULARY)

    def test_resumed_run_equals_uninterrupted(self, tmp_path):
        full = train_prior(toy(steps=20), tmp_path / "full")
        train_prior(toy(steps=10), tmp_path / "split")  # stops at step 10 (a checkpoint) ...
        resumed = train_prior(toy(steps=20), tmp_path / "split")  # ... and continues to 20
        for (k, a), (_, b) in zip(full.state_dict().items(), resumed.state_dict().items()):
            assert torch.equal(a, b), k

    def test_other_config_refuses_to_resume(self, tmp_path):
        train_prior(toy(steps=2), tmp_path)
        with pytest.raises(Exception, match="different"):
            train_prior(toy(steps=2, batch_size=4), tmp_path)


class TestTrainingScenes:
    def test_a_source_draws_the_named_split_s_scenes(self):
        """The ``wide`` split's scenes are the world's own for that split (its generic shapes included), not
        ``train``'s: the source renders exactly what ``generate`` renders for (split, seed, start)."""
        from lasagna.training.tasks import SCENE_RANGE

        rng = torch.Generator().manual_seed(7)
        x0, _, cond = world_source("relight", 8, split="wide", seed=5)(3, rng)
        start = int(torch.randint(0, SCENE_RANGE, (1,), generator=torch.Generator().manual_seed(7)))
        scene = generate("wide", 3, 5, 8, start=start)
        assert torch.equal(cond, scene.albedo) and torch.equal(x0, scene.albedo * scene.shading)
        other = generate("train", 3, 5, 8, start=start)
        assert not torch.equal(cond, other.albedo)

    def test_rendering_on_the_device_or_the_cpu_trains_the_same_weights_on_a_cpu(self, tmp_path):
        """``render_on`` moves where the scenes are drawn, not which: on a CPU both settings are one run."""
        a = train_prior(toy(steps=3, render_on="device"), tmp_path / "a", device="cpu")
        b = train_prior(toy(steps=3, render_on="cpu"), tmp_path / "b", device="cpu")
        for (k, v), w in zip(a.state_dict().items(), b.state_dict().values()):
            assert torch.equal(v, w), k

    @pytest.mark.parametrize("split", ["select", "heldout", "far"])
    def test_held_out_splits_at_the_benchmarks_seed_are_refused(self, tmp_path, split):
        with pytest.raises(LasagnaError, match="world_seed: training on .* would train on the benchmarks' own"):
            train_prior(toy(split=split, world_seed=0), tmp_path / "x")
        assert not (tmp_path / "x").exists()

    def test_cli_split_and_world_seed_reach_the_run(self, tmp_path, capsys):
        from lasagna.cli import main

        assert main(["train-prior", "--task", "relight", "--resolution", "8", "--channels", "8,16", "--steps", "1",
                     "--batch-size", "2", "--split", "wide", "--world-seed", "5", "--out", str(tmp_path / "r"),
                     "--no-progress"]) == 0  # fmt: skip
        config = json.loads((tmp_path / "r" / "train_config.json").read_text())
        assert (config["split"], config["world_seed"], config["render_on"]) == ("wide", 5, "device")
        code = main(["train-prior", "--split", "far", "--out", str(tmp_path / "f"), "--no-progress"])
        err = capsys.readouterr().err.strip()
        assert code == 2 and err.count("\n") == 0 and "benchmarks' own scenes" in err
        code = main(["train-prior", "--split", "nowhere", "--world-seed", "3", "--out", str(tmp_path / "n")])
        err = capsys.readouterr().err.strip()
        assert code == 2 and "unknown split 'nowhere'" in err


class TestEvaluate:
    def test_psnr_closed_form(self):
        a = torch.zeros(2, 3, 4, 4)
        b = torch.full((2, 3, 4, 4), 0.1)
        assert torch.allclose(psnr(a, b), torch.full((2,), 20.0, dtype=torch.float64))

    def test_sample_quality_and_denoising_error_run_per_label(self):
        prior = UNetPrior(unet_config_for("relight", resolution=8, channels=(8, 16))).eval()
        scene = generate("heldout", 4, seed=0, resolution=8)
        q = sample_quality(prior, scene.image, scene.label, scene.albedo, omegas=(1.0,), steps=3)
        assert set(q[1.0]) == set(scene.label) | {"all"}
        err = denoising_error(prior, scene.image, scene.label, scene.albedo, t_values=(0.1, 0.9))
        assert all(v >= 0 and v == v for v in err.values())


class TestSchedulesAndStages:
    def test_cosine_lr_closed_form(self):
        import math

        cfg = toy(steps=101, lr=2e-3, warmup_steps=0, lr_schedule="cosine", lr_min_ratio=0.1)
        for step in (0, 25, 50, 100):
            frac = step / 100
            want = 2e-3 * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * frac)))
            assert cfg.lr_at(step) == pytest.approx(want, rel=1e-12)
        lrs = [cfg.lr_at(s) for s in range(101)]
        assert all(a >= b for a, b in zip(lrs, lrs[1:]))  # never rises after warm-up
        warm = toy(steps=101, lr=2e-3, warmup_steps=10, lr_schedule="cosine")
        assert warm.lr_at(0) == pytest.approx(2e-4 * (0.5 * (1 + math.cos(0.0))))
        assert toy(steps=50, lr=1e-3, warmup_steps=0).lr_at(49) == 1e-3  # the default "step" schedule: constant

    def test_init_from_starts_at_those_weights(self, tmp_path):
        first = train_prior(toy(steps=5), tmp_path / "one")
        # lr so small that one step cannot move the weights visibly: the second stage starts where the first ended.
        second = train_prior(
            toy(steps=1, lr=1e-12, warmup_steps=0, ema_decay=None, init_from=str(tmp_path / "one" / "prior")),
            tmp_path / "two",
        )
        for (k, a), (_, b) in zip(first.state_dict().items(), second.state_dict().items()):
            torch.testing.assert_close(a, b, atol=1e-8, rtol=0, msg=k)
        fresh = train_prior(toy(steps=1, lr=1e-12, warmup_steps=0, ema_decay=None), tmp_path / "three")
        assert any(not torch.allclose(a, b) for a, b in zip(first.state_dict().values(), fresh.state_dict().values()))

    def test_a_grown_prior_starts_computing_what_it_grew_from(self, tmp_path):
        first = train_prior(toy(steps=5), tmp_path / "one")
        start = str(tmp_path / "one" / "prior")
        unet = run_unet_config("relight", first.config, start, "keep", grow_res_blocks=3)
        assert unet.res_blocks == 3 and unet.model_copy(update={"res_blocks": 1}) == first.config
        grown = train_prior(
            toy(steps=1, lr=1e-12, warmup_steps=0, ema_decay=None, unet=unet, init_from=start), tmp_path / "two"
        )
        assert len(grown.net.down[0]["blocks"]) == 3 and len(grown.net.up[1]["blocks"]) == 3
        # The added blocks' first convolutions are random (they would change the output if the last were not
        # zero); the output is init_from's to the size of one step at lr 1e-12.
        assert grown.net.down[0]["blocks"][2].conv1.weight.abs().max() > 0.01
        g = torch.Generator().manual_seed(0)
        z, cond = torch.randn(4, 3, 8, 8, generator=g), torch.rand(4, 3, 8, 8, generator=g)
        t, label = torch.tensor([10, 300, 700, 990]), torch.tensor([0, 3, 7, 8])
        with torch.no_grad():
            want, got = first.eval().raw(z, t, label, cond), grown.eval().raw(z, t, label, cond)
        assert want.abs().max() > 0.01
        torch.testing.assert_close(got, want, atol=1e-6, rtol=0)
        fresh = UNetPrior(unet).eval()
        with torch.no_grad():
            assert (fresh.raw(z, t, label, cond) - want).abs().max() > 1e-3  # not a test that any prior passes

    def test_growth_is_refused_where_it_would_cut_or_has_nothing_to_grow(self, tmp_path, capsys):
        from lasagna.cli import main

        train_prior(toy(steps=1, unet=unet_config_for("relight", resolution=8, channels=(8, 16), res_blocks=2)),
                    tmp_path / "two")  # fmt: skip
        base = ["train-prior", "--steps", "1", "--batch-size", "2", "--resolution", "8", "--no-progress"]
        code = main([*base, "--init-from", str(tmp_path / "two" / "prior"), "--grow-res-blocks", "1",
                     "--out", str(tmp_path / "cut")])  # fmt: skip
        err = capsys.readouterr().err.strip()
        assert code == 2 and err.count("\n") == 0 and "fewer than the 2" in err and "--grow-res-blocks" in err
        code = main([*base, "--grow-res-blocks", "2", "--out", str(tmp_path / "none")])
        err = capsys.readouterr().err.strip()
        assert code == 2 and err.count("\n") == 0 and "give --init-from too" in err
        assert not (tmp_path / "cut").exists() and not (tmp_path / "none").exists()

    def test_init_from_another_architecture_is_refused(self, tmp_path):
        train_prior(toy(steps=1), tmp_path / "one")
        other = toy(
            steps=1,
            unet=unet_config_for("relight", resolution=8, channels=(8, 8)),
            init_from=str(tmp_path / "one" / "prior"),
        )
        with pytest.raises(Exception, match="UNet config differs"):
            train_prior(other, tmp_path / "two")

    def test_fresh_labels_start_another_task_from_the_old_unconditional_model(self, tmp_path):
        first = train_prior(toy(steps=5), tmp_path / "relight")
        light = toy(
            task="light",
            steps=1,
            lr=1e-12,
            warmup_steps=0,
            ema_decay=None,
            init_labels="fresh",
            init_from=str(tmp_path / "relight" / "prior"),
        )
        second = train_prior(light, tmp_path / "light")
        old, new = first.state_dict(), second.state_dict()
        assert second.vocabulary == ("warm", "cool", "white") and set(old) == set(new)
        for k in old:
            if k != "net.label_emb.weight":
                torch.testing.assert_close(new[k], old[k], atol=1e-8, rtol=0, msg=k)
        emb = new["net.label_emb.weight"]
        assert emb.shape == (4, old["net.label_emb.weight"].shape[1])  # three labels and the null label
        for row in emb:  # every label starts as relight's null label
            torch.testing.assert_close(row, old["net.label_emb.weight"][-1], atol=1e-8, rtol=0)
        with pytest.raises(Exception, match="UNet config differs"):  # without "fresh" the vocabularies must agree
            train_prior(toy(task="light", steps=1, init_from=str(tmp_path / "relight" / "prior")), tmp_path / "keep")

    def test_cli_fresh_labels_need_the_same_conditioning_channels(self, tmp_path, capsys):
        from lasagna.cli import main

        train_prior(toy(task="colorize", steps=1), tmp_path / "colour")
        code = main(
            [
                "train-prior",
                "--task",
                "light",
                "--out",
                str(tmp_path / "run"),
                "--init-from",
                str(tmp_path / "colour" / "prior"),
                "--init-labels",
                "fresh",
                "--no-progress",
            ]
        )
        err = capsys.readouterr().err.strip()
        assert code == 2 and err.count("\n") == 0 and "1 conditioning channel(s); a light prior needs 3" in err
        assert not (tmp_path / "run").exists()

    def test_cli_refuses_a_prior_of_another_task(self, tmp_path, capsys):
        from lasagna.cli import main

        train_prior(toy(task="colorize", steps=1), tmp_path / "colour")
        code = main(
            [
                "train-prior",
                "--task",
                "relight",
                "--out",
                str(tmp_path / "run"),
                "--init-from",
                str(tmp_path / "colour" / "prior"),
                "--no-progress",
            ]
        )
        err = capsys.readouterr().err.strip()
        assert code == 2 and err.count("\n") == 0 and "expected a relight prior" in err
        assert not (tmp_path / "run").exists()


class TestDirectionTraining:
    def test_direction_batch_mixes_named_and_random_lights_and_relights_to_them(self):
        from lasagna.document.condition import format_direction
        from lasagna.training.prior import direction_batch
        from lasagna.world.lighting import LIGHTS
        from lasagna.world.scene import with_light
        from lasagna.world.tasks import relight_sources, relighting

        scene = generate("train", 32, seed=3, resolution=8, dtype=torch.float64)
        x0, rows, cond = direction_batch("relit", scene, torch.Generator().manual_seed(0))
        named = [
            i
            for i in range(32)
            if any(
                torch.allclose(rows[i, :3].double(), torch.tensor(v, dtype=torch.float64), atol=1e-6)
                for v in LIGHTS.values()
            )
        ]
        assert 6 <= len(named) <= 26 and rows[:, 3].eq(0).all()  # about half named, none null
        source = with_light(scene, relight_sources(scene.params))
        assert torch.equal(cond, source.image)
        # the target is the scene under each row's direction
        i = next(i for i in range(32) if i not in named)
        v = rows[i, :3].double()
        az = math.degrees(math.atan2(float(v[1]), float(v[0]))) % 360
        el = math.degrees(math.acos(max(-1.0, min(1.0, float(v[2])))))
        again = relighting(scene, relight_sources(scene.params), [format_direction(round(az, 2), round(el, 2))] * 32)
        assert torch.allclose(x0[i], again.target[i], atol=1e-5)
        x0b, rowsb, _ = direction_batch("relit", scene, torch.Generator().manual_seed(0))
        assert torch.equal(x0, x0b) and torch.equal(rows, rowsb)  # a function of the generator's state

    def test_a_label_prior_starts_a_direction_prior(self, tmp_path):
        start = tmp_path / "start"
        torch.manual_seed(0)
        label_prior = UNetPrior(unet_config_for("relight", resolution=8, channels=(8, 16)))
        label_prior.save_pretrained(start)
        unet = unet_config_for("relit", resolution=8, channels=(8, 16), directions=True)
        out = train_prior(toy("relit", unet=unet, steps=1, lr=1e-12, init_from=str(start)), tmp_path / "run")
        assert out.config.directions
        old, new = label_prior.state_dict(), out.state_dict()
        assert torch.allclose(new["net.null_emb"], old["net.label_emb.weight"][-1], atol=1e-6)
        assert torch.allclose(new["net.inp.weight"], old["net.inp.weight"], atol=1e-6)
        assert "net.label_emb.weight" not in new and "net.dir_mlp.0.weight" in new

    def test_directions_only_for_light_tasks(self):
        with pytest.raises(LasagnaError, match="no light direction"):
            unet_config_for("colorize", directions=True)
