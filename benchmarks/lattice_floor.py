"""The floor under ``adjust10_vs_normal10``: what one colour-lattice read costs at machine speed.

Issue #25 asks ten adjustment layers at 2048² to cost ≤ 1.5× ten normal layers. ``compose/lut.py`` reads a run
of adjustments from one 65³ lattice; accuracy (``LUT_TOLERANCE``) splits the benchmark's stack into three runs and
three exact steps. This script measures the cheapest that reading can be, outside torch: a C++ program (compiled
here with ``g++ -O3 -march=native``; the script says so and exits 0 when there is no compiler) times, on one
thread, over a 2048² planar float32 canvas,

* ``trilinear_ms``: one trilinear read of a 65³ RGB lattice (8 corners × 3 channels per pixel), what ``lut.py``
  does by ``grid_sample``;
* ``tetrahedral_ms``: one tetrahedral read (4 corners, the cheapest interpolation colour management uses);
* ``normal10_ms``: the baseline, ten normal blends of opacity 0.8 over the base, band by band (the canvas band stays
  in cache and each layer is streamed once, as the banded forward does).

and prints ``trilinear_vs_normal10`` and ``tetrahedral_vs_normal10``: the ratio of a single read, the whole stack
in one lattice, which the tolerance does not even allow. Usage::

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/lattice_floor.py [--size 2048] [--repeats 5]
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import machine_info, print_json_line  # noqa: E402

SOURCE = r"""
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <vector>

static std::vector<float> img, out, lut, layers;
static int N, L = 65;

static void trilinear() {
  const float s = L - 1; const float *R = img.data(), *G = R + N, *B = G + N; float *o = out.data();
  const int LL = L * L, LLL = L * L * L;
  for (int p = 0; p < N; p++) {
    float r = R[p] * s, g = G[p] * s, b = B[p] * s;
    int ir = std::min((int)r, L - 2), ig = std::min((int)g, L - 2), ib = std::min((int)b, L - 2);
    float fr = r - ir, fg = g - ig, fb = b - ib; int i = (ir * L + ig) * L + ib;
    for (int c = 0; c < 3; c++) {
      const float *T = lut.data() + c * LLL;
      float c00 = T[i] + fb * (T[i + 1] - T[i]), c01 = T[i + L] + fb * (T[i + L + 1] - T[i + L]);
      float c10 = T[i + LL] + fb * (T[i + LL + 1] - T[i + LL]);
      float c11 = T[i + LL + L] + fb * (T[i + LL + L + 1] - T[i + LL + L]);
      float c0 = c00 + fg * (c01 - c00), c1 = c10 + fg * (c11 - c10);
      o[c * N + p] = c0 + fr * (c1 - c0);
    }
  }
}

static void tetrahedral() {
  const float s = L - 1; const float *R = img.data(), *G = R + N, *B = G + N; float *o = out.data();
  const int LL = L * L, LLL = L * L * L;
  for (int p = 0; p < N; p++) {
    float r = R[p] * s, g = G[p] * s, b = B[p] * s;
    int ir = std::min((int)r, L - 2), ig = std::min((int)g, L - 2), ib = std::min((int)b, L - 2);
    float fr = r - ir, fg = g - ig, fb = b - ib; int i = (ir * L + ig) * L + ib;
    // The tetrahedron of the cube holding the point: the corners along the sorted fractions.
    int d1, d2; float w0, w1, w2, w3;
    if (fr >= fg) {
      if (fg >= fb) { d1 = LL; d2 = LL + L; w0 = 1 - fr; w1 = fr - fg; w2 = fg - fb; w3 = fb; }
      else if (fr >= fb) { d1 = LL; d2 = LL + 1; w0 = 1 - fr; w1 = fr - fb; w2 = fb - fg; w3 = fg; }
      else { d1 = 1; d2 = LL + 1; w0 = 1 - fb; w1 = fb - fr; w2 = fr - fg; w3 = fg; }
    } else {
      if (fb >= fg) { d1 = 1; d2 = L + 1; w0 = 1 - fb; w1 = fb - fg; w2 = fg - fr; w3 = fr; }
      else if (fb >= fr) { d1 = L; d2 = L + 1; w0 = 1 - fg; w1 = fg - fb; w2 = fb - fr; w3 = fr; }
      else { d1 = L; d2 = LL + L; w0 = 1 - fg; w1 = fg - fr; w2 = fr - fb; w3 = fb; }
    }
    for (int c = 0; c < 3; c++) {
      const float *T = lut.data() + c * LLL;
      o[c * N + p] = w0 * T[i] + w1 * T[i + d1] + w2 * T[i + d2] + w3 * T[i + LL + L + 1];
    }
  }
}

