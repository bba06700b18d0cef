"""A command-line relight edit from a cold start, with and without torch.optim's first-call cost.

    OMP_NUM_THREADS=2 python benchmarks/cold_edit.py [--rounds 2]

Every ``lasagna edit`` is a fresh process, so it pays what a warm library call does not. One of those costs:
``torch.optim.Optimizer`` imports ``torch._dynamo`` on its first call (``torch._disable_dynamo``), 1.1–1.4 s on the
project's CPUs. The per-image runs now use ``lasagna.distill.adam.Adam`` (torch's functional Adam, the same
updates bit for bit, no dynamo). This times ``lasagna edit PHOTO --layer relight --condition left`` on each of
``examples/photos/large``, each in a fresh interpreter, alternating the baseline (``torch.optim.Adam`` put back)
and the shipped code: the process's wall time and the edit's own seconds (as the command prints them), medians,
and whether the two wrote the same layer PNG. Ends with one JSON line.
"""

from __future__ import annotations

import argparse
import hashlib
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import machine_info, print_json_line  # noqa: E402

CHILD = """
import sys
if sys.argv[1] == "baseline":
    import torch
    import lasagna.distill.per_image as per_image, lasagna.distill.surface as surface
    per_image.Adam = surface.Adam = torch.optim.Adam
from lasagna.cli import main
rc = main(sys.argv[2:])
print("dynamo", "torch._dynamo" in sys.modules)
raise SystemExit(rc)
"""


def one(mode: str, photo: Path, out: Path) -> dict:
    argv = [sys.executable, "-c", CHILD, mode, "edit", str(photo), "--layer", "relight", "--condition", "left"]
    argv += ["-o", str(out), "--force", "--no-ora"]
    t0 = time.perf_counter()
    done = subprocess.run(argv, capture_output=True, text=True, check=True)
    wall = time.perf_counter() - t0
    edit = float(re.search(r"; ([0-9.]+) s\)", done.stdout).group(1))
    layer = next((out / "layers").glob("relight-*.png")).read_bytes()
    sha = hashlib.sha256(layer).hexdigest()
    return {"wall": wall, "edit": edit, "dynamo": "dynamo True" in done.stdout, "sha": sha}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=2, help="fresh-process rounds per photo and mode (alternating)")
    args = p.parse_args(argv)
    photos = sorted((ROOT / "examples" / "photos" / "large").glob("*.jpg"))
    runs: dict[str, list[dict]] = {"baseline": [], "shipped": []}
    same = True
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for photo in photos:
                order = ("baseline", "shipped") if r % 2 == 0 else ("shipped", "baseline")
                got = {m: one(m, photo, Path(tmp) / m) for m in order}
                same &= got["baseline"]["sha"] == got["shipped"]["sha"]
                for m, v in got.items():
                    runs[m].append(v)
    med = {m: {k: statistics.median(v[k] for v in vs) for k in ("wall", "edit")} for m, vs in runs.items()}
    print_json_line(
        {
            "benchmark": "cold_edit",
            "machine": machine_info(),
            "command": " ".join(sys.argv),
            "edits_per_mode": len(runs["shipped"]),
            "cli_wall_seconds_baseline": round(med["baseline"]["wall"], 2),
            "cli_wall_seconds": round(med["shipped"]["wall"], 2),
            "edit_seconds_baseline": round(med["baseline"]["edit"], 2),
            "edit_seconds": round(med["shipped"]["edit"], 2),
            "dynamo_imported_baseline": all(v["dynamo"] for v in runs["baseline"]),
            "dynamo_imported": any(v["dynamo"] for v in runs["shipped"]),
            "same_layer_png": same,
        }
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
