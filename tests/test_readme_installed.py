"""Every README command, run as a user runs it (issue #27; slow, ``pytest -m slow tests/test_readme_installed.py``).

The wheel built from this checkout (``tests.support.wheel.build_wheel``) is installed by its distribution name,
``pip install --find-links DIST 'lasagna-layers[serve,psd]'``, into a fresh venv; then the README's ``lasagna``
commands (``tests/test_readme_commands.py``'s parser, the one place that reads them) run in the README's order
from a folder outside the checkout that holds a copy of ``examples/``, as a clone or the README's downloads
give a user. Each must exit 0, and the installed package folder must be unchanged by them all, ``train-layer
--install`` included (it writes into ``$HOME/.local/share/lasagna/layers``, a temporary home here).

The venv gets ``torch==2.13.0`` first, the CPU wheel on this machine's disk, as the Makefile's venv does: a bare
``torch`` requirement resolves to the CUDA build (5 GB with its libraries). The repo venv's torch through a
``.pth`` file would be quicker, but a ``.pth`` puts a whole folder on the path — .venv's site-packages, which
holds the checkout's editable ``lasagna-layers`` too — so the test would no longer show what a user's install
does. The diffusers extra is left out: the commands that need it need a model folder of one's own too.

Changed from the README's text, and why (each says so in ``plan``):
- training budgets cut to a few steps with each command's own flags (``BUDGETS``): the README's runs take 2 to 40
  minutes each; what is checked is that each starts from what a user has, trains, writes and installs.
- the user's own inputs the README only names (``painting.ora``, ``shots/``, ``a.png``, ``big/``, ``photo.jpg``)
  are made from the examples (``own_inputs``) before the commands run.
- ``serve`` runs until stopped: it is started, its printed URL is fetched, and it is stopped with Ctrl-C.
- skipped: the commands naming ``/models/…`` (a diffusers model of one's own; the adapter is tested with a tiny
  pipeline in ``tests/priors``) and the entry ``prior add`` registers from it.
- added: ``lasagna demo`` from a folder with no ``examples/`` (the README: installed, it is ``make demo`` without a
  checkout), so its inputs can only come from the package.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.request
import zipfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from lasagna.version import DISTRIBUTION, __version__
from tests.support.bounded import HANG_SECONDS
from tests.support.wheel import ROOT, build_wheel
from tests.test_readme_commands import readme_commands

pytestmark = pytest.mark.slow

# The Makefile's TORCH: the CPU wheel on this machine's disk, installed before the distribution so that its
# `torch>=2.2` is already met (a bare `torch` resolves to the CUDA build).
TORCH = "torch==2.13.0"

# Training budgets, by the command's own flags (set where the README gives them, added where not): a few steps,
# small batches, one evaluation batch. The README's `--minutes` stay: with `--steps` they are upper bounds.
BUDGETS: dict[str, dict[str, str]] = {
    "train-prior": {"--steps": "2", "--batch-size": "4", "--warmup": "1"},
    "train-corrective": {
        "--steps": "2",
        "--batch-size": "4",
        "--eval-batches": "1",
        "--batches": "1",
        "--buckets": "2",
    },
    "train-layer": {"--steps": "2", "--batch-size": "4"},
    "train-surface": {"--steps": "2", "--batch-size": "4", "--warmup": "1"},
}
# The spectral fit's own budget (batches per timestep bucket, buckets): not given to a network run.
SPECTRAL_ONLY = ("--batches", "--buckets")


def plan(args: list[str]) -> tuple[list[str] | None, str]:
    """(the argument list to run, what was changed and why); (None, why) for a command not run here."""
    if any(a.startswith("/models/") for a in args) or "relight-sd" in args:
        return None, "a diffusers model folder of one's own (/models/…): tested with a tiny pipeline in tests/priors"
    budget = dict(BUDGETS.get(args[0], {}))
    if args[0] == "train-corrective" and "spectral" not in args:
        budget = {k: v for k, v in budget.items() if k not in SPECTRAL_ONLY}
    if not budget:
        return args, ""
    out = list(args)
    for flag, value in budget.items():
        if flag in out:
            out[out.index(flag) + 1] = value
        else:
            out += [flag, value]
    return out, "training budget cut to a few steps"


def own_inputs(work: Path) -> None:
    """The inputs a README command names but a user brings (``USERS_OWN`` of test_readme_commands), made from the
    examples: a painting (the basic stack exported by this checkout), photographs, a folder of shots, a stack."""
    from lasagna.api import export_ora, export_psd, load

    basic = load(ROOT / "examples" / "stacks" / "basic")
    export_ora(basic, work / "painting.ora")
    export_psd(basic, work / "painting.psd")
    chelsea = Image.open(ROOT / "examples" / "photos" / "chelsea.png").convert("RGB")
    (work / "shots" / "day1").mkdir(parents=True)
    chelsea.save(work / "shots" / "day1" / "chelsea.jpg", quality=92)
    chelsea.save(work / "photo.jpg", quality=92)
    rng = np.random.default_rng(0)
    Image.fromarray(rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)).save(work / "a.png")
    shutil.copytree(ROOT / "examples" / "stacks" / "basic", work / "big")


def tree_hashes(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` (bytecode caches left out: the interpreter's, not the program's writes) by
    relative path → SHA-256."""
    return {
        p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and "__pycache__" not in p.parts
    }


