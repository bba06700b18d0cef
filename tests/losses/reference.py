"""Independent float64 references for the distillation tests: numpy only, nothing from ``lasagna``.

Written from the formulas, not from the package's code:
* the DDPM linear schedule (Ho et al. 2020): β_t = linspace(1e−4, 0.02, T), ᾱ_t = Π (1 − β_s);
* Gaussian (mixture) posteriors by direct linear algebra (np.linalg.solve / slogdet on the full
  covariance, no eigenbasis): E[ε | z_t] = Σ_k r_k √(1 − ᾱ) C_k⁻¹ (z_t − √ᾱ μ_k),
  C_k = ᾱ Σ_k + (1 − ᾱ) I, r_k ∝ w_k N(z_t; √ᾱ μ_k, C_k);
* the distribution of integer timesteps produced by t ~ U(t_min, t_max), index = round(t (T − 1));
* the guided-SDS fixed point (derivation in ``sds_fixed_point``).
"""

from __future__ import annotations

import numpy as np

T = 1000


def alpha_bar(num_steps: int = T, beta_start: float = 1e-4, beta_end: float = 0.02) -> np.ndarray:
    betas = np.linspace(beta_start, beta_end, num_steps, dtype=np.float64)
    return np.cumprod(1.0 - betas)


def as_matrix(cov, dim: int) -> np.ndarray:
    cov = np.asarray(cov, dtype=np.float64)
    if cov.ndim == 2:
        return cov
    return np.diag(np.broadcast_to(cov.reshape(-1), (dim,)))


def mixture_eps_x0(
    z_t: np.ndarray, ab: float, comps: list[tuple[float, np.ndarray, np.ndarray]]
) -> tuple[np.ndarray, np.ndarray]:
    """E[ε | z_t] and E[x | z_t] for one flat z_t (D,) under Σ_k w_k N(μ_k, Σ_k)."""
    d = z_t.shape[0]
    logs, eps, x0 = [], [], []
    for w, mu, cov in comps:
        S = as_matrix(cov, d)
        C = ab * S + (1 - ab) * np.eye(d)
        r = z_t - np.sqrt(ab) * mu
        sol = np.linalg.solve(C, r)
        _, logdet = np.linalg.slogdet(C)
        logs.append(np.log(w) - 0.5 * (r @ sol + logdet + d * np.log(2 * np.pi)))
        eps.append(np.sqrt(1 - ab) * sol)
        x0.append(mu + np.sqrt(ab) * S @ sol)
    logs = np.array(logs)
    resp = np.exp(logs - logs.max())
    resp /= resp.sum()
    return (resp[:, None] * np.array(eps)).sum(0), (resp[:, None] * np.array(x0)).sum(0)


def batch_eps(z_t: np.ndarray, ab: np.ndarray, comps_per_row: list) -> np.ndarray:
    """E[ε | z_t] for a batch (B, ...) with per-row ᾱ and per-row component lists."""
    flat = z_t.reshape(z_t.shape[0], -1)
    out = np.stack([mixture_eps_x0(flat[i], float(ab[i]), comps_per_row[i])[0] for i in range(flat.shape[0])])
    return out.reshape(z_t.shape)


def batch_x0(z_t: np.ndarray, ab: np.ndarray, comps_per_row: list) -> np.ndarray:
    flat = z_t.reshape(z_t.shape[0], -1)
    out = np.stack([mixture_eps_x0(flat[i], float(ab[i]), comps_per_row[i])[1] for i in range(flat.shape[0])])
    return out.reshape(z_t.shape)


def expected_x0_single(z: np.ndarray, ab: float, mu: np.ndarray, cov) -> np.ndarray:
    """E_ε[E[x | √ᾱ z + √(1−ᾱ) ε]] for one Gaussian: E[x|z_t] is affine in z_t, so plug in E[z_t] = √ᾱ z."""
    d = z.shape[0]
    S = as_matrix(cov, d)
    C = ab * S + (1 - ab) * np.eye(d)
    return mu + ab * S @ np.linalg.solve(C, z - mu)


def timestep_probabilities(t_min: float = 0.02, t_max: float = 0.98, num_steps: int = T) -> np.ndarray:
    """P(index = k) for u ~ U(t_min, t_max), index = round(u (T − 1)): the overlap of each rounding cell
    [(k − ½)/(T − 1), (k + ½)/(T − 1)) with [t_min, t_max], divided by t_max − t_min."""
    k = np.arange(num_steps, dtype=np.float64)
    lo = np.maximum((k - 0.5) / (num_steps - 1), t_min)
    hi = np.minimum((k + 0.5) / (num_steps - 1), t_max)
    return np.clip(hi - lo, 0.0, None) / (t_max - t_min)


def sds_fixed_point(
    omega: float,
    mu_c: np.ndarray,
    var_c: np.ndarray,
    mu_u: np.ndarray,
    var_u: np.ndarray,
    weighting: str = "1-alpha_bar",
    t_min: float = 0.02,
    t_max: float = 0.98,
) -> tuple[np.ndarray, np.ndarray]:
    """The z where the expected guided SDS gradient vanishes, for diagonal Gaussians (per dimension).

    With ε_b(z_t) = √(1−ᾱ) (z_t − √ᾱ μ_b)/c_b, c_b = ᾱ σ_b² + 1 − ᾱ, and E_ε[z_t] = √ᾱ z:
        E_ε[ε_b] = √(ᾱ(1−ᾱ)) (z − μ_b)/c_b,   E_ε[ε] = 0, so
        E_{t,ε}[g] = Σ_t p(t) w(t) √(ᾱ(1−ᾱ)) [ω (z − μ_c)/c_c + (1 − ω)(z − μ_u)/c_u] = a z − b
    with a = Σ_t p w √(ᾱ(1−ᾱ)) [ω/c_c + (1−ω)/c_u] and b = Σ_t p w √(ᾱ(1−ᾱ)) [ω μ_c/c_c + (1−ω) μ_u/c_u].
    The fixed point is z* = b/a; it attracts gradient descent iff a > 0 (true when σ_u ≥ σ_c for
    ω ≥ 1, and always for 0 ≤ ω ≤ 1). For small t only, c → σ² and z* is the mode of
    p_c^ω p_u^(1−ω); over a range of t it is that mode's t-averaged version. Returns (z*, a).
    """
    ab = alpha_bar()
    p = timestep_probabilities(t_min, t_max)
    w = {"uniform": np.ones_like(ab), "1-alpha_bar": 1 - ab, "sqrt_alpha_bar(1-alpha_bar)": np.sqrt(ab) * (1 - ab)}[
        weighting
    ]
    k = p * w * np.sqrt(ab * (1 - ab))  # (T,)
    c_c = ab[:, None] * var_c[None] + (1 - ab[:, None])
    c_u = ab[:, None] * var_u[None] + (1 - ab[:, None])
    a = (k[:, None] * (omega / c_c + (1 - omega) / c_u)).sum(0)
    b = (k[:, None] * (omega * mu_c[None] / c_c + (1 - omega) * mu_u[None] / c_u)).sum(0)
    return b / a, a
