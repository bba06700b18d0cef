"""A first probe of learned shading against the truth (not yet issue #5's full benchmark).

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/distill_probe.py     (~70 s)

16 `heldout` scenes at 32², base = albedo, a free per-pixel shading layer distilled for 150 steps from
the bundled `relight-32` prior (with `relight-32-bhat` for LMC-SDS), SDS and LMC-SDS at ω = 1 and 7.5;
shading PSNR against the true shading over all pixels and over object pixels, composite PSNR against
the true relit image, beside the best constant shading per image. Prints one JSON line.
"""
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import time, torch
torch.set_num_threads(2)
rows = []
from lasagna.catalogue import load_preset, load_prior, load_corrective
from lasagna.distill import distill_image
from lasagna.world import generate
pre = load_preset("shading"); prior = load_prior("relight-32"); corr = load_corrective("relight-32-bhat")
sc = generate("heldout", 16, 7, 32)
def psnr(a, b, m=None):
    d = (a - b) ** 2
    mse = d.mean() if m is None else (d * m).sum() / m.sum().clamp_min(1)
    return float(-10 * torch.log10(mse))
true = sc.shading
const = true.mean(dim=(1, 2, 3), keepdim=True).expand_as(true)  # best constant per image (least squares)
mask = sc.mask
rows.append({"method": "best-constant", "shading": round(psnr(const, true), 2), "objects": round(psnr(const, true, mask), 2)})
print(rows[-1], flush=True)
for loss in ("sds", "lmc-sds"):
    for w in (1.0, 7.5):
        t = time.time()
        r = distill_image(sc.albedo, pre, prior, corr if loss == "lmc-sds" else None, condition=sc.label, loss=loss,
                          guidance=w, steps=150, seed=0, early_stop=False)
        y = r.layer[:, :1]
        rows.append({"method": loss, "omega": w, "shading": round(psnr(y, true), 2), "objects": round(psnr(y, true, mask), 2),
                     "composite": round(psnr(r.composite, sc.image), 2), "seconds": round(time.time() - t, 1)})
        print(rows[-1], flush=True)
print(json.dumps({"rows": rows}))
