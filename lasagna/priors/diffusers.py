"""``DiffusersPrior``: a Stable-Diffusion-style prior from 🤗 diffusers (optional extra ``lasagna-layers[diffusers]``).

It wraps a ``UNet2DConditionModel`` (SD 1.x, 2.x or SDXL), any number of ControlNets (``ControlNetModel``; the
Lasagna paper's prior is a ControlNet conditioned on the input image and a lighting prompt "A photo of
an object with [r] lighting") and optionally an ``AutoencoderKL`` (then the denoiser works on latents):

* ``encode(x)``: x ∈ [0, 1] → the VAE encoder's posterior, WITH gradient (the distillation gradient
  flows through the encoder into the composite), ``latent="mean"`` (deterministic) or ``"sample"``
  (mean + std·ξ, ξ from ``latent_rng``), then (z − shift) × scaling_factor as diffusers
  pipelines do. Without a VAE the UNet works on pixels and ``encode`` is 2x − 1. A VAE whose config
  says ``force_upcast`` (SDXL's overflows in float16) is run in float32.
* **prompts**: one text per vocabulary label — the label written into ``prompt_template``, or the
  label's own text from ``prompts`` (free text, e.g. ``{"prompt": "dramatic rim light"}``) — and the
  **unconditional** text, ``negative_prompt`` ("" by default: the null prompt). Every text is encoded
  ONCE by the text encoder(s) at construction. The negative prompt *replaces* the unconditional branch
  ε_u of ε̂ = ε_u + ω(ε_c − ε_u), as diffusers pipelines do with ``negative_prompt``.
  ``prompt_embeds`` (V + 1, L, D) — unconditional row last — may be passed instead (no encoder needed).
* **SD 1.x/2.x** pass the text encoder's last hidden state; **SDXL** (a UNet with
  ``addition_embed_type="text_time"``) the penultimate hidden states of both encoders concatenated,
  the second encoder's pooled projection as ``text_embeds`` and the micro-conditioning ``time_ids``
  (original size, crop corner (0, 0), target size: the view's pixel size), as
  ``StableDiffusionXLPipeline`` builds them; an empty negative prompt is all zeros when the pipeline's
  ``force_zeros_for_empty_prompt`` is set (SDXL base's default).
* the schedule: ᾱ_t built in float64 from the diffusers scheduler config (``beta_schedule``,
  ``beta_start``, ``beta_end``, ``num_train_timesteps``); ``prediction_type`` "epsilon",
  "v_prediction" and "sample" are converted to ε.
* **ControlNets**: their residuals are summed (``MultiControlNetModel``'s rule), each net with its own
  ``conditioning_scale``. The conditioning image is passed in [0, 1] at pixel resolution, as diffusers'
  ControlNet pipelines pass it (their control-image processor does not normalise to [−1, 1]); with
  several nets it is their images concatenated along the channels (``Condition.image`` stays one
  tensor), or one image every net shares.

Using real weights on a GPU machine (nothing is downloaded: point it at folders on disk)::

    from lasagna.priors.diffusers import DiffusersPrior
    prior = DiffusersPrior.from_local(
        "/models/stable-diffusion-v1-5",        # a diffusers folder: unet/ vae/ text_encoder/ tokenizer/ scheduler/
        controlnets=["/models/my-relight-controlnet"],   # ControlNetModel folders, optional
        vocabulary=("left", "right", "top", "bottom", "front"),
        prompt_template="A photo of an object with {label} lighting",
        device="cuda", dtype="float16", variant="fp16",
    )

(``huggingface-cli download <repo> --local-dir /models/...`` on a machine with network access
produces such folders.) All parameters are frozen (requires_grad=False) and the modules are in eval
mode: the prior is never trained through this adapter. ``lasagna edit --prior PATH`` and
``lasagna prior add`` load it through ``lasagna.catalogue.load_prior``.
"""

from __future__ import annotations

import contextlib
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
from lasagna.version import install_hint, missing_extra

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


