"""Numerics in one place: named epsilons with their reasons, and the reduction dtype (upcasts).

Every tolerance the package uses lives here, so a reader can audit them together.
"""

from __future__ import annotations

import torch

# Divisions by a standard deviation (L_k of the LMC-SDS paper, eq. 10): a constant image has
# sigma = 0. 1e-6 is far below the sigma of any image worth normalising (one 8-bit step is 3.9e-3)
# and far above float32's tiny (1.2e-38), so the quotient stays finite in float32 and bfloat16.
STD_EPS = 1e-6

# Divisions by (1 - alpha_bar) and alpha_bar near t = 0 and t = 1 of a diffusion schedule.
SCHEDULE_EPS = 1e-8

# Colour-dodge export of a multiplier y > 1 uses d = 1 - 1/y; keep 1 - d >= DODGE_EPS so the
# written layer is finite even for y = +inf-like outliers (clamped earlier to the layer's range).
DODGE_EPS = 1.0 / 65535.0

# ClipColor of W3C Compositing Level 1 (the non-separable blends) divides by L − min(C) and max(C) − L,
# which vanish for a gray (all channels equal). The spec leaves 0/0 there; the denominators are kept
# >= CLIP_COLOR_EPS instead. 1e-6 is above the float32 rounding of Lum(C) = 0.3R + 0.59G + 0.11B (a few
# ulp of 1, ~2e-7), so a gray is never divided by rounding noise, and far below one 16-bit step: a
# guarded division only pulls an almost-gray colour (|C − L| of the same order) towards its luminosity.
CLIP_COLOR_EPS = 1e-6

# Hard mix's tie Cb + Cs = 1 (Photoshop answers 1 only where Cb > 1/2) is a fact of 8-bit codes: a + b = 255. Our
# values arrive as float32 code/255 (then perhaps float64), whose sum is 1 only to a few float32 ulps; a sum
# within HARD_MIX_TIE_EPS of 1 is that tie. 2^-20 is far above those roundings and far below half a 16-bit code
# (1/131070), so no two distinct codes are confused.
HARD_MIX_TIE_EPS = 2.0**-20

# Unpremultiplying a group's colour, C = c / α (W3C Compositing Level 1, section 5.1): where α = 0, c = 0 as
# well and the spec leaves 0/0. Dividing by max(α, UNPREMULTIPLY_EPS) gives 0 there; where 0 < α < eps the
# quotient is off by at most a factor, but every use weights it by α again (the group's alpha, αb·B(Cb, Cs)),
# so its contribution stays below eps · |C|. 1e-12 is far below one 16-bit step of alpha (1.5e-5) and far
# above float32's tiny (1.2e-38); the gradient −c/α² it leaves is bounded by |C|/α, times that same α.
UNPREMULTIPLY_EPS = 1e-12

# Adjustments (compose/adjust.py): a power t^(1/γ) of a tone curve has an infinite slope at t = 0 for γ > 1, and a
# few divisions (a gray's HSL saturation, a flat interpolation interval) vanish. Bases and divisors are kept >=
# ADJUST_POW_EPS: 1e-12 is far below one 16-bit step (1.5e-5; (1e-12)^(1/9.99) = 0.063 is still only reached at
# t = 1e-12, never at a code) and far above float32's tiny, so values and gradients stay finite.
ADJUST_POW_EPS = 1e-12

# Logit of a value in [0, 1] (inverting y = lo + (hi - lo) * sigmoid(x)): clamp to
# [LOGIT_EPS, 1 - LOGIT_EPS] so an exact 0 or 1 maps to a large finite logit (+-13.8).
LOGIT_EPS = 1e-6


def reduction_dtype(dtype: torch.dtype) -> torch.dtype:
    """Reductions (means, norms, std) of half-precision tensors run in float32."""
    return torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype


# Saving a layer checks that its values lie in its range [lo, hi]. Values within this fraction of
# the range's width outside it are float32 rounding of values on the boundary (y = lo + (hi - lo)·v
# computed in float32), not content, and are saved as the boundary. 1e-6 is 1/15 of a 16-bit step.
RANGE_SAVE_TOLERANCE = 1e-6

# A generator's output squashed by a sigmoid cannot reach a range boundary; when the identity edit
# lies on one (an alpha of 0, a light of 0) and a sigmoid is asked for anyway, the head starts at
# logit ∓IDENTITY_LOGIT: sigmoid(−12) = 6.1e-6 of the range's width, below the 1e-5 at which a first
# composite counts as the input (half a 16-bit step is 7.6e-6) and far from float32's resolution.
IDENTITY_LOGIT = 12.0

# The spectral corrective's least-squares gain Σ Ẑ·conj Z / Σ |Z|² (lasagna.losses.spectral): a frequency
# no fitting image excites (Σ |Z|² below this) keeps the identity gain instead of 0/0. Images in [−1, 1]
# have |Z|² of order 1e2–1e5 per frequency and image, so only exact zeros fall under it.
SPECTRAL_POWER_FLOOR = 1e-8
