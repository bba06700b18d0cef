"""Photographs as people have them (issue #27): ``lasagna edit`` of a 12 MP (and 24 MP) JPEG with no flags — wall
time, peak memory and the time of each phase. Plain script; ends with one JSON line.

    python benchmarks/photos.py                       # 12 MP, shading, OMP_NUM_THREADS=1 and 2
    python benchmarks/photos.py --sizes 12 24 --threads 1 --presets shading relight

The photo is ``examples/photos/large/chelsea.jpg`` enlarged with Pillow (LANCZOS) to 4000×3000 (12 MP) or
6000×4000 (24 MP), JPEG quality 90, written once into a temporary folder. Each run is its own process,

    OMP_NUM_THREADS=T /usr/bin/time -v lasagna edit PHOTO --layer PRESET --condition left -o OUT --progress

(the console script of this checkout's environment); wall time and peak RSS are ``/usr/bin/time``'s ("Elapsed",
"Maximum resident set size"), the phases the ``--progress`` lines ("… done in X s"). The load average before and
after each run is recorded: other work on the machine is measured too (say "not quiet" when it is above ~0.5).

Targets (docs/BENCHMARKS.md, "Photographs"): at 12 MP, peak ≤ 3 GB and wall ≤ 20 s on the project's 2-core CPU.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from PIL import Image

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
from _common import machine_info, print_json_line  # noqa: E402

SIZES = {12: (4000, 3000), 24: (6000, 4000)}
PHASE = re.compile(r"lasagna: (.+?)… done in ([0-9.]+) s")
TARGETS = {"peak_gb": 3.0, "wall_s": 20.0}  # at 12 MP


def make_photo(folder: Path, mp: int) -> Path:
    path = folder / f"chelsea-{mp}mp.jpg"
    if not path.exists():
        with Image.open(ROOT / "examples" / "photos" / "large" / "chelsea.jpg") as im:
            im.convert("RGB").resize(SIZES[mp], Image.Resampling.LANCZOS).save(path, quality=90)
    return path


def lasagna_command() -> list[str]:
    script = Path(sys.executable).with_name("lasagna")
    return [str(script)] if script.exists() else [sys.executable, "-m", "lasagna"]


def run_edit(photo: Path, out: Path, preset: str, threads: int) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS=str(threads))
    cmd = ["/usr/bin/time", "-v", *lasagna_command(), "edit", str(photo), "--layer", preset, "--condition", "left"]
    cmd += ["-o", str(out), "--progress"]
    load_before = os.getloadavg()[0]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    load_after = os.getloadavg()[0]
    err = proc.stderr
    if proc.returncode != 0:
        raise SystemExit(f"lasagna edit failed ({proc.returncode}):\n{err[-2000:]}")
    wall = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): (?:(\d+):)?(\d+):([0-9.]+)", err)
    h, m, s = (float(g) if g else 0.0 for g in wall.groups())  # type: ignore[union-attr]
    peak_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", err).group(1))  # type: ignore[union-attr]
    phases = {name: float(t) for name, t in PHASE.findall(err + proc.stdout)}
    return {
        "wall_s": round(3600 * h + 60 * m + s, 2),
        "peak_gb": round(peak_kb * 1024 / 1e9, 3),
        "phases_s": phases,
        "load_before": round(load_before, 2),
        "load_after": round(load_after, 2),
        "command": f"OMP_NUM_THREADS={threads} /usr/bin/time -v lasagna edit {photo.name} --layer {preset} "
        f"--condition left -o OUT --progress",
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", choices=sorted(SIZES), default=[12])
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--presets", nargs="+", default=["shading"])
    ap.add_argument("--repeats", type=int, default=1, help="runs of each configuration (all reported)")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="lasagna-photos-") as tmp:
        folder = Path(tmp)
        for mp in args.sizes:
            photo = make_photo(folder, mp)
            for preset in args.presets:
                for threads in args.threads:
                    for _ in range(args.repeats):
                        out = folder / "out"
                        shutil.rmtree(out, ignore_errors=True)
                        row = {"mp": mp, "preset": preset, "threads": threads, **run_edit(photo, out, preset, threads)}
                        if mp == 12:
                            row["meets"] = all(row[k] <= v for k, v in TARGETS.items())
                        print(
                            f"{mp} MP {preset} threads={threads}: {row['wall_s']} s, {row['peak_gb']} GB "
                            f"(load {row['load_before']} → {row['load_after']}) {row['phases_s']}",
                            flush=True,
                        )
                        rows.append(row)
    print_json_line({"benchmark": "photos", "machine": machine_info(), "targets_12mp": TARGETS, "runs": rows})


if __name__ == "__main__":
    main()
