"""A tour of Lasagna's Python API: build a stack from tensors, render it, save, export, reload.

    python examples/api_tour.py [OUT_DIR]        (default out/api_tour; runs in a few seconds)

The stack is the Lasagna paper's decomposition of an image: an albedo base, a shading layer that
*multiplies* it (one channel, range [0, 2]: values above 1 brighten), and a colour layer laid on
with the alpha-linear ("normal") blend.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

import lasagna

H, W = 96, 128


def albedo() -> torch.Tensor:
    """A checkerboard of two colours, (3, H, W) in [0, 1]."""
    y, x = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    check = ((x // 16 + y // 16) % 2).float()
    a, b = torch.tensor([0.8, 0.6, 0.4]), torch.tensor([0.3, 0.5, 0.7])
    return a[:, None, None] * check + b[:, None, None] * (1 - check)


def shading() -> torch.Tensor:
    """A lit sphere's Lambert shading, (1, H, W): 2·max(n·l, 0) + 0.2 inside, 1 outside, in [0, 2]."""
    y, x = torch.meshgrid(torch.linspace(-1, 1, H), torch.linspace(-W / H, W / H, W), indexing="ij")
    r2 = (x / 0.8) ** 2 + (y / 0.8) ** 2
    nz = torch.sqrt((1 - r2).clamp_min(0))
    light = torch.tensor([-0.5, -0.5, 0.707])
    lambert = (light[0] * x / 0.8 + light[1] * y / 0.8 + light[2] * nz).clamp_min(0)
    return torch.where(r2 < 1, (1.8 * lambert + 0.2).clamp(0, 2), torch.ones_like(x))[None]


def main(out: Path) -> None:
    # 1. Build: the base sets the canvas; layers go on top, bottom to top.
    stack = lasagna.from_image(albedo(), id="albedo", name="Albedo")
    stack.add_layer("shade", shading(), name="Shading", blend="multiply", range=(0.0, 2.0))
    patch = torch.zeros(4, 32, 48)
    patch[0], patch[3] = 1.0, 0.5  # red at alpha 0.5 (RGBA: the 4th channel is alpha)
    stack.add_layer("paint", patch, name="Red paint", blend="normal", offset=(72, 56), opacity=0.8)
    print(stack)

    # 2. Render: what was composed and what was skipped, and why.
    result = lasagna.render(stack)
    print(f"rendered {tuple(result.image.shape)}; evaluated {result.evaluated}; skipped {result.skipped}")

    # 3. Save the stack folder (16-bit PNG for the [0, 2] multiplier) with its composite, export ORA.
    written = lasagna.save(stack, out / "stack", composite=True)
    ora = lasagna.export_ora(stack, out / "tour.ora")
    print(f"wrote {written}, {written.parent / 'composite.png'} and {ora}")

    # 4. Reload and check: the [0, 2] multiplier (16-bit) survives within half a step of 2/65535;
    #    the [0, 1] albedo and paint are stored in 8 bits (±0.5/255, the albedo's error times a
    #    shading of up to 2), so the composite agrees within 1.5/255.
    again = lasagna.load(out / "stack")
    err = (again.tensors["shade"].color - stack.tensors["shade"].color).abs().max().item()
    same = (lasagna.render(again).image - result.image).abs().max().item()
    print(f"reloaded: shading max error {err:.2e} (bound {2 / 65535 / 2:.2e}); composite max difference {same:.2e}")
    assert err <= 2 / 65535 / 2 + 1e-6 and same <= 1.5 / 255

    # 5. Gradients flow from the composite to a layer (what learned layers are trained through).
    shade = stack.tensors["shade"].color.clone().requires_grad_(True)
    stack.set_pixels("shade", shade)
    lasagna.render(stack).image.mean().backward()
    print(f"d mean(composite) / d shading: {shade.grad.abs().sum().item():.4f} (nonzero: gradients flow)")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("out/api_tour"))