@pytest.fixture(scope="module")
def venv(tmp_path_factory) -> tuple[Path, Path]:
    """(the fresh venv, its site-packages), ``lasagna-layers`` installed from the wheel by its name."""
    tmp = tmp_path_factory.mktemp("readme-installed")
    wheel = build_wheel(tmp)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PIP_NO_INDEX")}
    subprocess.run([sys.executable, "-m", "venv", str(tmp / "venv")], check=True, timeout=HANG_SECONDS)
    python = tmp / "venv" / "bin" / "python"
    for requirement in ([TORCH], ["--find-links", str(wheel.parent), f"{DISTRIBUTION}[serve,psd]"]):
        inst = subprocess.run(
            [python, "-m", "pip", "install", "-q", *requirement],
            capture_output=True,
            text=True,
            timeout=HANG_SECONDS,
            env=env,
            cwd=tmp,
        )
        assert inst.returncode == 0, inst.stderr[-3000:]
    site = Path(
        subprocess.check_output(
            [python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], text=True
        ).strip()
    )
    # What was installed is this wheel, every file of it byte for byte (no index's lasagna-layers).
    assert (site / f"lasagna_layers-{__version__}.dist-info").is_dir()
    installed = tree_hashes(site / "lasagna")
    with zipfile.ZipFile(wheel) as z:
        packed = {
            n.removeprefix("lasagna/"): hashlib.sha256(z.read(n)).hexdigest()
            for n in z.namelist()
            if n.startswith("lasagna/") and not n.endswith("/")
        }
    assert installed == packed
    return tmp / "venv", site


def _serve(cmd: list[str], cwd: Path, env: dict[str, str]) -> tuple[int, str]:
    """``lasagna serve``: started, its URL fetched (200 and the editor's page), stopped with Ctrl-C as a user stops
    it; (exit status, output), the status -1 where no URL was printed or its page did not come."""
    proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    hang = threading.Timer(HANG_SECONDS, proc.kill)  # a server silent that long ends the read below
    hang.start()
    lines, fetched = [], False
    try:
        for line in proc.stdout:
            lines.append(line)
            if line.strip().startswith("http://"):
                with urllib.request.urlopen(line.strip(), timeout=60) as page:
                    fetched = page.status == 200 and b"<html" in page.read().lower()
                break
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=HANG_SECONDS)
    finally:
        hang.cancel()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode if fetched else -1, "".join(lines) + (rest or "")


def test_every_readme_command_runs_from_the_wheel_installed_by_name_outside_the_checkout(venv, tmp_path):
    root, site = venv
    work, home = tmp_path / "work", tmp_path / "home"
    work.mkdir()
    home.mkdir()
    assert not work.resolve().is_relative_to(ROOT)
    shutil.copytree(ROOT / "examples", work / "examples", ignore=shutil.ignore_patterns("__pycache__"))
    own_inputs(work)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "LASAGNA_LAYERS", "XDG_DATA_HOME")}
    # A temporary home (the user's catalogue), one thread (a loaded two-core machine), no browser opened.
    env.update(HOME=str(home), OMP_NUM_THREADS="1", BROWSER="true", PATH=f"{root / 'bin'}{os.pathsep}{env['PATH']}")
    where = subprocess.run(
        [root / "bin" / "python", "-c", "import lasagna; print(lasagna.__file__)"],
        cwd=work,
        env=env,
        capture_output=True,
        text=True,
        timeout=HANG_SECONDS,
    )
    assert Path(where.stdout.strip()).resolve().is_relative_to(site.resolve()), where.stdout + where.stderr
    package = tree_hashes(site / "lasagna")
    lasagna = str(root / "bin" / "lasagna")
    failed, ran, skipped = [], [], []
    for args in readme_commands():
        argv, why = plan(args)
        if argv is None:
            skipped.append(f"lasagna {' '.join(args)}: {why}")
            continue
        t0 = time.monotonic()
        if argv[0] == "serve":
            code, output = _serve([lasagna, *argv], work, env)
        else:
            proc = subprocess.run(
                [lasagna, *argv], cwd=work, env=env, capture_output=True, text=True, timeout=HANG_SECONDS
            )
            code, output = proc.returncode, proc.stdout[-1500:] + proc.stderr[-1500:]
        line = f"lasagna {' '.join(argv)}  ({time.monotonic() - t0:.1f} s{'; ' + why if why else ''})"
        ran.append(line)
        if code != 0:
            failed.append(f"{line}: exit {code}\n{output}")
        if code == 0 and argv[0] == "train-layer" and "--install" in argv:
            assert tree_hashes(site / "lasagna") == package, f"{line} changed the installed package"
            generator = home / ".local" / "share" / "lasagna" / "layers" / argv[argv.index("--preset") + 1]
            assert (generator / "generator" / "model.safetensors").is_file(), f"{line} installed nothing in {generator}"
    # `lasagna demo` where there is no examples/: the world scenes rendered, the photographs the package's own.
    bare = tmp_path / "bare"
    bare.mkdir()
    t0 = time.monotonic()
    proc = subprocess.run(
        [lasagna, "demo", "-o", "out/demo"], cwd=bare, env=env, capture_output=True, text=True, timeout=HANG_SECONDS
    )
    line = f"lasagna demo -o out/demo  ({time.monotonic() - t0:.1f} s; from a folder with no examples/)"
    ran.append(line)
    stacks = list((bare / "out" / "demo" / "stacks").glob("*/stack.json"))
    if proc.returncode != 0 or "no examples/ here" not in proc.stdout or len(stacks) != 38:
        failed.append(
            f"{line}: exit {proc.returncode}, {len(stacks)} stacks\n{proc.stdout[-1500:]}{proc.stderr[-1500:]}"
        )
    print("\n".join(["ran:", *ran, "skipped:", *skipped]))
    assert not failed, "\n\n".join(failed)
    assert tree_hashes(site / "lasagna") == package, "the README's commands changed the installed package"
    assert len(ran) >= 30
