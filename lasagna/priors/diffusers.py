"""``DiffusersPrior``: a Stable-Diffusion-style prior from 🤗 diffusers (optional extra ``lasagna[diffusers]``).

It wraps a ``UNet2DConditionModel``, optionally a ``ControlNetModel`` (the Lasagna paper's prior: a
ControlNet conditioned on the input image and a lighting prompt "A photo of an object with [r]
lighting") and optionally an ``AutoencoderKL`` (then the denoiser works on VAE latents):

* ``encode(x)``: x ∈ [0, 1] → the VAE encoder's posterior, WITH gradient (the distillation gradient
  flows through the encoder into the composite), ``latent="mean"`` (deterministic) or ``"sample"``
  (mean + std·ξ, ξ from ``latent_rng``), then (z − shift) × scaling_factor as diffusers
  pipelines do. Without a VAE the UNet works on pixels and ``encode`` is 2x − 1.
* ``decode(z)``: the VAE decoder, back to [0, 1] (not clamped).
* prompts: every vocabulary label is written into ``prompt_template`` and encoded ONCE by the text
  encoder (the last hidden state, as SD pipelines pass it); the empty prompt is the null label.
  ``prompt_embeds`` (V + 1, L, D) — null last — may be passed instead (no text encoder needed).
* the schedule: ᾱ_t built in float64 from the diffusers scheduler config (``beta_schedule``,
  ``beta_start``, ``beta_end``, ``num_train_timesteps``); ``prediction_type`` "epsilon",
  "v_prediction" and "sample" are converted to ε.
* the ControlNet image is passed in [0, 1] at pixel resolution, as diffusers' ControlNet pipelines
  pass it (their control-image processor does not normalise to [−1, 1]).

Using real weights on a GPU machine (nothing is downloaded: point it at folders on disk)::

    from lasagna.priors.diffusers import DiffusersPrior
    prior = DiffusersPrior.from_local(
        "/models/stable-diffusion-v1-5",        # a diffusers folder: unet/ vae/ text_encoder/ tokenizer/ scheduler/
        controlnet="/models/my-relight-controlnet",  # optional: a ControlNetModel folder
        vocabulary=("left", "right", "top", "bottom", "front"),
        prompt_template="A photo of an object with {label} lighting",
        device="cuda", dtype=torch.float16,
    )

(``huggingface-cli download <repo> --local-dir /models/...`` on a machine with network access
produces such folders.) All parameters are frozen (requires_grad=False) and the modules are in eval
mode: the prior is never trained through this adapter.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import torch
from torch import nn

from lasagna.errors import ConditionError, LasagnaError
from lasagna.priors.base import NoiseSchedule, Prior
from lasagna.priors.nn import randn

DEFAULT_TEMPLATE = "A photo of an object with {label} lighting"

# diffusers beta_schedule name -> NoiseSchedule kind (squaredcos_cap_v2 is Nichol & Dhariwal's cosine
# with β clipped at 0.999, exactly what NoiseSchedule("cosine") builds).
_BETA_SCHEDULES = {"linear": "linear", "scaled_linear": "scaled_linear", "squaredcos_cap_v2": "cosine"}
_PREDICTION_TYPES = ("epsilon", "v_prediction", "sample")


def schedule_from_diffusers(config: Mapping[str, Any]) -> tuple[NoiseSchedule, str]:
    """(float64 ``NoiseSchedule``, prediction_type) from a diffusers scheduler config dict.

    Options that change ᾱ beyond these (``trained_betas``, ``rescale_betas_zero_snr``) are refused
    rather than silently ignored.
    """
    if config.get("trained_betas") is not None:
        raise LasagnaError(
            "trained_betas are not supported; expected beta_schedule linear, scaled_linear or squaredcos_cap_v2",
            "scheduler_config",
        )
    if config.get("rescale_betas_zero_snr"):
        raise LasagnaError("rescale_betas_zero_snr is not supported; expected it false", "scheduler_config")
    name = config.get("beta_schedule", "linear")
    if name not in _BETA_SCHEDULES:
        raise LasagnaError(
            f"beta_schedule is {name!r}; expected one of {', '.join(_BETA_SCHEDULES)}", "scheduler_config"
        )
    pred = config.get("prediction_type", "epsilon")
    if pred not in _PREDICTION_TYPES:
        raise LasagnaError(
            f"prediction_type is {pred!r}; expected one of {', '.join(_PREDICTION_TYPES)}", "scheduler_config"
        )
    sched = NoiseSchedule(
        num_steps=int(config.get("num_train_timesteps", 1000)),
        kind=_BETA_SCHEDULES[name],
        beta_start=float(config.get("beta_start", 1e-4)),
        beta_end=float(config.get("beta_end", 0.02)),
    )
    return sched, pred


class DiffusersPrior(Prior):
    """A diffusers UNet (+ ControlNet, + VAE) behind the ``Prior`` interface (see the module docstring)."""

    def __init__(
        self,
        unet: nn.Module,
        scheduler_config: Mapping[str, Any],
        vocabulary: Sequence[str],
        *,
        prompt_template: str = DEFAULT_TEMPLATE,
        text_encoder: nn.Module | None = None,
        tokenizer: Any = None,
        prompt_embeds: torch.Tensor | None = None,
        controlnet: nn.Module | None = None,
        vae: nn.Module | None = None,
        latent: Literal["sample", "mean"] = "mean",
        conditioning_scale: float = 1.0,
        latent_rng: torch.Generator | None = None,
    ):
        super().__init__()
        if latent not in ("sample", "mean"):
            raise ValueError(f"latent must be 'sample' or 'mean', got {latent!r}")
        cfg = unet.config
        if cfg.out_channels != cfg.in_channels:
            raise LasagnaError(
                f"unet.out_channels is {cfg.out_channels}; expected in_channels = {cfg.in_channels} "
                "(learned-variance UNets are not supported)",
                "unet",
            )
        self.unet, self.controlnet, self.vae = unet, controlnet, vae
        self.schedule, self.prediction_type = schedule_from_diffusers(scheduler_config)
        self.vocabulary = tuple(vocabulary)
        self.prompt_template = prompt_template
        self.prompts = tuple(prompt_template.format(label=lab) for lab in self.vocabulary) + ("",)
        self.latent = latent
        self.conditioning_scale = conditioning_scale
        self.latent_rng = latent_rng
        size = cfg.sample_size if isinstance(cfg.sample_size, int) else cfg.sample_size[0]
        self.sample_shape = (cfg.in_channels, size, size)
        self.vae_scale_factor = 2 ** (len(vae.config.block_out_channels) - 1) if vae is not None else 1
        embeds = prompt_embeds if prompt_embeds is not None else self._encode_prompts(text_encoder, tokenizer)
        n = len(self.vocabulary) + 1
        if embeds.dim() != 3 or embeds.shape[0] != n or embeds.shape[2] != cfg.cross_attention_dim:
            raise LasagnaError(
                f"prompt_embeds has shape {tuple(embeds.shape)}; expected ({n}, L, {cfg.cross_attention_dim}) — one "
                "row per label, the null (empty) prompt last",
                "prompt_embeds",
            )
        # A buffer so .to(device, dtype) moves it with the networks; not saved (it is derived data).
        self.register_buffer("prompt_embeds", embeds.detach().clone(), persistent=False)
        self.requires_grad_(False)
        self.eval()

    @torch.no_grad()
    def _encode_prompts(self, text_encoder: nn.Module | None, tokenizer: Any) -> torch.Tensor:
        """Encode every prompt once (the vocabulary's, then the empty one): (V + 1, L, D)."""
        if text_encoder is None or tokenizer is None:
            raise LasagnaError("give either prompt_embeds or both text_encoder and tokenizer", "DiffusersPrior")
        ids = tokenizer(
            list(self.prompts),
            padding="max_length",
            max_length=tokenizer.model_max_length,
            truncation=True,
            return_tensors="pt",
        ).input_ids
        device = next(text_encoder.parameters()).device
        return text_encoder(ids.to(device))[0]  # last_hidden_state, as SD pipelines use it

    # -- the space the denoiser works in --------------------------------------------------------
    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """x ∈ [0, 1] (B, 3, H, W) → latents (B, C, H/f, W/f) in x's dtype; differentiable."""
        if self.vae is None:
            return x * 2 - 1
        vae = self.vae
        dist = vae.encode((x * 2 - 1).to(vae.dtype)).latent_dist
        z = dist.mean
        if self.latent == "sample":
            z = z + dist.std * randn(tuple(z.shape), self.latent_rng, z.device, z.dtype)
        shift = getattr(vae.config, "shift_factor", None) or 0.0
        return ((z - shift) * vae.config.scaling_factor).to(x.dtype)

    def decode(self, z: torch.Tensor) -> torch.Tensor:
        """Latents → image in [0, 1] (not clamped), in z's dtype."""
        if self.vae is None:
            return (z + 1) / 2
        vae = self.vae
        shift = getattr(vae.config, "shift_factor", None) or 0.0
        x = vae.decode((z / vae.config.scaling_factor + shift).to(vae.dtype)).sample
        return ((x + 1) / 2).to(z.dtype)

    # -- the raw network ------------------------------------------------------------------------
    def _eps(
        self, z_t: torch.Tensor, t: torch.Tensor, label_idx: torch.Tensor, image: torch.Tensor | None
    ) -> torch.Tensor:
        dtype, dev = self.unet.dtype, z_t.device
        z = z_t.to(dtype)
        t = t.to(dev)
        enc = self.prompt_embeds[label_idx.to(dev)].to(dtype)  # (B, L, D)
        extra = {}
        if self.controlnet is not None:
            f = self.vae_scale_factor
            c = self.controlnet.config.conditioning_channels
            expected = (z.shape[0], c, z.shape[2] * f, z.shape[3] * f)
            if image is None:
                raise ConditionError(
                    f"this prior has a ControlNet and needs a conditioning image of shape {expected}; got None",
                    "condition.image",
                )
            if tuple(image.shape) != expected:
                raise ConditionError(f"image has shape {tuple(image.shape)}; expected {expected}", "condition.image")
            down, mid = self.controlnet(
                z,
                t,
                encoder_hidden_states=enc,
                controlnet_cond=image.to(dtype),
                conditioning_scale=self.conditioning_scale,
                return_dict=False,
            )
            extra = {"down_block_additional_residuals": down, "mid_block_additional_residual": mid}
        elif image is not None:
            raise ConditionError("this prior has no ControlNet; expected image=None", "condition.image")
        out = self.unet(z, t, encoder_hidden_states=enc, return_dict=False, **extra)[0]
        if self.prediction_type == "v_prediction":
            return self.schedule.eps_from_v(z, out, t)
        if self.prediction_type == "sample":
            return self.schedule.eps_from_x0(z, out, t)
        return out

    # -- loading real weights -------------------------------------------------------------------
    @classmethod
    def from_local(
        cls,
        path: str | os.PathLike,
        *,
        controlnet: str | os.PathLike | None = None,
        vocabulary: Sequence[str],
        prompt_template: str = DEFAULT_TEMPLATE,
        device: str | torch.device = "cuda",
        dtype: torch.dtype = torch.float16,
        latent: Literal["sample", "mean"] = "mean",
        conditioning_scale: float = 1.0,
    ) -> DiffusersPrior:
        """Load a Stable-Diffusion folder (diffusers layout) and an optional ControlNet folder from disk.

        Never touches the network (``local_files_only=True``). ``path`` must hold ``unet/``,
        ``scheduler/scheduler_config.json``, ``text_encoder/`` and ``tokenizer/``; ``vae/`` is
        optional (without it the UNet is taken to work on pixels).
        """
        from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel
        from transformers import CLIPTextModel, CLIPTokenizer

        root = Path(path)
        for sub in ("unet", "scheduler", "text_encoder", "tokenizer"):
            if not (root / sub).is_dir():
                raise LasagnaError(
                    f"missing folder {sub}/; expected a diffusers Stable-Diffusion folder (unet/ scheduler/ "
                    "text_encoder/ tokenizer/ [vae/])",
                    str(root),
                )
        sched_path = root / "scheduler" / "scheduler_config.json"
        try:
            sched_cfg = json.loads(sched_path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise LasagnaError(f"cannot read the scheduler config ({exc})", str(sched_path)) from None
        unet = UNet2DConditionModel.from_pretrained(root, subfolder="unet", local_files_only=True)
        vae = (
            AutoencoderKL.from_pretrained(root, subfolder="vae", local_files_only=True)
            if (root / "vae").is_dir()
            else None
        )
        cn = (
            ControlNetModel.from_pretrained(Path(controlnet), local_files_only=True) if controlnet is not None else None
        )
        tokenizer = CLIPTokenizer.from_pretrained(root, subfolder="tokenizer", local_files_only=True)
        text_encoder = CLIPTextModel.from_pretrained(root, subfolder="text_encoder", local_files_only=True)
        text_encoder = text_encoder.to(device=device, dtype=dtype).eval()
        prior = cls(
            unet.to(device=device, dtype=dtype),
            sched_cfg,
            vocabulary,
            prompt_template=prompt_template,
            text_encoder=text_encoder,
            tokenizer=tokenizer,
            controlnet=cn.to(device=device, dtype=dtype) if cn is not None else None,
            vae=vae.to(device=device, dtype=dtype) if vae is not None else None,
            latent=latent,
            conditioning_scale=conditioning_scale,
        )
        del text_encoder  # the prompts are encoded; the text encoder is not kept
        return prior
