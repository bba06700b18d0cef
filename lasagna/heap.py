"""glibc's heap thresholds, set once so band temporaries and canvases are reused, not page-faulted in again.

The compose engine works in bands of ``TILE_PIXELS`` pixels (``compose/engine.py``): a 2^18-pixel RGB
float32 band is 3 MiB, and a W3C mode's formula allocates several temporaries of that size per band
(soft-light about a dozen). glibc serves an allocation of at least ``M_MMAP_THRESHOLD`` bytes (128 KiB
at start) with its own ``mmap``, and gives the top of the heap back to the kernel once more than
``M_TRIM_THRESHOLD`` of it is free. Both adapt upwards only when an mmapped chunk is freed (to its
size, at most 32 MiB, the trim threshold to twice that), so what a fresh process pays depends on what
it happened to allocate before: band-sized temporaries land on a heap that is trimmed after each band
and faulted in again (zeroed page by page) on the next one.

Measured on this project's box (2 vCPU AMD EPYC, torch 2.13.0+cpu, 2048² RGB, 2 threads, a base and one
opaque layer, ``render(plan, out=)``, median of 7): overlay 96–104 ms, soft-light 260–280 ms in a fresh
process; 9–13 ms and 21–28 ms after these thresholds are set (or after anything in the process freed a
large mmapped chunk, which is why ``benchmarks/compositing.py`` always saw the fast figures).

``tune_heap()`` sets ``M_MMAP_THRESHOLD`` to ``MMAP_THRESHOLD_BYTES`` (256 MiB) and ``M_TRIM_THRESHOLD`` to
``TRIM_THRESHOLD_BYTES`` (1 GiB) with ``mallopt``, once per process, on the first render. Band temporaries
then stay on the heap, and so do canvas-sized tensors (a 2048² RGB float32 canvas is 48 MiB, a 4096² one
192 MiB): a training step's fresh gradients and recorded intermediates reuse freed memory instead of
faulting new pages in. Measured (same box, 2 threads, a training step of 4 learned layers at 2048²): the
banded engine 46–65 → 36–41 ms, the recorded one (``grad_engine="autograd"``) 55–63 → 23–26 ms; with
only the band temporaries fixed (32 MiB / 64 MiB) the recorded one stayed at 55–60 ms.

The cost: up to ``TRIM_THRESHOLD_BYTES`` of freed memory stays mapped to the process between renders
(reused by the next one; a one-shot CLI call exits anyway). Peaks do not grow: ``benchmarks/hostile.py``'s
8192² composite peaked at 2401 MB with these thresholds and 2406 MB without (its target is a peak within
1.5× the output and inputs). Tensors above 256 MiB are still mmapped and returned on free.

Two profiles (``PROFILES``): ``"compute"`` above, the default, for a process that composites or trains;
``"server"`` (``SERVER_MMAP_THRESHOLD_BYTES``, ``SERVER_TRIM_THRESHOLD_BYTES``: 32 MiB and 64 MiB, glibc's own
adaptive maxima), which ``lasagna serve`` asks for: a long-lived editor should not keep up to 1 GiB of freed
memory mapped for hours. "server" still fixes the band temporaries. What it costs, measured with
``benchmarks/serve.py`` at 2048² (alternating runs, ``LASAGNA_HEAP=compute`` / ``server``): adding a learned
layer 256–298 ms with "compute" against 470–514 ms with "server" (target ≤ 1.5 s); toggle → repaint medians
69–81 ms against 71–78 ms, no difference this VM's noise can show (single runs ranged 63–98 ms with either).
The first call in a process sets the profile; ``LASAGNA_HEAP=compute|server`` overrides the caller's choice.

It does nothing where the C library is not glibc (macOS, musl, Windows), when the user has set the
thresholds themselves (``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_TRIM_THRESHOLD_``, or ``GLIBC_TUNABLES``
naming either), or when ``LASAGNA_HEAP=system``.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import platform

# mallopt parameter numbers, from glibc's <malloc.h>.
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3

# Above a 4096² RGB float32 canvas (192 MiB): band temporaries and canvases come from the heap.
MMAP_THRESHOLD_BYTES = 256 << 20
# Freed heap kept mapped before the top is given back: a few canvases' worth, so a training step's
# gradients and intermediates (4 layers at 2048²: ~400 MB) are reused, not faulted in again.
TRIM_THRESHOLD_BYTES = 1 << 30

# glibc's adaptive maxima on 64-bit (DEFAULT_MMAP_THRESHOLD_MAX and twice it): the "server" profile.
SERVER_MMAP_THRESHOLD_BYTES = 32 << 20
SERVER_TRIM_THRESHOLD_BYTES = 64 << 20
PROFILES = {
    "compute": (MMAP_THRESHOLD_BYTES, TRIM_THRESHOLD_BYTES),
    "server": (SERVER_MMAP_THRESHOLD_BYTES, SERVER_TRIM_THRESHOLD_BYTES),
}

_state: dict[str, bool | str] = {}


def _env() -> str:
    return os.environ.get("LASAGNA_HEAP", "").strip().lower()


def _user_has_set() -> bool:
    if _env() == "system":
        return True
    if "MALLOC_MMAP_THRESHOLD_" in os.environ or "MALLOC_TRIM_THRESHOLD_" in os.environ:
        return True
    tunables = os.environ.get("GLIBC_TUNABLES", "")
    return "mmap_threshold" in tunables or "trim_threshold" in tunables


def tune_heap(profile: str = "compute") -> bool:
    """Set glibc's mmap and trim thresholds to ``PROFILES[profile]`` (``LASAGNA_HEAP`` naming a profile wins),
    once per process: later calls change nothing (module docstring). True if they are set."""
    if "done" in _state:
        return bool(_state["done"])
    profile = _env() if _env() in PROFILES else profile
    if profile not in PROFILES:
        raise ValueError(f"heap profile {profile!r}; expected one of {', '.join(PROFILES)}")
    done = False
    if platform.system() == "Linux" and platform.libc_ver()[0] == "glibc" and not _user_has_set():
        mmap_bytes, trim_bytes = PROFILES[profile]
        try:
            libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
            done = bool(libc.mallopt(M_MMAP_THRESHOLD, mmap_bytes)) and bool(libc.mallopt(M_TRIM_THRESHOLD, trim_bytes))
        except (OSError, AttributeError):  # no loadable C library, or no mallopt in it
            done = False
    _state["done"] = done
    _state["profile"] = profile if done else "system"
    return done


def heap_profile() -> str | None:
    """The profile set in this process ("system" where none could be), None before ``tune_heap`` ran."""
    return _state.get("profile")  # type: ignore[return-value]


__all__ = [
    "MMAP_THRESHOLD_BYTES",
    "PROFILES",
    "SERVER_MMAP_THRESHOLD_BYTES",
    "SERVER_TRIM_THRESHOLD_BYTES",
    "TRIM_THRESHOLD_BYTES",
    "heap_profile",
    "tune_heap",
]
