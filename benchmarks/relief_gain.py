"""Is the estimators' relief too shallow? Their heights scaled by a gain, measured on select (issue #24's diagnostic).

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/relief_gain.py                   # gains 1 1.5 2 3 4, ~12 min
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/relief_gain.py --gains 1 2 --photos

A regression to the mean makes a height estimator shallow where it is unsure; photographs' swings (the relight's
light moving across the image) grow with the relief. So a gain g on every estimated height (the normals of g·h:
steeper slopes, the same outlines; the dome prior untouched) is measured where choices are made, on `select`'s 16
scenes at 64² (dB over the best constant or the unchanged input, all / object pixels, and the wall leak):

* the shading preset's surface (`surface-albedo-32`, domes 0.25 / 0.25: `benchmarks/surface.py`'s row),
* the relight's surface route (`surface-lit-closeup-32`, domes 0.15 / 0.5, its own source light),
* the default relight (`lasagna.edit(image, "relight", light)`: the free ratio started from that surface, planar
  lock, ω 1: `benchmarks/relight_sweep.py`'s "default" row, composite PSNR against the truth),
* with ``--photos``, the default's swing on the photograph selection set (`benchmarks/photo_swing.py`).

The gain is applied to ``SurfaceEstimator.outputs`` for the run (a diagnostic, not a preset field: no estimator
ships with one). Ends with one JSON line: per gain, each row.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import photo_swing  # noqa: E402
import relight_sweep  # noqa: E402
import surface  # noqa: E402
from _common import machine_info, print_json_line  # noqa: E402

from lasagna.generators.surface import SurfaceEstimator, SurfaceOutputs  # noqa: E402

LAYERS = ROOT / "layers"


@contextlib.contextmanager
def relief_gain(gain: float):
    """Every height-field estimator's heights times ``gain`` inside the block (normals heads untouched)."""
    outputs = SurfaceEstimator.outputs

    def scaled(self, image):
        out = outputs(self, image)
        if self.config.output != "height":
            return out
        return SurfaceOutputs(out.surface * gain, out.shading, out.silhouette)

    SurfaceEstimator.outputs = scaled
    try:
        yield
    finally:
        SurfaceEstimator.outputs = outputs


def last_json(main, argv: list[str]) -> dict:
    """Run a benchmark's ``main(argv)`` quietly; its closing JSON line and every row it printed before."""
    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        main(argv)
    lines = []
    for line in buffer.getvalue().splitlines():
        with contextlib.suppress(json.JSONDecodeError):  # progress lines that are not JSON (photo_swing's rows)
            lines.append(json.loads(line))
    return {"last": lines[-1], "rows": lines[:-1]}


def measure(gain: float, photos: bool) -> dict:
    out: dict = {"gain": gain}
    with relief_gain(gain):
        for kind, folder, dome in (
            ("albedo", LAYERS / "surface-albedo-32", "0.25,0.25"),
            ("lit", LAYERS / "surface-lit-closeup-32", "0.15,0.5"),
        ):
            argv = ["--splits", "select", "--sizes", "64", f"--{kind}", str(folder), "--dome", dome]
            run = last_json(surface.main, [*argv, "--photos", str(ROOT / "none")])
            for r in run["rows"]:
                row = r.get("shading") or r.get("relight") or {}
                if str(row.get("method", "")).startswith(f"surface estimator ({kind})") and "true source" not in str(
                    row["method"]
                ):
                    out[f"{kind}_surface_db"] = [row["gain_db"], row["gain_obj_db"]]
                if "leak" in r:
                    out[f"{kind}_leak_db"] = r["leak"][f"leak_db_{kind}"]
        default = last_json(relight_sweep.main, ["--split", "select", "--size", "64", "--only", "default"])
        row = default["last"]["rows"][0]
        out["relight_default_psnr"] = [row["composite_psnr"], row["object_psnr"]]
        if photos:
            swing = last_json(photo_swing.main, ["--label", f"gain {gain:g}"])["last"]
            out["photo_select"] = {k: swing[k] for k in ("swing_mean", "wrong_signs", "below_0.10")}
    print(json.dumps(out), file=sys.stderr, flush=True)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--gains", nargs="+", type=float, default=[1.0, 1.5, 2.0, 3.0, 4.0])
    p.add_argument("--photos", action="store_true", help="also the default's swings on examples/photos/select")
    args = p.parse_args(argv)
    rows = [measure(g, args.photos) for g in args.gains]
    record = {"benchmark": "relief_gain", "split": "select", "size": 64, "rows": rows}
    print_json_line({**record, "machine": machine_info()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
