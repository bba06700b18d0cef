"""The ``lasagna`` CLI against its recorded output: every command's ``--help`` and one real invocation
each (plus bad input), compared with the golden files under ``tests/cli/golden/``.

The goldens were recorded before the CLI was redesigned into ``lasagna.cli``'s package (issue 13), so
this test is the proof that commands, flags, outputs and exit codes did not change. Only what varies
legitimately between runs is normalised: the temporary folder, the checkout's path and wall-clock
seconds. ``LASAGNA_GOLDEN=update pytest tests/cli/test_golden.py`` rewrites the files (review the diff).
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import pytest

from lasagna.cli import main

REPO = Path(__file__).resolve().parents[2]
GOLDEN = Path(__file__).resolve().parent / "golden"
BASIC = REPO / "examples" / "stacks" / "basic"
PHOTO = REPO / "examples" / "photos" / "coffee.png"
UPDATE = os.environ.get("LASAGNA_GOLDEN") == "update"

COMMANDS = (
    "composite",
    "export",
    "validate",
    "schema",
    "import-ora",
    "edit",
    "render",
    "light",
    "add-surface",
    "layers",
    "demo",
    "world",
    "train-prior",
    "train-corrective",
    "train-layer",
)

# name -> argv; "{tmp}" is the test's temporary folder. Cases run in order within one folder, so a later
# case may read what an earlier one wrote (import-ora reads the export's ORA, render the edit's stack).
REAL: dict[str, list[str]] = {
    "validate": ["validate", str(BASIC)],
    "composite": ["composite", str(BASIC), "-o", "{tmp}/out.png", "-v"],
    "export": ["export", str(BASIC), "--ora", "{tmp}/basic.ora", "--layers", "{tmp}/layers"],
    "import-ora": ["import-ora", "{tmp}/basic.ora", "-o", "{tmp}/imported"],
    "validate-imported": ["validate", "{tmp}/imported"],
    "schema": ["schema", "preset"],
    "schema-out": ["schema", "--out", "{tmp}/schemas"],
    "layers": ["layers"],
    "layers-json": ["layers", "--json"],
    "world": ["world", "-o", "{tmp}/world", "--split", "heldout", "--count", "2", "--resolution", "16"],
    "edit": ["edit", str(PHOTO), "--layer", "shading", "--condition", "left", "-o", "{tmp}/edit"],
    "edit-free": [
        "edit",
        str(PHOTO),
        "--layer",
        "shading",
        "--condition",
        "top",
        "--generator",
        "free",
        "--steps",
        "2",
        "--no-ora",
        "-o",
        "{tmp}/edit-free",
    ],
    "edit-twice": ["edit", "{tmp}/edit", "--condition", "top", "--optimize", "1", "--no-ora", "-o", "{tmp}/twice"],
    "render": ["render", "{tmp}/edit"],
    "render-all": ["render", "{tmp}/edit-free", "--all"],
    "train-prior": [
        "train-prior",
        "--out",
        "{tmp}/prior",
        "--steps",
        "2",
        "--batch-size",
        "2",
        "--resolution",
        "16",
        "--channels",
        "8,16",
        "--no-progress",
    ],
    "train-corrective": [
        "train-corrective",
        "--kind",
        "spectral",
        "--prior",
        "{tmp}/prior/prior",
        "--task",
        "relight",
        "--out",
        "{tmp}/spectral",
        "--batches",
        "1",
        "--buckets",
        "2",
        "--batch-size",
        "2",
        "--eval-batches",
        "1",
        "--no-progress",
    ],
    "train-layer": [
        "train-layer",
        "--preset",
        "shading",
        "--supervised",
        "--steps",
        "2",
        "--batch-size",
        "2",
        "--resolution",
        "16",
        "--channels",
        "8,16",
        "--out",
        "{tmp}/gen",
    ],
    # bad input: one line on stderr, exit 2
    "no-command": [],
    "unknown-command": ["frobnicate"],
    "missing-argument": ["composite"],
    "bad-choice": ["schema", "nope"],
    "validate-missing": ["validate", "{tmp}/nowhere"],
    "export-nothing": ["export", str(BASIC)],
    "edit-bad-label": ["edit", str(PHOTO), "--condition", "sideways", "-o", "{tmp}/bad"],
    "edit-bad-loss": ["edit", str(PHOTO), "--condition", "left", "--loss", "l2", "-o", "{tmp}/bad"],
    "edit-exists": ["edit", str(PHOTO), "--condition", "left", "-o", "{tmp}/edit"],
    "demo-bad-steps": ["demo", "-o", "{tmp}/demo", "--steps", "0"],
    "world-bad-count": ["world", "-o", "{tmp}/w2", "--split", "heldout", "--count", "0"],
    "train-prior-bad-task": ["train-prior", "--task", "paint", "--out", "{tmp}/p2"],
    "train-corrective-no-source": ["train-corrective", "--prior", "{tmp}/prior/prior", "--out", "{tmp}/c2"],
    "train-layer-bad-channels": ["train-layer", "--preset", "shading", "--channels", "a,b", "--out", "{tmp}/g2"],
    "version": ["--version"],
}
HELP: dict[str, list[str]] = {"help": ["--help"], **{f"help-{c}": [c, "--help"] for c in COMMANDS}}


def normalise(text: str, tmp: Path) -> str:
    text = text.replace(str(tmp), "<TMP>").replace(str(REPO), "<REPO>")
    text = re.sub(r"\b\d+\.\d+ s\b", "<SECONDS> s", text)  # wall-clock seconds in a summary line
    return text


def record(argv: list[str], tmp: Path, capsys) -> str:
    args = [a.replace("{tmp}", str(tmp)) for a in argv]
    code = main(args)
    out, err = capsys.readouterr()
    return normalise(f"$ lasagna {' '.join(argv)}\n--- exit {code}\n--- stdout\n{out}--- stderr\n{err}", tmp)


# A computed quality number (a PSNR, a loss) printed with all its digits: compared to this relative tolerance,
# not to the last digit — float order (BLAS, threads, a loaded machine's scheduling of reductions) moves the
# last few ulps (3e-7 dB was seen on the same code). Everything else in the text is compared exactly.
FLOAT = re.compile(r"-?\d+\.\d{6,}(?:e[-+]?\d+)?")
RTOL = 1e-6


def same_text(text: str, golden: str) -> bool:
    """``text`` is ``golden`` but for long floats, which agree within ``RTOL``."""
    if FLOAT.split(text) != FLOAT.split(golden):
        return False
    got, want = FLOAT.findall(text), FLOAT.findall(golden)
    return len(got) == len(want) and all(
        math.isclose(float(a), float(b), rel_tol=RTOL, abs_tol=RTOL) for a, b in zip(got, want)
    )


def check(name: str, text: str) -> None:
    path = GOLDEN / f"{name}.txt"
    if UPDATE:
        path.write_text(text, encoding="utf-8")
        return
    assert path.is_file(), f"no golden file {path.name}; record it with LASAGNA_GOLDEN=update"
    assert same_text(text, path.read_text(encoding="utf-8")), f"{name}: the CLI's output differs from {path.name}"


@pytest.fixture
def cli_env(monkeypatch):
    monkeypatch.setenv("COLUMNS", "100")  # argparse wraps help text to the terminal's width
    monkeypatch.delenv("LASAGNA_LAYERS", raising=False)
    monkeypatch.delenv("LASAGNA_DEBUG", raising=False)


@pytest.mark.parametrize("name", sorted(HELP))
def test_help(name, tmp_path, capsys, cli_env):
    check(name, record(HELP[name], tmp_path, capsys))


def test_real_invocations(tmp_path, capsys, cli_env):
    """Every case in order in one folder (later cases read what earlier ones wrote)."""
    for name, argv in REAL.items():
        check(name, record(argv, tmp_path, capsys))
    assert sorted(p.stem for p in GOLDEN.glob("*.txt")) == sorted(
        [*REAL, *HELP, "edit-free-stack-json", "edit-twice-stack-json"]
    )


@pytest.mark.parametrize("case", ["edit-free", "edit-twice"])
def test_learned_outputs_unchanged(case, tmp_path, capsys, cli_env):
    """The stack.json an edit writes (minus its timestamps) is byte-identical to the recorded one."""
    if case == "edit-twice":
        record(REAL["edit"], tmp_path, capsys)
    record(REAL[case], tmp_path, capsys)
    out = REAL[case][REAL[case].index("-o") + 1].replace("{tmp}", str(tmp_path))
    text = (Path(out) / "stack.json").read_text(encoding="utf-8")
    text = re.sub(r'"(created|rendered)": "[^"]*"', r'"\1": "<TIME>"', text)
    text = re.sub(r'"(seconds|generate_seconds|render_seconds)": [0-9.e-]+', r'"\1": 0', text)
    check(f"{case}-stack-json", normalise(text, tmp_path))


def test_quality_numbers_are_compared_to_a_stated_tolerance():
    golden = '{"step": 2, "layer_psnr": 7.672522518550819}'
    assert same_text('{"step": 2, "layer_psnr": 7.672522818550819}', golden)  # 3e-7 dB
    assert not same_text('{"step": 2, "layer_psnr": 7.682522518550819}', golden)
    assert not same_text('{"step": 3, "layer_psnr": 7.672522518550819}', golden)
