"""Run ``lasagna`` in a fresh Python process and report its peak resident memory, for tests that bound
what hostile input may cost (the child's VmHWM; in-process numbers would include pytest's)."""

from __future__ import annotations

import functools
import subprocess
import sys
import zlib
from pathlib import Path

from tests.support import pngcraft
from tests.support.bounded import HANG_SECONDS

# The peak is the child's VmHWM, not ru_maxrss: Linux keeps ru_maxrss across exec, so a child of a large
# pytest process would report at least the parent's resident size; VmHWM belongs to the new image.
_PEAK = """
def _peak_kb():
    with open("/proc/self/status") as fh:
        return next(int(line.split()[1]) for line in fh if line.startswith("VmHWM:"))
"""

_CHILD = (
    _PEAK
    + """
import sys
from lasagna.cli import main
code = main(sys.argv[1:])
sys.stdout.flush()
print("PEAK_KB", _peak_kb())
sys.exit(code)
"""
)


def run_cli(*argv, timeout: float = HANG_SECONDS) -> tuple[int, str, str, float]:
    """``lasagna ARGV`` in a child process: (exit status, stdout without the peak line, stderr, peak MB)."""
    proc = subprocess.run(
        [sys.executable, "-c", _CHILD, *map(str, argv)],
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    lines = proc.stdout.splitlines()
    assert lines and lines[-1].startswith("PEAK_KB "), (proc.stdout, proc.stderr)
    return proc.returncode, "\n".join(lines[:-1]), proc.stderr, int(lines[-1].split()[1]) / 1024


def run_python(code: str, timeout: float = HANG_SECONDS) -> tuple[int, str, str, float]:
    """``python -c CODE``: (exit status, stdout, stderr, peak MB of the child)."""
    wrapped = _PEAK + code + "\nprint('PEAK_KB', _peak_kb())\n"
    proc = subprocess.run([sys.executable, "-c", wrapped], capture_output=True, text=True, timeout=timeout)
    lines = proc.stdout.splitlines()
    assert lines and lines[-1].startswith("PEAK_KB "), (proc.stdout, proc.stderr)
    return proc.returncode, "\n".join(lines[:-1]), proc.stderr, int(lines[-1].split()[1]) / 1024


@functools.lru_cache(maxsize=1)
def baseline_mb() -> float:
    """Peak MB of a process that only imports the CLI and torch (what every command costs anyway)."""
    return run_python("import lasagna.cli, torch")[3]


def zero_rgb_png(path: Path, side: int) -> Path:
    """A ``side``² 8-bit RGB PNG of zeros, deflated row by row (never the whole raw image in memory):
    16384² is ~780 KB on disk and 3 GiB as float32."""
    deflate = zlib.compressobj(9)
    row = b"\x00" * (1 + 3 * side)
    parts = [deflate.compress(row) for _ in range(side)]
    parts.append(deflate.flush())
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pngcraft.png_bytes(side, side, b"".join(parts), color_type=2))
    return path
