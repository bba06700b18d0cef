"""Score-distillation losses behind one interface (base.py), sharing one core (core.py).

=========  ==========================================  =========================================
name       class                                       gradient in the prior's space (× w(t))
=========  ==========================================  =========================================
sds        ``SDS`` (sds.py)                            ε̂^ω − ε = L_cond + L_proj
lmc-sds    ``LMCSDS`` (lmc_sds.py)                     (L_cond + L_lmc)/ω, L_lmc = b̃ − ẑ_t
dds        ``DDS`` (dds.py)                            ε̂^ω(z_t, y) − ε̂^ω(ẑ_t, ŷ)
nfsd       ``NFSD`` (nfsd.py)                          ω δ_C + δ_D
ms-sds     ``MSSDS`` (ms_sds.py)                       √ᾱ/√(1−ᾱ)·(z − x̂₀ after K DDIM steps)
=========  ==========================================  =========================================

The manifold corrective b̂ lives beside lmc_sds (corrective.py, spectral.py); its trainers are
``lasagna.training.corrective``.
"""

from lasagna.losses.base import LossOptions, LossOutput, ScoreLoss, Terms, available_losses, get_loss, register_loss
from lasagna.losses.core import Diagnostics, TimestepOptions, TimestepSampler, cfg, inject, weight
from lasagna.losses.dds import DDS
from lasagna.losses.lmc_sds import LMCSDS, LMCSDSOptions, identity_corrective, normalize_like
from lasagna.losses.ms_sds import MSSDS, MSSDSOptions
from lasagna.losses.nfsd import NFSD, NFSDOptions
from lasagna.losses.sds import SDS, SDSOptions

__all__ = [
    "DDS",
    "Diagnostics",
    "LMCSDS",
    "LMCSDSOptions",
    "LossOptions",
    "LossOutput",
    "MSSDS",
    "MSSDSOptions",
    "NFSD",
    "NFSDOptions",
    "SDS",
    "SDSOptions",
    "ScoreLoss",
    "Terms",
    "TimestepOptions",
    "TimestepSampler",
    "available_losses",
    "cfg",
    "get_loss",
    "identity_corrective",
    "inject",
    "normalize_like",
    "register_loss",
    "weight",
]
