"""Hostile-input benchmark (issue #16): bombs refused, memory bounded, nothing left behind. Plain script; ends
with one JSON line.

    python benchmarks/hostile.py              # every section (~2 min; the 8192² stack takes most of it)
    python benchmarks/hostile.py --quick      # 2048² instead of 8192², fewer kill tries
    python benchmarks/hostile.py --fuzz N     # also N fuzzed inputs per family through tests/fuzz (slow)

Every measured command runs as its own process through ``lasagna.cli.main`` with a small wrapper that
reports its peak RSS (VmHWM) and wall time from the start of the interpreter's work, imports included (a
refusal that needs no torch never loads it). The composite section's *baseline in the same run* is the
interpreter with torch and the I/O tier imported doing nothing, so its "delta" is what the work cost.

Sections and targets (docs/BENCHMARKS.md#hostile-input):
- ``composite``: peak memory of a no-grad ``lasagna composite`` of an 8192² stack (an RGB base and a
  one-channel multiply layer, photo-like noise so the PNGs are not trivially compressible) against
  1.5 × (float32 output + decoded inputs); and the same render written the old way (the whole canvas as
  float64 codes, then ``encode_png``) as the baseline.
- ``bombs``: each known bomb refused (exit 2, one line) in ≤ 2 s and ≤ 500 MB.
- ``kill``: ``lasagna edit`` killed with SIGKILL at random moments, then run again: temporaries left.
- ``fuzz``: tests/fuzz/test_hostile.py's slow cases, internal errors counted (0 is the target).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np
from PIL import Image

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
from _common import machine_info, print_json_line  # noqa: E402

# Peak RSS is VmHWM (reset by exec), not ru_maxrss, which a child inherits from the process that forked it.
PEAK = "int([l for l in open('/proc/self/status') if l.startswith('VmHWM')][0].split()[1])"
WRAPPER = f"""
import sys, time
t0 = time.perf_counter()
from lasagna.cli import main  # what a user runs: torch is imported only by what the command needs
rc = main(sys.argv[1:]) if len(sys.argv) > 1 else 0
sys.stderr.write("@@%d %.3f\\n" % ({PEAK}, time.perf_counter() - t0))
sys.exit(rc)
"""
# The baseline of the composite section: the interpreter with torch and the I/O tier imported, doing nothing.
BASELINE = f"""
import sys
import torch, lasagna.io.stack
sys.stderr.write("@@%d 0\\n" % {PEAK})
"""

MB = 2**20


def run_cli(*argv: str, cwd: Path, timeout: float = 120, program: str = WRAPPER) -> dict:
    """Run ``lasagna argv`` in a fresh process: exit status, stderr lines (without the report), peak MB, s."""
    env = dict(os.environ, OMP_NUM_THREADS="1")
    t0 = time.perf_counter()
    try:
        p = subprocess.run(
            [sys.executable, "-c", program, *argv], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env
        )
    except subprocess.TimeoutExpired:
        return {"rc": None, "stderr": ["timeout"], "peak_mb": None, "seconds": timeout, "hung": True}
    wall = time.perf_counter() - t0
    lines = [line for line in p.stderr.splitlines() if not line.startswith("@@")]
    report = [line for line in p.stderr.splitlines() if line.startswith("@@")]
    peak = int(report[-1][2:].split()[0]) / 1024 if report else None
    return {"rc": p.returncode, "stderr": lines, "peak_mb": peak, "seconds": round(wall, 2)}


# ---- fixtures -------------------------------------------------------------------------------------


def write_doc(folder: Path, width: int, height: int, layers: list[dict]) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    doc = {"format": "lasagna.stack", "version": 1, "canvas": {"width": width, "height": height}, "layers": layers}
    (folder / "stack.json").write_text(json.dumps(doc))
    return folder


def noise_png(path: Path, side: int, mode: str, seed: int) -> None:
    """A photo-like PNG (smooth noise plus grain), written band by band to bound this script's memory."""
    rng = np.random.default_rng(seed)
    channels = 3 if mode == "RGB" else 1
    coarse = rng.random((channels, side // 64 + 2, side // 64 + 2)).astype(np.float32)
    img = Image.new(mode, (side, side))
    band = 512
    for y in range(0, side, band):
        ys = (np.arange(y, min(side, y + band)) / 64.0)[:, None]
        xs = (np.arange(side) / 64.0)[None, :]
        y0, x0 = ys.astype(int), xs.astype(int)
        fy, fx = ys - y0, xs - x0
        out = []
        for c in range(channels):
            g = coarse[c]
            v = (g[y0, x0] * (1 - fy) + g[y0 + 1, x0] * fy) * (1 - fx) + (
                g[y0, x0 + 1] * (1 - fy) + g[y0 + 1, x0 + 1] * fy
            ) * fx
            v = v + rng.normal(0, 0.03, v.shape)
            out.append(np.clip(v * 255, 0, 255).astype(np.uint8))
        arr = np.stack(out, -1) if channels == 3 else out[0]
        img.paste(Image.fromarray(arr), (0, y))
    img.save(path, compress_level=1)


def big_stack(folder: Path, side: int) -> Path:
    (folder / "layers").mkdir(parents=True, exist_ok=True)
    if not (folder / "layers" / "shade.png").exists():
        noise_png(folder / "layers" / "base.png", side, "RGB", 1)
        noise_png(folder / "layers" / "shade.png", side, "L", 2)
    return write_doc(
        folder,
        side,
        side,
        [
            {"id": "base", "kind": "pixels", "source": "layers/base.png"},
            {"id": "shade", "kind": "pixels", "source": "layers/shade.png", "blend": "multiply", "range": [0, 2]},
        ],
    )


OLD_WRITE = f"""
import sys, torch
from lasagna.io.stack import load_stack
from lasagna.io.render import render_stack
from lasagna.io.png import write_png
r = render_stack(load_stack(sys.argv[1]))
codes = (r.image.to(torch.float64).clamp(0, 1) * 255).round().to(torch.uint8)  # the pre-#16 write_composite
write_png(sys.argv[2], codes.double() / 255.0)
sys.stderr.write("@@%d 0\\n" % {PEAK})
"""


def section_composite(work: Path, side: int) -> dict:
    from lasagna.io.png import decode_bytes, read_png_header

    stack = big_stack(work / f"big{side}", side)
    base = run_cli(cwd=work, program=BASELINE)  # torch and the I/O tier imported, nothing done
    new = run_cli("composite", str(stack), "-o", str(work / "out_new.png"), cwd=work, timeout=600)
    env = dict(os.environ, OMP_NUM_THREADS="1")
    p = subprocess.run(
        [sys.executable, "-c", OLD_WRITE, str(stack), str(work / "out_old.png")],
        capture_output=True,
        text=True,
        env=env,
    )
    old_peak = int([line for line in p.stderr.splitlines() if line.startswith("@@")][-1][2:].split()[0]) / 1024
    same = np.array_equal(np.asarray(Image.open(work / "out_new.png")), np.asarray(Image.open(work / "out_old.png")))
    output_mb = side * side * 3 * 4 / MB
    inputs_mb = sum(decode_bytes(read_png_header(stack / "layers" / n))[0] for n in ("base.png", "shade.png")) / MB
    delta = new["peak_mb"] - base["peak_mb"]
    return {
        "side": side,
        "baseline_peak_mb": round(base["peak_mb"]),
        "peak_mb": round(new["peak_mb"]),
        "peak_delta_mb": round(delta),
        "old_write_peak_mb": round(old_peak),
        "output_mb": round(output_mb),
        "inputs_mb": round(inputs_mb),
        "ratio": round(delta / (output_mb + inputs_mb), 3),
        "seconds": new["seconds"],
        "rc": new["rc"],
        "same_pixels_as_old_write": bool(same),
    }


def make_bombs(work: Path) -> dict[str, list[str]]:
    """Each bomb's command line (files made here)."""
    b = work / "bombs"
    (b / "png/layers").mkdir(parents=True, exist_ok=True)
    big = b / "png/layers/big.png"
    if not big.exists():
        Image.new("RGB", (16384, 16384)).save(big)
    Image.new("RGB", (8, 8)).save(b / "png/layers/base.png")
    write_doc(
        b / "png",
        8,
        8,
        [
            {"id": "base", "kind": "pixels", "source": "layers/base.png"},
            {"id": "big", "kind": "pixels", "source": "layers/big.png"},
        ],
    )
    write_doc(b / "solid", 32768, 32768, [{"id": "s", "kind": "solid", "color": [0.5, 0.2, 0.1]}])
    (b / "deep").mkdir(exist_ok=True)
    (b / "deep/stack.json").write_text("[" * 100000)
    (b / "bigint").mkdir(exist_ok=True)
    (b / "bigint/stack.json").write_text('{"format": "lasagna.stack", "version": ' + "9" * 5000 + "}")
    (b / "huge").mkdir(exist_ok=True)
    with open(b / "huge/stack.json", "wb") as fh:  # 200 MB, sparse: refused from its size
        fh.truncate(200 * MB)

    def png_bytes(side: int) -> bytes:
        import io

        buf = io.BytesIO()
        Image.new("RGBA", (side, side)).save(buf, "PNG")
        return buf.getvalue()

    def ora(name: str, xml: bytes, entries: dict[str, bytes]) -> Path:
        path = b / name
        with zipfile.ZipFile(path, "w") as z:
            z.writestr(zipfile.ZipInfo("mimetype"), b"image/openraster")
            z.writestr("stack.xml", xml)
            for k, v in entries.items():
                z.writestr(k, v, compress_type=zipfile.ZIP_DEFLATED)
        return path

    layers = "".join(f'<layer src="data/a.png" name="l{i}"/>' for i in range(40))
    shared = ora(
        "shared.ora",
        f'<image w="2048" h="2048"><stack>{layers}</stack></image>'.encode(),
        {"data/a.png": png_bytes(2048)},
    )
    trail = ora(
        "trail.ora",
        b'<image w="64" h="64"><stack><layer src="data/a.png"/></stack></image>',
        {"data/a.png": png_bytes(64) + b"\0" * 2**30},
    )
    xml16 = (
        '<?xml version="1.0" encoding="UTF-16"?><!DOCTYPE x [<!ENTITY a "b">]>'
        '<image w="8" h="8"><stack><layer src="data/a.png"/></stack></image>'
    )
    utf16 = ora("utf16.ora", xml16.encode("utf-16"), {"data/a.png": png_bytes(8)})
    eps = b / "l.eps"
    eps.write_bytes(b"%!PS-Adobe-3.0 EPSF-3.0\n%%BoundingBox: 0 0 10 10\n{ } loop\n")
    png_edit = b / "huge.png"
    if not png_edit.exists():
        Image.new("L", (16384, 16384)).save(png_edit)
    return {
        "png_layer_16384_on_8x8_composite": ["composite", str(b / "png"), "-o", str(b / "o1.png")],
        "solid_canvas_32768_composite": ["composite", str(b / "solid"), "-o", str(b / "o2.png")],
        "json_nested_1e5": ["validate", str(b / "deep")],
        "json_int_5000_digits": ["validate", str(b / "bigint")],
        "json_200MB": ["validate", str(b / "huge")],
        "ora_40_layers_one_entry": ["import-ora", str(shared), "-o", str(b / "o3")],
        "ora_entry_png_plus_1GiB_zeros": ["import-ora", str(trail), "-o", str(b / "o4")],
        "ora_utf16_dtd": ["import-ora", str(utf16), "-o", str(b / "o5")],
        "eps_edit": ["edit", str(eps), "--condition", "left", "-o", str(b / "o6")],
        "png_16384_edit": ["edit", str(png_edit), "--condition", "left", "-o", str(b / "o7")],
    }


def section_bombs(work: Path) -> dict:
    results = {}
    for name, argv in make_bombs(work).items():
        r = run_cli(*argv, cwd=work, timeout=60)
        ok = r["rc"] == 2 and len(r["stderr"]) == 1 and "internal error" not in r["stderr"][0]
        ok = ok and r["seconds"] <= 2.0 and (r["peak_mb"] or 1e9) <= 500
        results[name] = {**r, "stderr": r["stderr"][:1], "met": ok}
    return results


def section_kill(work: Path, tries: int, seed: int = 0) -> dict:
    """``lasagna edit`` (a per-image run, ~2 s) SIGKILLed at a random moment, then re-run to completion."""
    rng = random.Random(seed)
    folder = work / "kill"
    folder.mkdir(exist_ok=True)
    img = folder / "in.png"
    Image.fromarray((np.random.default_rng(0).random((48, 64, 3)) * 255).astype(np.uint8)).save(img)
    left_after_kill, left_after_rerun, reruns_ok = 0, 0, 0
    env = dict(os.environ, OMP_NUM_THREADS="1")
    for i in range(tries):
        out = folder / f"out{i}"
        argv = [sys.executable, "-m", "lasagna.cli", "edit", str(img), "--condition", "left", "-o", str(out)]
        argv += ["--generator", "free", "--optimize", "30"]
        p = subprocess.Popen(argv, cwd=folder, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(rng.uniform(0.5, 4.0))
        p.send_signal(signal.SIGKILL)
        p.wait()
        litter = [q for q in folder.iterdir() if q.name.startswith(".") and "lasagna-" in q.name]
        left_after_kill += len(litter)
        done = subprocess.run(argv + ["--force"], cwd=folder, env=env, capture_output=True)
        reruns_ok += done.returncode == 0
        left_after_rerun += sum(1 for q in folder.iterdir() if q.name.startswith(".") and "lasagna-" in q.name)
    return {
        "tries": tries,
        "temporaries_after_kill": left_after_kill,
        "temporaries_after_rerun": left_after_rerun,
        "reruns_ok": reruns_ok,
    }


def section_fuzz(examples: int) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1", LASAGNA_FUZZ_EXAMPLES=str(examples))
    t0 = time.perf_counter()
    p = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "slow", "tests/fuzz"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env=env,
    )
    tail = p.stdout.strip().splitlines()[-1] if p.stdout.strip() else ""
    return {
        "examples_per_family": examples,
        "passed": p.returncode == 0,
        "summary": tail,
        "seconds": round(time.perf_counter() - t0),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--fuzz", type=int, default=0, metavar="N", help="fuzzed inputs per family (0: skip)")
    ap.add_argument("--work", help="folder for the fixtures (default: a temporary folder)")
    args = ap.parse_args()
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="lasagna-hostile-"))
    work.mkdir(parents=True, exist_ok=True)
    record: dict = {"benchmark": "hostile", "machine": machine_info()}
    record["composite"] = section_composite(work, 2048 if args.quick else 8192)
    print(json.dumps({"composite": record["composite"]}))
    record["bombs"] = section_bombs(work)
    for name, r in record["bombs"].items():
        verdict = "met" if r["met"] else "MISSED"
        line = r["stderr"][0][:110] if r["stderr"] else ""
        print(f"{name:36s} rc={r['rc']} {r['seconds']:5.2f} s {r['peak_mb'] or 0:7.0f} MB  {verdict}  {line}")
    record["kill"] = section_kill(work, 3 if args.quick else 8)
    print(json.dumps({"kill": record["kill"]}))
    if args.fuzz:
        record["fuzz"] = section_fuzz(args.fuzz)
        print(json.dumps({"fuzz": record["fuzz"]}))
    c = record["composite"]
    summary = {
        "composite_peak_ratio": c["ratio"],
        "composite_peak_target_met": c["ratio"] <= 1.5,
        "bombs_met": sum(r["met"] for r in record["bombs"].values()),
        "bombs": len(record["bombs"]),
        "bomb_max_seconds": max(r["seconds"] for r in record["bombs"].values()),
        "bomb_max_peak_mb": max((r["peak_mb"] or 0) for r in record["bombs"].values()),
        "temporaries_after_rerun": record["kill"]["temporaries_after_rerun"],
    }
    record["summary"] = summary
    print_json_line(record)


if __name__ == "__main__":
    main()
