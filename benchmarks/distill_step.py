"""Per-step cost of each distillation loss on a UNetPrior, split into network passes and overhead.

    OMP_NUM_THREADS=1 python benchmarks/distill_step.py [--quick] [--device cpu|cuda] [--seconds S]
                      [--resolutions 32 64] [--batches 1 8 32] [--losses sds ...] [--markdown]

For every resolution (32², 64²) × batch (1, 8, 32) × loss (sds, lmc-sds, lmc-sds with fixed ε, dds,
nfsd, ms-sds with 4 DDIM steps) it times

* ``step``: one full loss evaluation on an image that requires grad, plus ``loss.backward()``;
* ``prior``: the raw network passes that loss needs, called directly (``prior._eps`` on inputs of
  the same batch composition: SDS 2B, LMC-SDS 2B (3B with fixed ε), DDS 4B, NFSD 3B, MS-SDS 4 × 2B),
  under inference mode;
* ``bhat``: the corrective's pass (LMC-SDS only), under no_grad;

and reports overhead = step − prior − bhat and ratio = step / (prior + bhat). The target is
ratio ≤ 1.25 (cond and uncond in one batched pass, b̂ only for LMC-SDS, nothing recomputed).
Because a difference of two noisy timings is itself noisy on a shared machine, it also times the
same step with a zero-cost prior (ε̂ = z_t) and b̂ = z: ``null_ms`` is the loss's own arithmetic
(sampling, noising, CFG, x̂₀, normalisation, injection, backward), and
ratio_null = (prior + bhat + null) / (prior + bhat) a low-noise estimate of the same ratio.
Priors and correctives have random weights (timing does not depend on them): UNetPrior with
channels (32, 64, 128), a conditioning image, v-prediction; Corrective with filters (32, 64, 128)
at 32² and (32, 64, 128, 256) at 64², seeing the condition.

Timings alternate step / prior / bhat measurements in rounds, so a change of load on a shared
machine hits all three alike: ``ratio`` is the median over rounds of step_i / (prior_i + bhat_i)
(paired, adjacent measurements). Absolute times are the best (minimum) of the rounds — other work
only ever adds time, so the minimum estimates the intrinsic cost (``timeit``'s advice) — with the
median step time beside them. Ends with one JSON line: {"benchmark": "distill_step",
"overhead_vs_network": worst ratio, "worst": its configuration, "step_ms": {loss: {"32x8": ms}},
"results": [...]}. ``--quick``: 32² only, batches 1 and 8, short budgets (< 60 s on 2 CPU cores).
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time

import torch

from lasagna.losses import DDS, LMCSDS, MSSDS, NFSD, SDS, identity_corrective
from lasagna.losses.corrective import Corrective, CorrectiveConfig
from lasagna.priors import Condition, NoiseSchedule, Prior
from lasagna.priors.unet import UNetConfig, UNetPrior

VOCAB = ("left", "right", "top")
MS_STEPS = 4
# loss name -> (branches per pass, passes, uses b̂)
PLAN = {
    "sds": (2, 1, False),
    "lmc-sds": (2, 1, True),
    "lmc-sds-fixed": (3, 1, True),
    "dds": (4, 1, False),
    "nfsd": (3, 1, False),
    "ms-sds": (2, MS_STEPS, False),
}


def build(resolution: int, device: str) -> tuple[UNetPrior, Corrective]:
    torch.manual_seed(0)
    prior = UNetPrior(UNetConfig(resolution=resolution, cond_channels=3, vocabulary=VOCAB)).to(device).eval()
    filters = (32, 64, 128) if resolution <= 32 else (32, 64, 128, 256)
    corr = (
        Corrective(
            CorrectiveConfig(
                resolution=resolution, filters=filters, sees_condition=True, cond_channels=3, vocabulary=VOCAB
            )
        )
        .to(device)
        .eval()
    )
    # the zero-initialised output layers would make b̂ = z and ε = 0 regardless of input; perturb them so
    # the timed arithmetic is the arithmetic of a trained network (it is the same either way)
    for p in list(prior.parameters()) + list(corr.parameters()):
        if torch.count_nonzero(p) == 0:
            p.data.normal_(0, 1e-2)
    return prior, corr


class NullPrior(Prior):
    """A prior whose network costs nothing (ε̂ = z_t): timing a loss with it isolates the loss's own work."""

    def __init__(self, resolution: int):
        super().__init__()
        self.schedule = NoiseSchedule()
        self.vocabulary = VOCAB
        self.sample_shape = (3, resolution, resolution)

    def _eps(self, z_t, t, label_idx, image):
        return z_t


def make_loss(name: str, corr):
    return {
        "sds": lambda: SDS(),
        "lmc-sds": lambda: LMCSDS(corr),
        "lmc-sds-fixed": lambda: LMCSDS(corr, fixed_eps=True),
        "dds": lambda: DDS(),
        "nfsd": lambda: NFSD(),
        "ms-sds": lambda: MSSDS(steps=MS_STEPS),
    }[name]()


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def clock(fn, device: str) -> float:
    sync(device)
    t = time.perf_counter()
    fn()
    sync(device)
    return time.perf_counter() - t


