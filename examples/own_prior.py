"""Bring your own prior: a Stable Diffusion + ControlNet checkpoint on disk, used by ``lasagna edit``.

    python examples/own_prior.py [OUT_DIR]        (default out/own_prior; under a minute on a CPU)

With real weights you skip step 1 and point the same commands at your folders (on a GPU add
``--device cuda --dtype float16 --variant fp16``)::

    lasagna edit photo.png --prior /models/sd15 --controlnet /models/cn-relight --prompt "dramatic rim light" \\
        --negative-prompt "blurry" --optimize 150 -o out/rim                                   # SDS
    lasagna train-corrective --kind spectral --prior /models/sd15 --controlnet /models/cn-relight \\
        --images photos/ --out runs/sd15-spectral                                              # b̂, closed form
    lasagna edit photo.png --prior /models/sd15 --controlnet /models/cn-relight \\
        --corrective runs/sd15-spectral/corrective --condition left -o out/left                # LMC-SDS
    lasagna prior add /models/sd15 --name relight-sd --controlnet /models/cn-relight \\
        --corrective runs/sd15-spectral/corrective                                             # once
    lasagna edit photo.png --layer relight-sd --condition left -o out/left2                    # then by name

Step 1 here builds a TINY random-weight SD 1.x-style pipeline (UNet, VAE, CLIP text encoder, tokenizer,
scheduler) and a ControlNet and saves them with ``save_pretrained`` — the layout a downloaded checkpoint
has. Its pictures mean nothing; every command runs exactly as it would with real weights. Nothing is
downloaded (the tokenizer's vocabulary is written here, one token per byte).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import torch

EXAMPLES = Path(__file__).resolve().parent
STEPS = "3"  # per-image steps: enough to show the route, not a result


def byte_vocab() -> dict[str, int]:
    """CLIP's specials and one token per byte (GPT-2's byte→unicode table), so no merges file is needed."""
    bs = [*range(ord("!"), ord("~") + 1), *range(ord("¡"), ord("¬") + 1), *range(ord("®"), ord("ÿ") + 1)]
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


def build_tiny_pipeline(root: Path) -> tuple[Path, Path]:
    """A random SD 1.x-style pipeline at ``root/sd`` and a ControlNet at ``root/controlnet``, as save_pretrained
    writes them (latents 4×8×8, images 16×16)."""
    from diffusers import AutoencoderKL, ControlNetModel, DDPMScheduler, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer

    sd = root / "sd"
    (sd / "tokenizer").mkdir(parents=True, exist_ok=True)
    (sd / "tokenizer" / "vocab.json").write_text(json.dumps(byte_vocab()))
    (sd / "tokenizer" / "merges.txt").write_text("#version: 0.2\n")
    tokenizer = CLIPTokenizer.from_pretrained(sd / "tokenizer", model_max_length=64)
    tokenizer.save_pretrained(sd / "tokenizer")
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
    unet.save_pretrained(sd / "unet")
    AutoencoderKL(
        down_block_types=("DownEncoderBlock2D",) * 2,
        up_block_types=("UpDecoderBlock2D",) * 2,
        block_out_channels=(4, 8),
        latent_channels=4,
        norm_num_groups=4,
        sample_size=16,
    ).save_pretrained(sd / "vae")
    config = CLIPTextConfig(
        vocab_size=len(tokenizer),
        hidden_size=16,
        intermediate_size=32,
        num_hidden_layers=2,
        num_attention_heads=2,
        max_position_embeddings=64,
        bos_token_id=0,
        eos_token_id=1,
        pad_token_id=1,
    )
    CLIPTextModel(config).save_pretrained(sd / "text_encoder")
    DDPMScheduler(beta_schedule="scaled_linear", beta_start=0.00085, beta_end=0.012).save_pretrained(sd / "scheduler")
    (sd / "model_index.json").write_text(json.dumps({"_class_name": "StableDiffusionPipeline"}))
    controlnet = ControlNetModel.from_unet(unet, conditioning_embedding_out_channels=(4, 8))
    controlnet.save_pretrained(root / "controlnet")
    return sd, root / "controlnet"


def lasagna(*args) -> None:
    """One ``lasagna`` command, as a user types it (the same Python, so no install is needed)."""
    print("$ lasagna", " ".join(str(a) for a in args))
    subprocess.run([sys.executable, "-m", "lasagna.cli", *map(str, args)], check=True)


def main(out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    os.environ["LASAGNA_LAYERS"] = str(out / "catalogue")  # `prior add` writes here, not into your home
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    sd, cn = build_tiny_pipeline(out / "models")
    photos = out / "photos"
    photos.mkdir(exist_ok=True)
    for name in ("coffee", "chelsea", "astronaut"):
        (photos / f"{name}.png").write_bytes((EXAMPLES / "photos" / f"{name}.png").read_bytes())
    from PIL import Image

    photo = out / "coffee-wide.png"  # 96×64: not the prior's square; its aspect is kept (letterboxed views)
    Image.open(EXAMPLES / "photos" / "coffee.png").crop((0, 16, 96, 80)).save(photo)

    # 2. SDS with a free-text prompt and a negative prompt (the preset's layer: shading, a multiplier).
    lasagna("edit", photo, "--prior", sd, "--controlnet", cn, "--prompt", "dramatic rim light",
            "--negative-prompt", "blurry", "--optimize", STEPS, "--force", "-o", out / "sds")  # fmt: skip
    # 3. The spectral corrective b̂ of this prior, fitted in closed form on the user's photos.
    lasagna("train-corrective", "--kind", "spectral", "--prior", sd, "--controlnet", cn, "--images", photos,
            "--batches", "1", "--buckets", "4", "--batch-size", "3", "--eval-batches", "1",
            "--out", out / "b")  # fmt: skip
    # 4. LMC-SDS: one flag more (--corrective; the loss follows).
    lasagna("edit", photo, "--prior", sd, "--controlnet", cn, "--corrective", out / "b" / "corrective",
            "--condition", "left", "--optimize", STEPS, "--force", "-o", out / "lmc")  # fmt: skip
    # 5. Into the catalogue once, then by name; render re-makes it (and would warn if the weights changed).
    lasagna("prior", "add", sd, "--name", "tiny-sd", "--controlnet", cn, "--corrective", out / "b" / "corrective",
            "--force")  # fmt: skip
    lasagna("edit", photo, "--layer", "tiny-sd", "--condition", "top", "--optimize", STEPS, "--force",
            "-o", out / "by-name")  # fmt: skip
    lasagna("render", out / "by-name", "--all")

    # 6. The same through the Python API.
    from lasagna.api import edit

    res = edit(photo, "shading", prior=sd, controlnets=[(cn, 0.8)], prompt="soft window light", optimize=int(STEPS))
    res.save(out / "api", force=True)
    s = res.settings
    shape, loss, hashed = tuple(res.layer.shape), s["distill"]["loss"], len(s["weights"])
    print(f"API: layer {res.layer_id!r} {shape}, {loss}, the SHA-256 of {hashed} files recorded")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("out/own_prior"))
