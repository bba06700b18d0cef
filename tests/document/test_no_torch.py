"""The document tier never imports torch (docs/ARCHITECTURE.md: pydantic models only)."""

from __future__ import annotations

import subprocess
import sys

from tests.document.cases import ROOT

PROGRAM = """
import sys
import lasagna.document as d
d.load_document("examples/stacks/basic")
d.schemas()
d.load_preset("layers/shading")
leaked = sorted(m for m in sys.modules if m == "torch" or m.startswith("torch.") or m == "numpy")
print(",".join(leaked))
"""


def test_importing_and_using_the_document_tier_imports_no_torch():
    out = subprocess.run([sys.executable, "-c", PROGRAM], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"lasagna.document imported {out.stdout.strip()}"


def test_no_torch_in_the_source():
    for path in (ROOT / "lasagna" / "document").glob("*.py"):
        text = path.read_text(encoding="utf-8")
        assert "import torch" not in text and "from torch" not in text, path