def measure(
    name: str, prior: UNetPrior, corr: Corrective, res: int, batch: int, device: str, seconds: float, min_rounds: int
) -> dict:
    branches, passes, uses_b = PLAN[name]
    g = torch.Generator(device="cpu").manual_seed(0)
    labels = [VOCAB[i % len(VOCAB)] for i in range(batch)]
    cimg = torch.rand(batch, 3, res, res, generator=g).to(device)
    cond = Condition(labels, image=cimg, negative=list(reversed(labels)))
    image = torch.rand(batch, 3, res, res, generator=g).to(device).requires_grad_(True)
    loss = make_loss(name, corr)

    def step():
        out = loss(image, prior, cond, 7.5, rng=g)
        out.loss.backward()
        image.grad = None

    # the raw passes, on inputs of the loss's batch composition
    n = branches * batch
    zz = torch.randn(n, 3, res, res, generator=g).to(device)
    tt = torch.randint(20, 980, (n,), generator=g).to(device)
    idx = torch.randint(0, len(VOCAB) + 1, (n,), generator=g).to(device)
    img = cimg.repeat(branches, 1, 1, 1)
    z1, t1, i1 = zz[:batch], tt[:batch], idx[:batch]

    def net():
        with torch.inference_mode():
            for _ in range(passes):
                prior._eps(zz, tt, idx, img)

    def bhat():
        with torch.no_grad():
            corr(z1, t1, cond_image=cimg, label_idx=i1)

    null_prior, null_loss = NullPrior(res).to(device), make_loss(name, identity_corrective)

    def null_step():
        out = null_loss(image, null_prior, cond, 7.5, rng=g)
        out.loss.backward()
        image.grad = None

    for f in (step, net, bhat, null_step):  # warm-up: allocator, first-call paths
        f()
    null_ms = min(clock(null_step, device) for _ in range(20)) * 1e3
    rounds = {"step": [], "prior": [], "bhat": []}
    start = time.perf_counter()
    while len(rounds["step"]) < min_rounds or time.perf_counter() - start < seconds:
        rounds["step"].append(clock(step, device))
        rounds["prior"].append(clock(net, device))
        if uses_b:
            rounds["bhat"].append(clock(bhat, device))
    best = {k: min(v) * 1e3 if v else 0.0 for k, v in rounds.items()}
    bh = rounds["bhat"] or [0.0] * len(rounds["step"])
    paired = [s / (p + b) for s, p, b in zip(rounds["step"], rounds["prior"], bh)]
    network = best["prior"] + best["bhat"]
    return {
        "loss": name,
        "resolution": res,
        "batch": batch,
        "step_ms": round(best["step"], 3),
        "step_median_ms": round(statistics.median(rounds["step"]) * 1e3, 3),
        "prior_ms": round(best["prior"], 3),
        "bhat_ms": round(best["bhat"], 3),
        "overhead_ms": round(best["step"] - network, 3),
        "ratio": round(statistics.median(paired), 4),
        "null_ms": round(null_ms, 3),
        "ratio_null": round((network + null_ms) / network, 4),
        "rounds": len(rounds["step"]),
    }


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="32² only, batches 1 and 8, short budgets (< 60 s)")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--seconds", type=float, default=None, help="time budget per cell (default 2.0, quick 0.8)")
    ap.add_argument("--markdown", action="store_true", help="also print a markdown table (for docs/BENCHMARKS.md)")
    ap.add_argument("--resolutions", type=int, nargs="+", default=None, help="default 32 64 (quick: 32)")
    ap.add_argument("--batches", type=int, nargs="+", default=None, help="default 1 8 32 (quick: 1 8)")
    ap.add_argument("--losses", nargs="+", choices=list(PLAN), default=list(PLAN))
    args = ap.parse_args(argv)
    resolutions = tuple(args.resolutions or ((32,) if args.quick else (32, 64)))
    batches = tuple(args.batches or ((1, 8) if args.quick else (1, 8, 32)))
    seconds = args.seconds if args.seconds is not None else (0.8 if args.quick else 2.0)
    min_rounds = 5 if args.quick else 3

    results = []
    for res in resolutions:
        prior, corr = build(res, args.device)
        for batch in batches:
            for name in args.losses:
                r = measure(name, prior, corr, res, batch, args.device, seconds, min_rounds)
                results.append(r)
                print(
                    f"{res:>3}² B={batch:<3} {name:<14} step {r['step_ms']:9.2f} ms  prior {r['prior_ms']:9.2f}  "
                    f"b̂ {r['bhat_ms']:7.2f}  overhead {r['overhead_ms']:7.2f}  ratio {r['ratio']:.3f}  "
                    f"null {r['null_ms']:6.2f} ms  ratio_null {r['ratio_null']:.3f}",
                    flush=True,
                )
    if args.markdown:
        print(
            "\n| loss | res | batch | step ms | prior ms | b̂ ms | overhead ms | step / network | null-prior ms | "
            "ratio_null |"
        )
        print("|---|---|---|---|---|---|---|---|---|---|")
        for r in results:
            print(
                f"| {r['loss']} | {r['resolution']}² | {r['batch']} | {r['step_ms']:.2f} | {r['prior_ms']:.2f} | "
                f"{r['bhat_ms']:.2f} | {r['overhead_ms']:.2f} | {r['ratio']:.3f} | {r['null_ms']:.2f} | "
                f"{r['ratio_null']:.3f} |"
            )
    worst = max(results, key=lambda r: r["ratio"])
    summary = {
        "benchmark": "distill_step",
        "device": args.device if args.device != "cpu" else f"cpu ({platform.processor() or platform.machine()})",
        "threads": torch.get_num_threads(),
        "quick": args.quick,
        "overhead_vs_network": worst["ratio"],
        "worst": {k: worst[k] for k in ("loss", "resolution", "batch")},
        "overhead_vs_network_null_prior": max(r["ratio_null"] for r in results),
        "step_ms": {
            name: {f"{r['resolution']}x{r['batch']}": r["step_ms"] for r in results if r["loss"] == name}
            for name in args.losses
        },
        "results": results,
    }
    print(json.dumps(summary))
    return summary


if __name__ == "__main__":
    main()
