"""DiffusersPrior on toy Stable-Diffusion-style models built here from small configs (nothing is
downloaded; ``tests.support.toydiffusers``). References are diffusers/transformers called by hand and numpy
float64 schedules.
"""

from __future__ import annotations

import os

import numpy as np
import pytest
import torch

os.environ.setdefault("HF_HUB_OFFLINE", "1")
diffusers = pytest.importorskip(
    "diffusers", reason="diffusers is not installed (optional extra lasagna-layers[diffusers])"
)
transformers = pytest.importorskip(
    "transformers", reason="transformers is not installed (optional extra lasagna-layers[diffusers])"
)

from diffusers import DDPMScheduler  # noqa: E402

from lasagna.errors import ConditionError, LasagnaError  # noqa: E402
from lasagna.priors.base import Condition  # noqa: E402
from lasagna.priors.ddim import ddim_sample  # noqa: E402
from lasagna.priors.diffusers import DEFAULT_TEMPLATE, DiffusersPrior, schedule_from_diffusers  # noqa: E402
from tests.support.toydiffusers import SD_SCHED, controlnet_for, save_controlnet, save_pipeline, sd_parts, sdxl_parts  # noqa: E402

VOCAB = ("left", "right")


@pytest.fixture(scope="module")
def parts():
    return sd_parts()


@pytest.fixture(scope="module")
def prior(parts):
    return DiffusersPrior(
        parts["unet"],
        SD_SCHED,
        VOCAB,
        text_encoder=parts["text_encoder"],
        tokenizer=parts["tokenizer"],
        controlnet=parts["controlnet"],
        vae=parts["vae"],
    )


def manual_embedding(parts, text: str) -> torch.Tensor:
    ids = parts["tokenizer"](
        [text], padding="max_length", max_length=64, truncation=True, return_tensors="pt"
    ).input_ids
    with torch.no_grad():
        return parts["text_encoder"](ids).last_hidden_state[0]


def numpy_alpha_bar_sd() -> np.ndarray:
    return np.cumprod(1.0 - np.linspace(0.00085**0.5, 0.012**0.5, 1000) ** 2)


class TestSchedule:
    @pytest.mark.parametrize("name", ["linear", "scaled_linear", "squaredcos_cap_v2"])
    def test_matches_diffusers(self, name):
        cfg = {**SD_SCHED, "beta_schedule": name}
        sched, pred = schedule_from_diffusers(cfg)
        assert pred == "epsilon" and sched.alphas_cumprod.dtype == torch.float64
        ref = DDPMScheduler(**{k: v for k, v in cfg.items()}).alphas_cumprod  # diffusers' own, float32
        np.testing.assert_allclose(sched.alphas_cumprod.numpy(), ref.double().numpy(), atol=2e-6)

    def test_scaled_linear_float64_reference(self):
        sched, _ = schedule_from_diffusers(SD_SCHED)
        np.testing.assert_allclose(sched.alphas_cumprod.numpy(), numpy_alpha_bar_sd(), rtol=1e-12)

    @pytest.mark.parametrize(
        "patch, match",
        [
            ({"trained_betas": [0.1] * 1000}, "trained_betas"),
            ({"rescale_betas_zero_snr": True}, "rescale_betas_zero_snr"),
            ({"beta_schedule": "sigmoid"}, "beta_schedule is 'sigmoid'"),
            ({"prediction_type": "flow"}, "prediction_type is 'flow'"),
        ],
    )
    def test_refused_options(self, patch, match):
        with pytest.raises(LasagnaError, match=match):
            schedule_from_diffusers({**SD_SCHED, **patch})