static void normal10() {
  const int band = 4096;
  for (int c = 0; c < 3; c++)
    for (int p0 = 0; p0 < N; p0 += band) {
      float *o = out.data() + (size_t)c * N + p0; const float *b = img.data() + (size_t)c * N + p0;
      int n = std::min(band, N - p0);
      for (int p = 0; p < n; p++) o[p] = b[p];
      for (int k = 0; k < 10; k++) {
        const float *l = layers.data() + ((size_t)k * 3 + c) * N + p0;
        for (int p = 0; p < n; p++) o[p] += 0.8f * (l[p] - o[p]);
      }
    }
}

template <class F> static double best_ms(F f, int repeats) {
  f();
  std::vector<double> t;
  for (int k = 0; k < repeats; k++) {
    auto a = std::chrono::steady_clock::now(); f(); auto b = std::chrono::steady_clock::now();
    t.push_back(std::chrono::duration<double, std::milli>(b - a).count());
  }
  std::sort(t.begin(), t.end());
  return t[t.size() / 2];
}

int main(int argc, char **argv) {
  int size = atoi(argv[1]), repeats = atoi(argv[2]); N = size * size;
  srand(25);
  img.resize(3 * (size_t)N); out.resize(3 * (size_t)N);
  lut.resize(3 * (size_t)L * L * L); layers.resize(30 * (size_t)N);
  for (auto &v : img) v = (rand() % 256) / 255.f;
  for (auto &v : lut) v = (rand() % 256) / 255.f;
  for (auto &v : layers) v = (rand() % 256) / 255.f;
  double tri = best_ms(trilinear, repeats), tet = best_ms(tetrahedral, repeats), nrm = best_ms(normal10, repeats);
  double check = 0; for (size_t k = 0; k < out.size(); k += 4099) check += out[k];
  printf("%f %f %f %f\n", tri, tet, nrm, check);
}
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    compiler = shutil.which("g++")
    if compiler is None:
        print("lattice_floor: no g++ on this machine; nothing measured", file=sys.stderr)
        print_json_line({"benchmark": "lattice_floor", "skipped": "no g++"})
        return
    with tempfile.TemporaryDirectory() as tmp:
        src, exe = Path(tmp) / "floor.cpp", Path(tmp) / "floor"
        src.write_text(SOURCE)
        flags = ["-O3", "-march=native", "-std=c++17"]
        subprocess.run([compiler, *flags, "-o", str(exe), str(src)], check=True)
        line = subprocess.run([str(exe), str(args.size), str(args.repeats)], check=True, capture_output=True, text=True)
    tri, tet, nrm, _ = (float(v) for v in line.stdout.split())
    print_json_line(
        {
            "benchmark": "lattice_floor",
            "machine": {**machine_info(), "program_threads": 1, "compiler": f"g++ {' '.join(flags)}"},
            "size": args.size,
            "trilinear_ms": round(tri, 2),
            "tetrahedral_ms": round(tet, 2),
            "normal10_ms": round(nrm, 2),
            "trilinear_vs_normal10": round(tri / nrm, 3),
            "tetrahedral_vs_normal10": round(tet / nrm, 3),
        }
    )


if __name__ == "__main__":
    main()