# Floating-point types a user may ask the networks to run in ("auto": float16 on CUDA, where SD weights are
# published and run in half precision, float32 elsewhere: CPU half precision is slow and lacks kernels).
DTYPES: dict[str, torch.dtype] = {"float32": torch.float32, "float16": torch.float16, "bfloat16": torch.bfloat16}
DtypeName = Literal["auto", "float32", "float16", "bfloat16"]

# Files diffusers/transformers read weights from; a folder holding both formats is read as safetensors.
WEIGHT_SUFFIXES = (".safetensors", ".bin", ".ckpt", ".pt", ".pth")
# The sub-folders of a pipeline folder this adapter reads (``used_files`` hashes what is in them).
COMPONENTS = ("unet", "vae", "text_encoder", "text_encoder_2", "tokenizer", "tokenizer_2", "scheduler")
SDXL_CROP_TOP_LEFT = (0, 0)  # SDXL micro-conditioning: the view is the whole image, not a crop of one


def resolve_dtype(dtype: torch.dtype | str | None, device: str | torch.device) -> torch.dtype:
    """``dtype`` as a torch dtype; ``None``/``"auto"`` is float16 on CUDA and float32 elsewhere."""
    if isinstance(dtype, torch.dtype):
        return dtype
    if dtype in (None, "auto"):
        return torch.float16 if torch.device(device).type == "cuda" else torch.float32
    if dtype not in DTYPES:
        raise LasagnaError(f"got {dtype!r}; expected auto, {', '.join(DTYPES)}", "torch_dtype")
    return DTYPES[dtype]


def _as_nets(controlnet: Any) -> list[nn.Module]:
    """One ControlNet, a sequence of them, or diffusers' ``MultiControlNetModel`` (its ``nets``), as a list."""
    if controlnet is None:
        return []
    if isinstance(controlnet, (list, tuple, nn.ModuleList)):
        return list(controlnet)
    if hasattr(controlnet, "nets"):
        return list(controlnet.nets)
    return [controlnet]


@torch.no_grad()
def encode_prompts(texts: Sequence[str], encoders: Sequence[tuple[Any, nn.Module]], sdxl: bool):
    """Every text through the text encoder(s), in one call each: ((N, L, D), pooled (N, P) or None).

    SD 1.x/2.x: the last hidden state of the one encoder. SDXL: the penultimate hidden states of both
    encoders, concatenated, and the pooled projection of the last (``StableDiffusionXLPipeline.encode_prompt``).
    A text longer than the tokenizer's window is cut there, as the pipelines cut it, with a warning.
    """
    import warnings

    hidden, pooled = [], None
    for tokenizer, encoder in encoders:
        tokens = tokenizer(
            list(texts),
            padding="max_length",
            max_length=tokenizer.model_max_length,
            truncation=True,
            return_tensors="pt",
        )
        full = tokenizer(list(texts), padding="longest", return_tensors="pt").input_ids
        if full.shape[-1] > tokens.input_ids.shape[-1]:
            warnings.warn(
                f"a prompt is longer than the text encoder's {tokenizer.model_max_length} tokens; the rest is cut",
                stacklevel=3,
            )
        device = next(encoder.parameters()).device
        out = encoder(tokens.input_ids.to(device), output_hidden_states=sdxl)
        if not sdxl:
            return out[0], None  # last_hidden_state, as SD pipelines use it
        hidden.append(out.hidden_states[-2])
        if out[0].dim() == 2:  # CLIPTextModelWithProjection: text_embeds, SDXL's pooled prompt
            pooled = out[0]
    if pooled is None:
        raise LasagnaError("no text encoder gave a pooled projection; expected text_encoder_2 (SDXL)", "text_encoder_2")
    return torch.cat(hidden, dim=-1), pooled