class TestPrompts:
    def test_embeddings_encoded_once_and_cached(self, parts):
        calls = []
        handle = parts["text_encoder"].register_forward_hook(lambda *a: calls.append(1))
        try:
            p = DiffusersPrior(
                parts["unet"], SD_SCHED, VOCAB, text_encoder=parts["text_encoder"], tokenizer=parts["tokenizer"]
            )
            z = torch.randn(2, 4, 8, 8)
            for _ in range(3):
                p.predict(z, torch.tensor([10, 20]), Condition(["left", "right"]))
        finally:
            handle.remove()
        assert calls == [1]  # all prompts in one text-encoder call, at construction
        assert p.prompts == ("A photo of an object with left lighting", "A photo of an object with right lighting", "")
        assert p.prompt_embeds.shape == (3, 64, 16)
        assert not torch.equal(p.prompt_embeds[0], p.prompt_embeds[1])  # the label survives tokenisation
        for i, text in enumerate(p.prompts):
            torch.testing.assert_close(p.prompt_embeds[i], manual_embedding(parts, text), atol=1e-6, rtol=1e-6)

    def test_precomputed_embeddings(self, parts):
        embeds = torch.randn(3, 5, 16, generator=torch.Generator().manual_seed(0))
        p = DiffusersPrior(parts["unet"], SD_SCHED, VOCAB, prompt_embeds=embeds)
        z, t = torch.randn(2, 4, 8, 8), torch.tensor([100, 700])
        eps = p.predict(z, t, Condition(["right", "left"]), branches=("cond", "uncond")).eps
        with torch.no_grad():
            ref_c = parts["unet"](z, t, encoder_hidden_states=embeds[[1, 0]]).sample
            ref_u = parts["unet"](z, t, encoder_hidden_states=embeds[[2, 2]]).sample
        torch.testing.assert_close(eps["cond"], ref_c, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(eps["uncond"], ref_u, atol=1e-5, rtol=1e-5)

    def test_embedding_errors(self, parts):
        with pytest.raises(LasagnaError, match="prompt_embeds has shape"):
            DiffusersPrior(parts["unet"], SD_SCHED, VOCAB, prompt_embeds=torch.zeros(2, 5, 16))
        with pytest.raises(LasagnaError, match="either prompt_embeds or both"):
            DiffusersPrior(parts["unet"], SD_SCHED, VOCAB)


class TestEps:
    def test_controlnet_path_matches_manual_diffusers(self, prior, parts):
        z, t = torch.randn(2, 4, 8, 8), torch.tensor([5, 800])
        img = torch.rand(2, 3, 16, 16)
        eps = prior.predict(z, t, Condition(["left", "right"], image=img)).eps
        enc_c = torch.stack(
            [manual_embedding(parts, DEFAULT_TEMPLATE.format(label=label)) for label in ("left", "right")]
        )
        enc_u = torch.stack([manual_embedding(parts, "")] * 2)
        with torch.no_grad():
            for key, enc in (("cond", enc_c), ("uncond", enc_u)):
                down, mid = parts["controlnet"](z, t, encoder_hidden_states=enc, controlnet_cond=img, return_dict=False)
                ref = parts["unet"](
                    z,
                    t,
                    encoder_hidden_states=enc,
                    down_block_additional_residuals=down,
                    mid_block_additional_residual=mid,
                ).sample
                torch.testing.assert_close(eps[key], ref, atol=1e-5, rtol=1e-5)

    def test_image_and_label_matter(self, prior):
        z, t = torch.randn(1, 4, 8, 8), torch.tensor([300])
        a = prior._eps(z, t, torch.tensor([0]), torch.zeros(1, 3, 16, 16))
        b = prior._eps(z, t, torch.tensor([0]), torch.ones(1, 3, 16, 16))
        c = prior._eps(z, t, torch.tensor([1]), torch.zeros(1, 3, 16, 16))
        assert (a - b).abs().max() > 1e-6 and (a - c).abs().max() > 1e-6

    def test_v_prediction_converted(self, parts):
        p = DiffusersPrior(
            parts["unet"], {**SD_SCHED, "prediction_type": "v_prediction"}, VOCAB, prompt_embeds=torch.randn(3, 5, 16)
        )
        z, t = torch.randn(2, 4, 8, 8), torch.tensor([0, 999])
        with torch.no_grad():
            v = parts["unet"](z, t, encoder_hidden_states=p.prompt_embeds[[0, 0]]).sample.double().numpy()
            eps = p._eps(z, t, torch.tensor([0, 0]), None).double().numpy()
        ab = numpy_alpha_bar_sd()[[0, 999]][:, None, None, None]
        np.testing.assert_allclose(eps, np.sqrt(ab) * v + np.sqrt(1 - ab) * z.double().numpy(), atol=1e-5)

    def test_condition_errors(self, prior, parts):
        z, t = torch.randn(1, 4, 8, 8), torch.tensor([3])
        with pytest.raises(ConditionError, match="needs a conditioning image"):
            prior.predict(z, t, Condition("left"))
        with pytest.raises(ConditionError, match=r"expected \(2, 3, 16, 16\)"):
            prior.predict(z, t, Condition("left", image=torch.rand(1, 3, 8, 8)))
        with pytest.raises(ConditionError, match="expected one of left, right"):
            prior.predict(z, t, Condition("top", image=torch.rand(1, 3, 16, 16)))
        bare = DiffusersPrior(parts["unet"], SD_SCHED, VOCAB, prompt_embeds=torch.randn(3, 5, 16))
        with pytest.raises(ConditionError, match="has no ControlNet"):
            bare.predict(z, t, Condition("left", image=torch.rand(1, 3, 16, 16)))

    def test_frozen_and_eval(self, prior):
        assert not any(p.requires_grad for p in prior.parameters())
        assert not prior.training and prior.sample_shape == (4, 8, 8)


class TestLatents:
    def test_encode_mean_matches_vae_and_has_gradient(self, prior, parts):
        x = torch.rand(2, 3, 16, 16, requires_grad=True)
        z = prior.encode(x)
        assert z.shape == (2, 4, 8, 8)
        with torch.no_grad():
            ref = parts["vae"].encode(x * 2 - 1).latent_dist.mean * parts["vae"].config.scaling_factor
        torch.testing.assert_close(z.detach(), ref, atol=1e-6, rtol=1e-6)
        z.square().sum().backward()
        assert x.grad is not None and torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0

    def test_encode_sample_is_seeded(self, parts):
        def make(seed):
            return DiffusersPrior(
                parts["unet"],
                SD_SCHED,
                VOCAB,
                prompt_embeds=torch.randn(3, 5, 16),
                vae=parts["vae"],
                latent="sample",
                latent_rng=torch.Generator().manual_seed(seed),
            )

        x = torch.rand(1, 3, 16, 16)
        a, b, c = make(0).encode(x), make(0).encode(x), make(1).encode(x)
        mean = DiffusersPrior(
            parts["unet"], SD_SCHED, VOCAB, prompt_embeds=torch.randn(3, 5, 16), vae=parts["vae"]
        ).encode(x)
        assert torch.equal(a, b) and not torch.equal(a, c) and not torch.allclose(a, mean)

    def test_decode_and_pixel_mode(self, prior, parts):
        assert prior.decode(torch.randn(2, 4, 8, 8)).shape == (2, 3, 16, 16)
        with pytest.raises(ValueError, match="latent"):
            DiffusersPrior(parts["unet"], SD_SCHED, VOCAB, prompt_embeds=torch.randn(3, 5, 16), latent="mode")

    def test_ddim_end_to_end(self, prior):
        out = ddim_sample(
            prior,
            Condition(["left", "right"], image=torch.rand(2, 3, 16, 16)),
            steps=3,
            omega=2.0,
            rng=torch.Generator().manual_seed(0),
        )
        assert out.z.shape == (2, 4, 8, 8) and out.image.shape == (2, 3, 16, 16)
        assert torch.isfinite(out.image).all()


class TestFromLocal:
    def test_loads_a_diffusers_folder(self, parts, prior, tmp_path):
        root = tmp_path / "sd"
        parts["unet"].save_pretrained(root / "unet")
        parts["vae"].save_pretrained(root / "vae")
        parts["text_encoder"].save_pretrained(root / "text_encoder")
        parts["tokenizer"].save_pretrained(root / "tokenizer")
        DDPMScheduler(**SD_SCHED).save_pretrained(root / "scheduler")
        parts["controlnet"].save_pretrained(tmp_path / "cn")
        loaded = DiffusersPrior.from_local(
            root, controlnet=tmp_path / "cn", vocabulary=VOCAB, device="cpu", dtype=torch.float32
        )
        z, t, img = torch.randn(1, 4, 8, 8), torch.tensor([400]), torch.rand(1, 3, 16, 16)
        a = loaded.predict(z, t, Condition("right", image=img)).eps
        b = prior.predict(z, t, Condition("right", image=img)).eps
        for k in a:
            torch.testing.assert_close(a[k], b[k], atol=1e-5, rtol=1e-5)

    def test_missing_folder(self, tmp_path):
        (tmp_path / "unet").mkdir()
        with pytest.raises(LasagnaError, match="missing folder scheduler/"):
            DiffusersPrior.from_local(tmp_path, vocabulary=VOCAB, device="cpu", dtype=torch.float32)


class TestFreeTextAndNegativePrompts:
    def test_free_text_replaces_the_template(self, parts):
        p = DiffusersPrior(
            parts["unet"],
            SD_SCHED,
            ("prompt",),
            prompts={"prompt": "dramatic rim light"},
            text_encoder=parts["text_encoder"],
            tokenizer=parts["tokenizer"],
        )
        assert p.prompts == ("dramatic rim light", "")
        torch.testing.assert_close(p.prompt_embeds[0], manual_embedding(parts, "dramatic rim light"))
        torch.testing.assert_close(p.prompt_embeds[1], manual_embedding(parts, ""))  # the null prompt: uncond
        other = DiffusersPrior(
            parts["unet"],
            SD_SCHED,
            ("prompt",),
            prompts={"prompt": "soft window light"},
            text_encoder=parts["text_encoder"],
            tokenizer=parts["tokenizer"],
        )
        assert not torch.allclose(p.prompt_embeds[0], other.prompt_embeds[0])  # the embedding follows the text

    def test_negative_prompt_replaces_the_unconditional_branch(self, parts):
        kw = dict(text_encoder=parts["text_encoder"], tokenizer=parts["tokenizer"])
        plain = DiffusersPrior(parts["unet"], SD_SCHED, VOCAB, **kw)
        neg = DiffusersPrior(parts["unet"], SD_SCHED, VOCAB, negative_prompt="blurry, flat", **kw)
        torch.testing.assert_close(neg.prompt_embeds[-1], manual_embedding(parts, "blurry, flat"))
        torch.testing.assert_close(neg.prompt_embeds[:-1], plain.prompt_embeds[:-1])
        z, t = torch.randn(1, 4, 8, 8), torch.tensor([500])
        a = plain.predict(z, t, Condition("left"))
        b = neg.predict(z, t, Condition("left"))
        torch.testing.assert_close(a.eps["cond"], b.eps["cond"])
        assert (a.eps["uncond"] - b.eps["uncond"]).abs().max() > 1e-6

    def test_prompt_for_an_unknown_label(self, parts):
        with pytest.raises(LasagnaError, match="not in the vocabulary"):
            DiffusersPrior(parts["unet"], SD_SCHED, VOCAB, prompts={"top": "x"}, prompt_embeds=torch.randn(3, 5, 16))


class TestMultiControlNet:
    def test_two_nets_sum_their_residuals_with_their_scales(self, parts):
        second = controlnet_for(parts["unet"], seed=7)
        embeds = torch.randn(3, 5, 16, generator=torch.Generator().manual_seed(0))
        p = DiffusersPrior(
            parts["unet"],
            SD_SCHED,
            VOCAB,
            prompt_embeds=embeds,
            controlnet=[parts["controlnet"], second],
            conditioning_scale=[0.5, 2.0],
            vae=parts["vae"],
        )
        z, t = torch.randn(1, 4, 8, 8), torch.tensor([300])
        a, b = torch.rand(1, 3, 16, 16), torch.rand(1, 3, 16, 16)
        eps = p._eps(z, t, torch.tensor([0]), torch.cat([a, b], dim=1))
        with torch.no_grad():
            enc = embeds[[0]]
            d1, m1 = parts["controlnet"](z, t, enc, controlnet_cond=a, conditioning_scale=0.5, return_dict=False)
            d2, m2 = second(z, t, enc, controlnet_cond=b, conditioning_scale=2.0, return_dict=False)
            ref = parts["unet"](
                z,
                t,
                encoder_hidden_states=enc,
                down_block_additional_residuals=[x + y for x, y in zip(d1, d2)],
                mid_block_additional_residual=m1 + m2,
            ).sample
        torch.testing.assert_close(eps, ref, atol=1e-5, rtol=1e-5)
        shared = p._eps(z, t, torch.tensor([0]), a)  # one 3-channel image is shared by both nets
        concat = p._eps(z, t, torch.tensor([0]), torch.cat([a, a], dim=1))
        torch.testing.assert_close(shared, concat)
        with pytest.raises(ConditionError, match=r"expected \(1, 6, 16, 16\)"):
            p._eps(z, t, torch.tensor([0]), torch.rand(1, 4, 16, 16))

    def test_scales_must_match_the_nets(self, parts):
        with pytest.raises(LasagnaError, match="2 conditioning scale"):
            DiffusersPrior(
                parts["unet"],
                SD_SCHED,
                VOCAB,
                prompt_embeds=torch.randn(3, 5, 16),
                controlnet=[parts["controlnet"]] * 3,
                conditioning_scale=[1.0, 2.0],
            )


@pytest.fixture(scope="module")
def xl():
    return sdxl_parts()


class TestSDXL:
    def test_added_cond_kwargs_match_the_pipeline_recipe(self, xl):
        p = DiffusersPrior(
            xl["unet"],
            SD_SCHED,
            VOCAB,
            text_encoder=xl["text_encoder"],
            tokenizer=xl["tokenizer"],
            text_encoder_2=xl["text_encoder_2"],
            tokenizer_2=xl["tokenizer_2"],
            force_zeros_for_empty_prompt=True,
            controlnet=xl["controlnet"],
            vae=xl["vae"],
        )
        text = DEFAULT_TEMPLATE.format(label="right")
        ids = xl["tokenizer"]([text], padding="max_length", max_length=64, truncation=True, return_tensors="pt")
        with torch.no_grad():
            h1 = xl["text_encoder"](ids.input_ids, output_hidden_states=True).hidden_states[-2]
            out2 = xl["text_encoder_2"](ids.input_ids, output_hidden_states=True)
        enc = torch.cat([h1, out2.hidden_states[-2]], dim=-1)
        torch.testing.assert_close(p.prompt_embeds[1:2], enc)
        torch.testing.assert_close(p.pooled_embeds[1:2], out2.text_embeds)
        assert p.prompt_embeds[-1].abs().max() == 0 and p.pooled_embeds[-1].abs().max() == 0  # zeros for ""
        z, t, img = torch.randn(1, 4, 8, 8), torch.tensor([250]), torch.rand(1, 3, 16, 16)
        eps = p._eps(z, t, torch.tensor([1]), img)
        added = {"text_embeds": out2.text_embeds, "time_ids": torch.tensor([[16.0, 16.0, 0.0, 0.0, 16.0, 16.0]])}
        with torch.no_grad():
            down, mid = xl["controlnet"](z, t, enc, controlnet_cond=img, added_cond_kwargs=added, return_dict=False)
            ref = xl["unet"](
                z,
                t,
                encoder_hidden_states=enc,
                added_cond_kwargs=added,
                down_block_additional_residuals=down,
                mid_block_additional_residual=mid,
            ).sample
        torch.testing.assert_close(eps, ref, atol=1e-5, rtol=1e-5)

    def test_loads_an_sdxl_folder(self, xl, tmp_path):
        root = save_pipeline(tmp_path / "xl", xl)
        p = DiffusersPrior.from_local(root, vocabulary=VOCAB, device="cpu")
        assert p.sdxl and p.pooled_embeds.shape == (3, 16) and p.prompt_embeds.shape == (3, 64, 32)
        assert p.prompt_embeds[-1].abs().max() == 0  # force_zeros_for_empty_prompt: SDXL's default
        out = p.predict(torch.randn(1, 4, 8, 8), torch.tensor([10]), Condition("left"))
        assert torch.isfinite(out.eps["cond"]).all()


class TestLoadOptions:
    def test_dtype_variant_slicing_channels_last(self, parts, tmp_path):
        root = save_pipeline(tmp_path / "sd", parts, variant="fp16")
        save_controlnet(tmp_path / "cn", parts["controlnet"])
        p = DiffusersPrior.from_local(
            root,
            controlnets=[tmp_path / "cn", tmp_path / "cn"],
            conditioning_scale=[1.0, 0.5],
            vocabulary=VOCAB,
            device="cpu",
            dtype="bfloat16",
            variant="fp16",
            attention_slicing=True,
            channels_last=True,
        )
        assert p.unet.dtype == torch.bfloat16 and p.controlnets[1].dtype == torch.bfloat16
        assert len(p.controlnets) == 2 and p.conditioning_scales == (1.0, 0.5)
        out = p.predict(torch.randn(1, 4, 8, 8), torch.tensor([10]), Condition("left", image=torch.rand(1, 3, 16, 16)))
        assert out.eps["cond"].dtype == torch.bfloat16 and torch.isfinite(out.eps["cond"].float()).all()

    def test_missing_variant_is_one_line(self, parts, tmp_path):
        root = save_pipeline(tmp_path / "sd", parts)
        with pytest.raises(LasagnaError, match="cannot load the unet") as err:
            DiffusersPrior.from_local(root, vocabulary=VOCAB, device="cpu", variant="fp16")
        assert "\n" not in str(err.value)

    def test_offload_needs_an_accelerator(self, parts, tmp_path):
        root = save_pipeline(tmp_path / "sd", parts)
        with pytest.raises(LasagnaError, match="cpu_offload: model CPU offload"):
            DiffusersPrior.from_local(root, vocabulary=VOCAB, device="cpu", cpu_offload=True)

    def test_offload_moves_one_network_at_a_time(self, parts):
        p = DiffusersPrior(
            parts["unet"],
            SD_SCHED,
            VOCAB,
            prompt_embeds=torch.randn(3, 5, 16),
            controlnet=parts["controlnet"],
            vae=parts["vae"],
            offload_device="cpu",
        )
        seen = []
        p._offload["device"] = torch.device("cpu")
        original = p._use
        p._use = lambda m: (seen.append(type(m).__name__), original(m))[1]
        p.predict(torch.randn(1, 4, 8, 8), torch.tensor([10]), Condition("left", image=torch.rand(1, 3, 16, 16)))
        assert seen == ["ControlNetModel", "UNet2DConditionModel"] and p._offload["active"] is p.unet

    def test_bad_dtype(self):
        from lasagna.priors.diffusers import resolve_dtype

        assert resolve_dtype("auto", "cpu") == torch.float32 and resolve_dtype("auto", "cuda") == torch.float16
        with pytest.raises(LasagnaError, match="torch_dtype: got 'half'"):
            resolve_dtype("half", "cpu")


class TestUsedFiles:
    def test_weights_of_the_variant_and_every_config(self, parts, tmp_path):
        from lasagna.priors.diffusers import used_files

        root = save_pipeline(tmp_path / "sd", parts)
        parts["unet"].save_pretrained(root / "unet", variant="fp16")
        plain = {f.relative_to(root).as_posix() for f in used_files(root)}
        half = {f.relative_to(root).as_posix() for f in used_files(root, "fp16")}
        assert "unet/diffusion_pytorch_model.safetensors" in plain and "unet/config.json" in plain
        assert "unet/diffusion_pytorch_model.fp16.safetensors" not in plain
        assert "unet/diffusion_pytorch_model.fp16.safetensors" in half
        assert "scheduler/scheduler_config.json" in plain and "tokenizer/tokenizer.json" in plain
