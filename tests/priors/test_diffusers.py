"""DiffusersPrior on TINY Stable-Diffusion-style models built here from small configs (nothing is
downloaded): a UNet2DConditionModel, a ControlNetModel, an AutoencoderKL, a CLIP text encoder and a
byte-level CLIP tokenizer written to a temporary folder. References are diffusers/transformers
called by hand and numpy float64 schedules.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch

os.environ.setdefault("HF_HUB_OFFLINE", "1")
diffusers = pytest.importorskip("diffusers", reason="diffusers is not installed (optional extra lasagna[diffusers])")
transformers = pytest.importorskip(
    "transformers", reason="transformers is not installed (optional extra lasagna[diffusers])"
)

from diffusers import AutoencoderKL, ControlNetModel, DDPMScheduler, UNet2DConditionModel  # noqa: E402
from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer  # noqa: E402

from lasagna.errors import ConditionError, LasagnaError  # noqa: E402
from lasagna.priors.base import Condition  # noqa: E402
from lasagna.priors.ddim import ddim_sample  # noqa: E402
from lasagna.priors.diffusers import DEFAULT_TEMPLATE, DiffusersPrior, schedule_from_diffusers  # noqa: E402

VOCAB = ("left", "right")
SD_SCHED = {
    "num_train_timesteps": 1000,
    "beta_schedule": "scaled_linear",
    "beta_start": 0.00085,
    "beta_end": 0.012,
    "prediction_type": "epsilon",
}


def _byte_level_vocab() -> dict[str, int]:
    """GPT-2's byte→unicode table (written out here) as single-character tokens, plus CLIP's specials."""
    bs = list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1)) + list(range(ord("®"), ord("ÿ") + 1))
    cs, n = bs[:], 0
    for b in range(256):
        if b not in bs:
            bs.append(b)
            cs.append(256 + n)
            n += 1
    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for suffix in ("", "</w>"):
        for c in cs:
            vocab.setdefault(chr(c) + suffix, len(vocab))
    return vocab


def _randomize(module, seed, scale=0.05):
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * scale)


@pytest.fixture(scope="module")
def parts(tmp_path_factory):
    tok_dir = tmp_path_factory.mktemp("tokenizer")
    (tok_dir / "vocab.json").write_text(json.dumps(_byte_level_vocab()))
    (tok_dir / "merges.txt").write_text("#version: 0.2\n")
    # One token per byte, so 64 positions: long enough that the label survives truncation.
    tokenizer = CLIPTokenizer.from_pretrained(tok_dir, local_files_only=True, model_max_length=64)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        unet = UNet2DConditionModel(
            sample_size=8,
            in_channels=4,
            out_channels=4,
            layers_per_block=1,
            block_out_channels=(8, 16),
            down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
            up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
            cross_attention_dim=16,
            norm_num_groups=4,
            attention_head_dim=2,
        )
        controlnet = ControlNetModel.from_unet(unet, conditioning_embedding_out_channels=(4, 8))
        # ControlNet's zero convolutions would make the image irrelevant; give them weights.
        zero_init = [controlnet.controlnet_cond_embedding.conv_out, controlnet.controlnet_mid_block]
        for m in list(controlnet.controlnet_down_blocks) + zero_init:
            _randomize(m, 1)
        vae = AutoencoderKL(
            in_channels=3,
            out_channels=3,
            down_block_types=("DownEncoderBlock2D", "DownEncoderBlock2D"),
            up_block_types=("UpDecoderBlock2D", "UpDecoderBlock2D"),
            block_out_channels=(4, 8),
            latent_channels=4,
            norm_num_groups=4,
            sample_size=16,
        )
        text_encoder = CLIPTextModel(
            CLIPTextConfig(
                vocab_size=len(tokenizer),
                hidden_size=16,
                intermediate_size=32,
                num_hidden_layers=1,
                num_attention_heads=2,
                max_position_embeddings=64,
                bos_token_id=0,
                eos_token_id=1,
                pad_token_id=1,
            )
        ).eval()
    return dict(
        unet=unet.eval(), controlnet=controlnet.eval(), vae=vae.eval(), text_encoder=text_encoder, tokenizer=tokenizer
    )


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
