"""Toy Stable-Diffusion-style pipelines for tests, built here from small configs (nothing is downloaded).

``sd_parts()`` / ``sdxl_parts()``: a UNet2DConditionModel, a ControlNetModel (its zero convolutions given
weights, else the conditioning image could not matter), an AutoencoderKL, CLIP text encoder(s) and a
byte-level CLIP tokenizer (one token per byte, written to a temporary folder). ``save_pipeline(root, parts)``
writes them as ``save_pretrained`` folders — the layout of a real checkpoint on disk — and
``save_controlnet`` a ControlNet folder. SDXL-style means two text encoders, ``addition_embed_type="text_time"``.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import torch

os.environ.setdefault("HF_HUB_OFFLINE", "1")

from diffusers import AutoencoderKL, ControlNetModel, DDPMScheduler, UNet2DConditionModel  # noqa: E402
from transformers import CLIPTextConfig, CLIPTextModel, CLIPTextModelWithProjection, CLIPTokenizer  # noqa: E402

SD_SCHED = {
    "num_train_timesteps": 1000,
    "beta_schedule": "scaled_linear",
    "beta_start": 0.00085,
    "beta_end": 0.012,
    "prediction_type": "epsilon",
}
TOKENS = 64  # one token per byte: long enough that a label survives truncation
HIDDEN = 16


def byte_level_vocab() -> dict[str, int]:
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


def randomize(module: torch.nn.Module, seed: int, scale: float = 0.05) -> None:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * scale)


def tokenizer() -> CLIPTokenizer:
    folder = Path(tempfile.mkdtemp(prefix="tok-"))
    (folder / "vocab.json").write_text(json.dumps(byte_level_vocab()))
    (folder / "merges.txt").write_text("#version: 0.2\n")
    return CLIPTokenizer.from_pretrained(folder, local_files_only=True, model_max_length=TOKENS)


def _text_config(vocab_size: int, **extra) -> CLIPTextConfig:
    return CLIPTextConfig(
        vocab_size=vocab_size,
        hidden_size=HIDDEN,
        intermediate_size=32,
        num_hidden_layers=2,  # SDXL reads the penultimate hidden state: two layers make it differ from the last
        num_attention_heads=2,
        max_position_embeddings=TOKENS,
        bos_token_id=0,
        eos_token_id=1,
        pad_token_id=1,
        **extra,
    )


def controlnet_for(unet, seed: int = 1) -> ControlNetModel:
    net = ControlNetModel.from_unet(unet, conditioning_embedding_out_channels=(4, 8))
    for m in [*net.controlnet_down_blocks, net.controlnet_cond_embedding.conv_out, net.controlnet_mid_block]:
        randomize(m, seed)
    return net.eval()


def _vae() -> AutoencoderKL:
    return AutoencoderKL(
        in_channels=3,
        out_channels=3,
        down_block_types=("DownEncoderBlock2D", "DownEncoderBlock2D"),
        up_block_types=("UpDecoderBlock2D", "UpDecoderBlock2D"),
        block_out_channels=(4, 8),
        latent_channels=4,
        norm_num_groups=4,
        sample_size=16,
    ).eval()


def _unet(cross_attention_dim: int, **extra) -> UNet2DConditionModel:
    return UNet2DConditionModel(
        sample_size=8,
        in_channels=4,
        out_channels=4,
        layers_per_block=1,
        block_out_channels=(8, 16),
        down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
        cross_attention_dim=cross_attention_dim,
        norm_num_groups=4,
        attention_head_dim=2,
        **extra,
    ).eval()


def sd_parts(seed: int = 0) -> dict:
    """An SD 1.x-style pipeline's parts (latents 4×8×8, images 16×16) and a ControlNet."""
    tok = tokenizer()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        unet = _unet(HIDDEN)
        parts = dict(unet=unet, controlnet=controlnet_for(unet), vae=_vae(), tokenizer=tok)
        parts["text_encoder"] = CLIPTextModel(_text_config(len(tok))).eval()
    return parts


def sdxl_parts(seed: int = 0) -> dict:
    """An SDXL-style pipeline's parts: two text encoders (the second with a projection), text_time embedding."""
    tok = tokenizer()
    time_dim = 4
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        unet = _unet(
            2 * HIDDEN,
            addition_embed_type="text_time",
            addition_time_embed_dim=time_dim,
            projection_class_embeddings_input_dim=6 * time_dim + HIDDEN,
        )
        parts = dict(unet=unet, controlnet=controlnet_for(unet), vae=_vae(), tokenizer=tok, tokenizer_2=tok)
        parts["text_encoder"] = CLIPTextModel(_text_config(len(tok))).eval()
        parts["text_encoder_2"] = CLIPTextModelWithProjection(_text_config(len(tok), projection_dim=HIDDEN)).eval()
    return parts


def save_pipeline(root: Path, parts: dict, scheduler: dict | None = None, variant: str | None = None) -> Path:
    """The parts as a diffusers pipeline folder (what ``save_pretrained`` of a pipeline writes)."""
    root = Path(root)
    for name in ("unet", "vae", "text_encoder", "text_encoder_2"):
        if name in parts:
            parts[name].save_pretrained(root / name, variant=variant)
    for name in ("tokenizer", "tokenizer_2"):
        if name in parts:
            parts[name].save_pretrained(root / name)
    DDPMScheduler(**(scheduler or SD_SCHED)).save_pretrained(root / "scheduler")
    kind = "StableDiffusionXLPipeline" if "text_encoder_2" in parts else "StableDiffusionPipeline"
    (root / "model_index.json").write_text(json.dumps({"_class_name": kind}))
    return root


def save_controlnet(folder: Path, net) -> Path:
    net.save_pretrained(folder)
    return Path(folder)