class DiffusersPrior(Prior):
    """A diffusers UNet (+ ControlNets, + VAE) behind the ``Prior`` interface (see the module docstring)."""

    def __init__(
        self,
        unet: nn.Module,
        scheduler_config: Mapping[str, Any],
        vocabulary: Sequence[str],
        *,
        prompt_template: str = DEFAULT_TEMPLATE,
        prompts: Mapping[str, str] | None = None,
        negative_prompt: str = "",
        text_encoder: nn.Module | None = None,
        tokenizer: Any = None,
        text_encoder_2: nn.Module | None = None,
        tokenizer_2: Any = None,
        prompt_embeds: torch.Tensor | None = None,
        pooled_embeds: torch.Tensor | None = None,
        force_zeros_for_empty_prompt: bool = False,
        controlnet: Any = None,
        vae: nn.Module | None = None,
        latent: Literal["sample", "mean"] = "mean",
        conditioning_scale: float | Sequence[float] = 1.0,
        latent_rng: torch.Generator | None = None,
        offload_device: str | torch.device | None = None,
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
        self.unet, self.vae = unet, vae
        self.controlnets = nn.ModuleList(_as_nets(controlnet))
        n = len(self.controlnets)
        scales = [float(conditioning_scale)] * n if isinstance(conditioning_scale, (int, float)) else conditioning_scale
        if len(scales) != n:
            raise LasagnaError(
                f"got {len(scales)} conditioning scale(s) for {n} ControlNet(s); expected one, or one per net",
                "conditioning_scale",
            )
        self.conditioning_scales = tuple(float(s) for s in scales)
        self.control_channels = tuple(int(net.config.conditioning_channels) for net in self.controlnets)
        self.sdxl = getattr(cfg, "addition_embed_type", None) == "text_time"
        self.schedule, self.prediction_type = schedule_from_diffusers(scheduler_config)
        self.vocabulary = tuple(vocabulary)
        self.prompt_template = prompt_template
        own = dict(prompts or {})
        unknown = sorted(set(own) - set(self.vocabulary))
        if unknown:
            raise LasagnaError(
                f"prompts for {', '.join(unknown)}, which are not in the vocabulary; expected labels of "
                f"{', '.join(self.vocabulary)}",
                "prompts",
            )
        texts = [own[lab] if lab in own else prompt_template.format(label=lab) for lab in self.vocabulary]
        self.prompts = (*texts, negative_prompt)
        self.negative_prompt = negative_prompt
        self.latent = latent
        self.latent_rng = latent_rng
        size = cfg.sample_size if isinstance(cfg.sample_size, int) else cfg.sample_size[0]
        self.sample_shape = (cfg.in_channels, size, size)
        self.vae_scale_factor = 2 ** (len(vae.config.block_out_channels) - 1) if vae is not None else 1
        if prompt_embeds is None:
            if text_encoder is None or tokenizer is None:
                raise LasagnaError("give either prompt_embeds or both text_encoder and tokenizer", "DiffusersPrior")
            encoders = [(tokenizer, text_encoder)]
            if self.sdxl:
                if text_encoder_2 is None or tokenizer_2 is None:
                    raise LasagnaError("an SDXL UNet needs text_encoder_2 and tokenizer_2; got none", "DiffusersPrior")
                encoders.append((tokenizer_2, text_encoder_2))
            prompt_embeds, pooled_embeds = encode_prompts(self.prompts, encoders, self.sdxl)
            if force_zeros_for_empty_prompt and negative_prompt == "":
                prompt_embeds[-1] = 0  # SDXL's unconditional branch: zeros, not the encoded empty prompt
                if pooled_embeds is not None:
                    pooled_embeds[-1] = 0
        rows = len(self.vocabulary) + 1
        if (
            prompt_embeds.dim() != 3
            or prompt_embeds.shape[0] != rows
            or prompt_embeds.shape[2] != cfg.cross_attention_dim
        ):
            raise LasagnaError(
                f"prompt_embeds has shape {tuple(prompt_embeds.shape)}; expected "
                f"({rows}, L, {cfg.cross_attention_dim}) — one row per label, the unconditional (negative) prompt last",
                "prompt_embeds",
            )
        if self.sdxl and (pooled_embeds is None or pooled_embeds.dim() != 2 or pooled_embeds.shape[0] != rows):
            raise LasagnaError(
                f"an SDXL UNet needs pooled_embeds of shape ({rows}, P); got "
                f"{None if pooled_embeds is None else tuple(pooled_embeds.shape)}",
                "pooled_embeds",
            )
        # Buffers so .to(device, dtype) moves them with the networks; not saved (they are derived data).
        self.register_buffer("prompt_embeds", prompt_embeds.detach().clone(), persistent=False)
        pooled = pooled_embeds.detach().clone() if self.sdxl and pooled_embeds is not None else None
        self.register_buffer("pooled_embeds", pooled, persistent=False)
        # Model CPU offload (``_use``): a plain dict, so the active network is not registered as a submodule.
        self._offload = {"device": None if offload_device is None else torch.device(offload_device), "active": None}
        self.requires_grad_(False)
        self.eval()

    @property
    def controlnet(self) -> nn.Module | None:
        """The only ControlNet (None without one); several are ``controlnets``."""
        return self.controlnets[0] if len(self.controlnets) == 1 else None

    def _use(self, module: nn.Module) -> None:
        """Model CPU offload (diffusers' ``enable_model_cpu_offload``): the network about to run is moved to the
        execution device and the one that ran before it back to the CPU, so one large network at a time
        occupies the accelerator. Nothing happens without offload."""
        state = self._offload
        if state["device"] is None or state["active"] is module:
            return
        if state["active"] is not None:
            state["active"].to("cpu")
        module.to(state["device"])
        state["active"] = module

    # -- the space the denoiser works in --------------------------------------------------------
    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """x ∈ [0, 1] (B, 3, H, W) → latents (B, C, H/f, W/f) in x's dtype; differentiable."""
        if self.vae is None:
            return x * 2 - 1
        vae = self.vae
        self._use(vae)
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
        self._use(vae)
        shift = getattr(vae.config, "shift_factor", None) or 0.0
        x = vae.decode((z / vae.config.scaling_factor + shift).to(vae.dtype)).sample
        return ((x + 1) / 2).to(z.dtype)

    # -- the raw network ------------------------------------------------------------------------
    def _added_cond(self, idx: torch.Tensor, z: torch.Tensor) -> dict[str, torch.Tensor] | None:
        """SDXL's ``added_cond_kwargs``: the pooled prompt and the micro-conditioning ``time_ids``
        (original size, crop corner, target size: all the view's pixel size); None for SD 1.x/2.x."""
        if not self.sdxl:
            return None
        f = self.vae_scale_factor
        h, w = z.shape[2] * f, z.shape[3] * f
        ids = torch.tensor([h, w, *SDXL_CROP_TOP_LEFT, h, w], dtype=z.dtype, device=z.device)
        pooled = self.pooled_embeds[idx.to(self.pooled_embeds.device)].to(device=z.device, dtype=z.dtype)
        return {"text_embeds": pooled, "time_ids": ids.expand(z.shape[0], -1)}

    def _control_images(self, image: torch.Tensor | None, z: torch.Tensor) -> list[torch.Tensor]:
        """One conditioning image per ControlNet from ``image``: their channels concatenated, or one shared."""
        f, chans = self.vae_scale_factor, self.control_channels
        expected = (z.shape[0], sum(chans), z.shape[2] * f, z.shape[3] * f)
        if image is None:
            raise ConditionError(
                f"this prior has {len(chans)} ControlNet(s) and needs a conditioning image of shape {expected}; "
                "got None",
                "condition.image",
            )
        shared = len(set(chans)) == 1
        if tuple(image.shape) == expected:
            return list(image.split(list(chans), dim=1))
        if shared and tuple(image.shape) == (expected[0], chans[0], *expected[2:]):
            return [image] * len(chans)
        raise ConditionError(
            f"image has shape {tuple(image.shape)}; expected {expected}"
            + (f" (one image of {chans[0]} channels shared by every net also works)" if len(chans) > 1 else ""),
            "condition.image",
        )

    def _eps(
        self, z_t: torch.Tensor, t: torch.Tensor, label_idx: torch.Tensor, image: torch.Tensor | None
    ) -> torch.Tensor:
        dtype, dev = self.unet.dtype, z_t.device
        z = z_t.to(dtype)
        t = t.to(dev)
        enc = self.prompt_embeds[label_idx.to(self.prompt_embeds.device)].to(device=dev, dtype=dtype)  # (B, L, D)
        added = self._added_cond(label_idx, z)
        extra = {}
        if len(self.controlnets):
            down, mid = None, None
            for net, img, scale in zip(self.controlnets, self._control_images(image, z), self.conditioning_scales):
                self._use(net)
                d, m = net(
                    z,
                    t,
                    encoder_hidden_states=enc,
                    controlnet_cond=img.to(dtype),
                    conditioning_scale=scale,
                    added_cond_kwargs=added,
                    return_dict=False,
                )
                # MultiControlNetModel's rule: the nets' residuals are summed.
                down = list(d) if down is None else [a + b for a, b in zip(down, d)]
                mid = m if mid is None else mid + m
            extra = {"down_block_additional_residuals": down, "mid_block_additional_residual": mid}
        elif image is not None:
            raise ConditionError("this prior has no ControlNet; expected image=None", "condition.image")
        self._use(self.unet)
        out = self.unet(z, t, encoder_hidden_states=enc, added_cond_kwargs=added, return_dict=False, **extra)[0]
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
        controlnets: Sequence[str | os.PathLike] = (),
        controlnet: str | os.PathLike | None = None,
        conditioning_scale: float | Sequence[float] = 1.0,
        vocabulary: Sequence[str],
        prompt_template: str = DEFAULT_TEMPLATE,
        prompts: Mapping[str, str] | None = None,
        negative_prompt: str = "",
        device: str | torch.device = "cuda",
        dtype: torch.dtype | DtypeName | None = None,
        variant: str | None = None,
        latent: Literal["sample", "mean"] = "mean",
        cpu_offload: bool = False,
        attention_slicing: bool = False,
        channels_last: bool = False,
    ) -> DiffusersPrior:
        """Load a Stable-Diffusion folder (diffusers layout: SD 1.x/2.x, or SDXL with ``text_encoder_2/`` and
        ``tokenizer_2/``) and ControlNet folders from disk.

        Never touches the network (``local_files_only=True``). ``path`` must hold ``unet/``,
        ``scheduler/scheduler_config.json``, ``text_encoder/`` and ``tokenizer/``; ``vae/`` is optional
        (without it the UNet is taken to work on pixels). Weights are read in ``dtype`` (``"auto"``: float16
        on CUDA, float32 elsewhere) from the ``variant`` files (e.g. ``"fp16"``:
        ``diffusion_pytorch_model.fp16.safetensors``; a ControlNet without that variant is read from its plain
        files), not read in float32 and cast. ``cpu_offload`` keeps
        every network on the CPU until it runs (``_use``); ``attention_slicing`` computes attention in
        slices (less memory, a little slower); ``channels_last`` stores the UNet's and ControlNets'
        activations NHWC (faster convolutions on recent GPUs).
        """
        require_diffusers()
        with _quiet():
            return cls._from_local(
                path,
                controlnets=controlnets,
                controlnet=controlnet,
                conditioning_scale=conditioning_scale,
                vocabulary=vocabulary,
                prompt_template=prompt_template,
                prompts=prompts,
                negative_prompt=negative_prompt,
                device=device,
                dtype=dtype,
                variant=variant,
                latent=latent,
                cpu_offload=cpu_offload,
                attention_slicing=attention_slicing,
                channels_last=channels_last,
            )

    @classmethod
    def _from_local(
        cls,
        path,
        *,
        controlnets,
        controlnet,
        conditioning_scale,
        vocabulary,
        prompt_template,
        prompts,
        negative_prompt,
        device,
        dtype,
        variant,
        latent,
        cpu_offload,
        attention_slicing,
        channels_last,
    ) -> DiffusersPrior:
        from diffusers import AutoencoderKL, ControlNetModel, UNet2DConditionModel
        from transformers import CLIPTextModel, CLIPTextModelWithProjection, CLIPTokenizer

        root = Path(path)
        for sub in ("unet", "scheduler", "text_encoder", "tokenizer"):
            if not (root / sub).is_dir():
                raise LasagnaError(
                    f"missing folder {sub}/; expected a diffusers Stable-Diffusion folder (unet/ scheduler/ "
                    "text_encoder/ tokenizer/ [vae/] [text_encoder_2/ tokenizer_2/ for SDXL])",
                    str(root),
                )
        execution = torch.device(device)
        if cpu_offload and execution.type == "cpu":
            raise LasagnaError(
                "model CPU offload moves networks between the CPU and an accelerator; expected a cuda device "
                "(or no offload)",
                "cpu_offload",
            )
        dtype = resolve_dtype(dtype, execution)
        sched_path = root / "scheduler" / "scheduler_config.json"
        try:
            sched_cfg = json.loads(sched_path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise LasagnaError(f"cannot read the scheduler config ({exc})", str(sched_path)) from None
        index = _read_json(root / "model_index.json")
        sdxl = (root / "text_encoder_2").is_dir() and (root / "tokenizer_2").is_dir()
        weights = {"torch_dtype": dtype, "local_files_only": True}
        unet = _load(
            "unet",
            root / "unet",
            lambda: UNet2DConditionModel.from_pretrained(root / "unet", variant=variant, **weights),
        )
        vae = None
        if (root / "vae").is_dir():
            vae = _load(
                "vae",
                root / "vae",
                lambda: AutoencoderKL.from_pretrained(
                    root / "vae", variant=folder_variant(root / "vae", variant), **weights
                ),
            )
            if dtype == torch.float16 and getattr(vae.config, "force_upcast", False):
                vae = vae.float()  # the VAE's config says float16 overflows (SDXL's): run it in float32
        paths = [Path(p) for p in (*([controlnet] if controlnet is not None else []), *controlnets)]
        nets = [
            _load(
                "controlnet",
                p,
                lambda p=p: ControlNetModel.from_pretrained(p, variant=folder_variant(p, variant), **weights),
            )
            for p in paths
        ]
        # Text encoders run once, on the execution device, then are dropped (the embeddings are kept).
        text_kw = {("dtype" if _transformers_major() >= 5 else "torch_dtype"): dtype, "local_files_only": True}
        te_device = "cpu" if cpu_offload else execution
        tokenizer = _load("tokenizer", root / "tokenizer", lambda: CLIPTokenizer.from_pretrained(root / "tokenizer"))
        text_encoder = _load(
            "text_encoder",
            root / "text_encoder",
            lambda: CLIPTextModel.from_pretrained(
                root / "text_encoder", variant=folder_variant(root / "text_encoder", variant), **text_kw
            ),
        )
        tokenizer_2 = text_encoder_2 = None
        if sdxl:
            tokenizer_2 = _load(
                "tokenizer_2", root / "tokenizer_2", lambda: CLIPTokenizer.from_pretrained(root / "tokenizer_2")
            )
            text_encoder_2 = _load(
                "text_encoder_2",
                root / "text_encoder_2",
                lambda: CLIPTextModelWithProjection.from_pretrained(
                    root / "text_encoder_2", variant=folder_variant(root / "text_encoder_2", variant), **text_kw
                ),
            )
            text_encoder_2 = text_encoder_2.to(te_device).eval()
        for net in (unet, *nets):
            if channels_last:
                net.to(memory_format=torch.channels_last)
            if attention_slicing:
                net.set_attention_slice("auto")
        place = "cpu" if cpu_offload else execution
        prior = cls(
            unet.to(place),
            sched_cfg,
            vocabulary,
            prompt_template=prompt_template,
            prompts=prompts,
            negative_prompt=negative_prompt,
            text_encoder=text_encoder.to(te_device).eval(),
            tokenizer=tokenizer,
            text_encoder_2=text_encoder_2,
            tokenizer_2=tokenizer_2,
            force_zeros_for_empty_prompt=bool(index.get("force_zeros_for_empty_prompt", sdxl)),
            controlnet=[net.to(place) for net in nets],
            vae=vae.to(place) if vae is not None else None,
            latent=latent,
            conditioning_scale=conditioning_scale,
            offload_device=execution if cpu_offload else None,
        )
        if cpu_offload:  # the prompt embeddings live where the networks run
            prior.prompt_embeds = prior.prompt_embeds.to(execution)
            if prior.pooled_embeds is not None:
                prior.pooled_embeds = prior.pooled_embeds.to(execution)
        del text_encoder, text_encoder_2  # the prompts are encoded; the text encoders are not kept
        return prior


def require_diffusers() -> None:
    """A ``LasagnaError`` naming the extra to install when diffusers or transformers is not installed (a
    ModuleNotFoundError deep in a load would read as a bug)."""
    missing = missing_extra("diffusers")
    if missing is not None:
        raise LasagnaError(
            f"a diffusers prior needs the {missing} package, which is not installed; "
            f"expected the diffusers extra: {install_hint('diffusers')}",
            "prior",
        )


@contextlib.contextmanager
def _quiet():
    """diffusers' and transformers' loading chatter (progress bars, the advice to install accelerate) off while
    loading: the CLI's stderr carries one line per warning or error, and a library does not print."""
    from diffusers.utils import logging as dlog
    from transformers.utils import logging as tlog

    levels = (dlog.get_verbosity(), tlog.get_verbosity())
    bars = (dlog.is_progress_bar_enabled(), tlog.is_progress_bar_enabled())
    dlog.set_verbosity_error()
    tlog.set_verbosity_error()
    dlog.disable_progress_bar()
    tlog.disable_progress_bar()
    try:
        yield
    finally:
        dlog.set_verbosity(levels[0])
        tlog.set_verbosity(levels[1])
        if bars[0]:
            dlog.enable_progress_bar()
        if bars[1]:
            tlog.enable_progress_bar()


def _transformers_major() -> int:
    import transformers

    return int(transformers.__version__.split(".")[0])


def _read_json(path: Path) -> dict:
    """A JSON object as a dict; {} when absent, unreadable or not an object (model_index.json is optional)."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return doc if isinstance(doc, dict) else {}


def _load(what: str, where: Path, load):
    """``load()``, with diffusers'/transformers' failures (a missing file or variant, a bad config) as one line."""
    if not where.is_dir():
        raise LasagnaError(f"{what} folder does not exist; expected a folder written by save_pretrained", str(where))
    try:
        return load()
    except (OSError, ValueError, KeyError, TypeError) as exc:
        first = " ".join(str(exc).split())[:300]
        raise LasagnaError(
            f"cannot load the {what} ({first}); expected a folder written by save_pretrained", str(where)
        ) from None


def _weights_read(folder: Path, variant: str | None) -> list[Path]:
    """The weight files diffusers/transformers read in ``folder``: safetensors when there are any, of ``variant``
    (``name.<variant>.safetensors``, sharded ``name.<variant>-0000k-of-0000n``) or of no variant."""
    files = [f for f in folder.iterdir() if f.is_file() and f.suffix in WEIGHT_SUFFIXES]
    if any(f.suffix == ".safetensors" for f in files):
        files = [f for f in files if f.suffix == ".safetensors"]

    def variant_of(f: Path) -> str | None:
        parts = f.stem.split("-")[0].split(".")
        return parts[-1] if len(parts) > 1 else None

    return [f for f in files if variant_of(f) == variant]


def folder_variant(folder: Path, variant: str | None) -> str | None:
    """The variant a model folder is read in: ``variant`` when it has such files, else its plain weights —
    ``DiffusionPipeline.from_pretrained``'s fallback (a ControlNet from another repository, a text
    encoder published only in float32)."""
    return variant if folder.is_dir() and variant is not None and _weights_read(folder, variant) else None


def used_files(root: str | os.PathLike, variant: str | None = None, *, pipeline: bool = True) -> list[Path]:
    """Every file a load of ``root`` reads — weights (of ``variant``), configs, tokenizer files — sorted: what
    provenance hashes. ``pipeline``: ``root`` is a pipeline folder (its ``COMPONENTS`` sub-folders);
    otherwise one model's folder (a ControlNet)."""
    root = Path(root)
    folders = [root / c for c in COMPONENTS if (root / c).is_dir()] if pipeline else [root]
    out: list[Path] = []
    for folder in folders:
        # The UNet is read in the variant asked for (or fails); the other models fall back to plain weights.
        weights = set(_weights_read(folder, variant if folder.name == "unet" else folder_variant(folder, variant)))
        for f in sorted(folder.iterdir()):
            if f.is_file() and (f in weights or f.suffix not in WEIGHT_SUFFIXES):
                out.append(f)
    return out
