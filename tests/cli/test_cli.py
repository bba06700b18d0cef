"""The ``lasagna`` CLI: composites of random stacks against the independent float64 reference, every
subcommand's happy path, and hostile input (one line on stderr, exit 2, no traceback, outputs untouched)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from lasagna.cli import COMMANDS, main
from lasagna.export.ora_import import MAX_GROUP_DEPTH
from tests.support import pngcraft
from tests.support.bounded import HANG_SECONDS
from tests.support.reference import composite_reference, to_uint8
from tests.support.stackcraft import random_stack, write_png8, write_stack

BASIC = Path(__file__).resolve().parents[2] / "examples" / "stacks" / "basic"


def run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _png(path) -> np.ndarray:
    with Image.open(path) as im:
        assert im.mode == "RGB"
        return np.asarray(im).astype(int)


# ---- composite vs the reference ---------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(16))
@pytest.mark.parametrize("blend_space", ["srgb", "linear"])
def test_composite_matches_reference(tmp_path, capsys, seed, blend_space):
    clamp = "output" if seed % 4 == 3 else "layer"
    folder = random_stack(tmp_path / "s", seed, blend_space=blend_space, clamp=clamp)
    code, out, err = run(capsys, "composite", folder, "-o", tmp_path / "out.png")
    assert code == 0, err
    ours = _png(tmp_path / "out.png")
    ref = to_uint8(composite_reference(folder)).astype(int)
    assert ours.shape == ref.shape
    assert np.abs(ours - ref).max() <= 1


def test_composite_default_output_and_verbose(tmp_path, capsys):
    folder = shutil.copytree(BASIC, tmp_path / "basic")
    code, out, err = run(capsys, "composite", folder / "stack.json", "-v")
    assert code == 0 and err == ""
    assert (folder / "composite.png").is_file()
    assert "skipped: hidden: hidden" in out and "composed: base, shade, sticker, glow" in out
    assert np.abs(_png(folder / "composite.png") - to_uint8(composite_reference(folder))).max() <= 1


def test_learned_layer_without_source_is_reported(tmp_path, capsys):
    write_png8(tmp_path / "s/layers/base.png", np.full((4, 5, 3), 100))
    doc = {
        "format": "lasagna.stack",
        "version": 1,
        "canvas": {"width": 5, "height": 4},
        "layers": [
            {"id": "base", "kind": "pixels", "source": "layers/base.png"},
            {
                "id": "relit",
                "kind": "learned",
                "preset": "shading",
                "condition": {"label": "left"},
                "conditioned_on": "base",
                "blend": "multiply",
                "range": [0, 2],
            },
        ],
    }
    write_stack(tmp_path / "s", doc)
    code, out, _ = run(capsys, "composite", tmp_path / "s", "-v")
    assert code == 0 and "skipped: relit: not rendered (run `lasagna render`)" in out
    code, out, _ = run(capsys, "validate", tmp_path / "s")
    assert code == 0 and out.startswith("ok: 2 layers") and "not rendered" in out


# ---- other subcommands ----------------------------------------------------------------------------------


def test_validate_schema_export_import(tmp_path, capsys):
    code, out, _ = run(capsys, "validate", BASIC)
    assert code == 0 and out.startswith("ok: 5 layers")
    code, out, _ = run(capsys, "schema")
    assert code == 0 and json.loads(out)["$id"].endswith("stack.schema.json")
    code, out, _ = run(capsys, "schema", "--out", tmp_path / "schemas")
    assert code == 0 and sorted(p.name for p in (tmp_path / "schemas").iterdir()) == [
        "preset.schema.json",
        "stack.schema.json",
    ]
    code, out, err = run(
        capsys,
        "export",
        BASIC,
        "--ora",
        tmp_path / "b.ora",
        "--psd",
        tmp_path / "b.psd",
        "--layers",
        tmp_path / "layers",
    )
    assert code == 0, err
    assert zipfile.ZipFile(tmp_path / "b.ora").namelist()[0] == "mimetype"
    assert (tmp_path / "b.psd").read_bytes()[:4] == b"8BPS"
    meta = json.loads((tmp_path / "layers/layers.json").read_text())
    assert [layer["id"] for layer in meta["layers"]] == ["base", "shade", "sticker", "glow", "hidden"]
    code, out, err = run(capsys, "import-ora", tmp_path / "b.ora", "-o", tmp_path / "back")
    assert code == 0, err
    code, _, _ = run(capsys, "composite", tmp_path / "back")
    assert np.abs(_png(tmp_path / "back/composite.png") - to_uint8(composite_reference(BASIC))).max() <= 1
    # A second import into the same folder refuses to overwrite the stack.
    before = (tmp_path / "back/stack.json").read_bytes()
    code, _, err = run(capsys, "import-ora", tmp_path / "b.ora", "-o", tmp_path / "back")
    assert code == 2 and "--force" in err and (tmp_path / "back/stack.json").read_bytes() == before


def test_export_needs_an_output(capsys):
    code, _, err = run(capsys, "export", BASIC)
    assert code == 2 and "expected at least one of --ora" in err


# ---- hostile input --------------------------------------------------------------------------------------


def _good_stack(folder: Path, **layer_changes) -> Path:
    write_png8(folder / "layers/base.png", np.full((6, 8, 3), 120))
    write_png8(folder / "layers/top.png", np.full((6, 8, 4), 200))
    top = {"id": "top", "kind": "pixels", "source": "layers/top.png", **layer_changes}
    doc = {
        "format": "lasagna.stack",
        "version": 1,
        "canvas": {"width": 8, "height": 6},
        "layers": [{"id": "base", "kind": "pixels", "source": "layers/base.png"}, top],
    }
    return write_stack(folder, doc)


def _hostile(tmp_path: Path, case: str) -> Path:
    s = tmp_path / "s"
    if case == "malformed-json":
        _good_stack(s)
        (s / "stack.json").write_text('{"format": "lasagna.stack", "version": 1, "canvas": {')
    elif case == "unknown-blend":
        _good_stack(s, blend="mutliply")
    elif case == "missing-png":
        _good_stack(s, source="layers/nope.png")
    elif case == "corrupt-png":
        _good_stack(s)
        data = bytearray((s / "layers/top.png").read_bytes())
        data[40] ^= 0x55
        (s / "layers/top.png").write_bytes(bytes(data))
    elif case == "truncated-png":
        _good_stack(s)
        data = (s / "layers/top.png").read_bytes()
        (s / "layers/top.png").write_bytes(data[: len(data) - 20])
    elif case == "not-png":
        _good_stack(s)
        (s / "layers/top.png").write_bytes(b"GIF89a" + b"\x00" * 50)
    elif case == "size-mismatch":
        _good_stack(s, mask="masks/top.png")
        write_png8(s / "masks/top.png", np.zeros((5, 8)))
    elif case == "nan":
        _good_stack(s)
        (s / "stack.json").write_text(
            (s / "stack.json").read_text().replace('"id": "top"', '"opacity": NaN, "id": "top"')
        )
    elif case == "nan-colour":
        _good_stack(s)
        doc = json.loads((s / "stack.json").read_text())
        doc["layers"].append({"id": "sol", "kind": "solid", "color": [0.1, float("nan"), 0.2]})
        (s / "stack.json").write_text(json.dumps(doc))
    elif case == "dotdot-source":
        _good_stack(s, source="../outside.png")
        write_png8(tmp_path / "outside.png", np.zeros((6, 8, 3)))
    elif case == "absolute-source":
        _good_stack(s, source=str(tmp_path / "outside.png"))
        write_png8(tmp_path / "outside.png", np.zeros((6, 8, 3)))
    elif case == "symlink-escape":
        _good_stack(s)
        write_png8(tmp_path / "outside.png", np.zeros((6, 8, 4)))
        (s / "layers/top.png").unlink()
        os.symlink(tmp_path / "outside.png", s / "layers/top.png")
    elif case == "symlink-dir-escape":
        _good_stack(s, source="linked/top.png")
        (tmp_path / "elsewhere").mkdir()
        write_png8(tmp_path / "elsewhere/top.png", np.zeros((6, 8, 4)))
        os.symlink(tmp_path / "elsewhere", s / "linked")
    elif case == "header-bomb":
        _good_stack(s)
        (s / "layers/top.png").write_bytes(pngcraft.header_bomb())
    elif case == "side-bomb":  # under the pixel limit, over the canvas limit of 32768 per side
        _good_stack(s)
        (s / "layers/top.png").write_bytes(pngcraft.header_bomb(100_000, 2))
    elif case == "idat-bomb":
        _good_stack(s)
        (s / "layers/top.png").write_bytes(pngcraft.idat_bomb(8, 6, expands_to=32 * 2**20))
    elif case == "source-is-folder":
        _good_stack(s, source="layers")
    elif case == "duplicate-id":
        _good_stack(s, id="BASE")
    elif case == "not-utf8":
        _good_stack(s)
        (s / "stack.json").write_bytes(b"\xff\xfe{\x00")
    elif case == "unreadable":
        _good_stack(s)
        (s / "layers/top.png").chmod(0)
    elif case == "range-for-normal":
        _good_stack(s, range=[0, 2])
    else:
        raise AssertionError(case)
    return s


HOSTILE = [
    "malformed-json",
    "unknown-blend",
    "missing-png",
    "corrupt-png",
    "truncated-png",
    "not-png",
    "size-mismatch",
    "nan",
    "nan-colour",
    "dotdot-source",
    "absolute-source",
    "symlink-escape",
    "symlink-dir-escape",
    "header-bomb",
    "side-bomb",
    "idat-bomb",
    "source-is-folder",
    "duplicate-id",
    "not-utf8",
    "unreadable",
    "range-for-normal",
]


@pytest.mark.parametrize("case", HOSTILE)
def test_hostile_stack(tmp_path, capsys, case):
    if case == "unreadable" and os.geteuid() == 0:
        pytest.skip("root reads files whatever their mode")
    s = _hostile(tmp_path, case)
    out_png = tmp_path / "out.png"
    out_png.write_bytes(b"precious")
    for argv in (["composite", s, "-o", out_png], ["validate", s], ["export", s, "--ora", out_png]):
        code, out, err = run(capsys, *argv)
        assert code == 2, (argv, out, err)
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("lasagna: error: "), err
        assert "Traceback" not in err and out == ""
        assert out_png.read_bytes() == b"precious"
    assert not (s / "composite.png").exists()


def test_hostile_messages_name_the_problem(tmp_path, capsys):
    expect = {
        "unknown-blend": "layers[1].blend",
        "missing-png": "does not exist",
        "size-mismatch": "mask is 8x5",
        "symlink-escape": "outside the stack folder",
        "header-bomb": "decompression-bomb guard",
        "idat-bomb": "expands beyond",
        "dotdot-source": "escapes the stack folder",
        "malformed-json": "invalid JSON",
    }
    for case, fragment in expect.items():
        s = _hostile(tmp_path / case, case)
        code, _, err = run(capsys, "composite", s, "-o", tmp_path / "o.png")
        assert code == 2 and fragment in err, (case, err)


def _zip(path: Path, entries: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("mimetype", b"image/openraster", compress_type=zipfile.ZIP_STORED)
        for name, data in entries.items():
            zf.writestr(name, data)
    return path


def _xml(*layers: str, w: int = 4, h: int = 3) -> bytes:
    return (f'<?xml version="1.0"?><image w="{w}" h="{h}"><stack>' + "".join(layers) + "</stack></image>").encode()


@pytest.mark.parametrize(
    "case",
    [
        "zip-slip-entry",
        "zip-slip-src",
        "absolute-src",
        "too-deep-stack",
        "unknown-op",
        "bomb-layer",
        "not-zip",
        "no-mimetype",
        "dtd",
        "lone-dodge",
        "missing-src",
    ],
)
def test_hostile_ora(tmp_path, capsys, case):
    png = pngcraft.gray8(4, 3)
    layer = '<layer name="a" src="data/a.png" composite-op="{op}"/>'
    entries = {"stack.xml": _xml(layer.format(op="svg:src-over")), "data/a.png": png}
    if case == "zip-slip-entry":
        entries["../../evil.png"] = png
    elif case == "zip-slip-src":
        entries["stack.xml"] = _xml('<layer name="a" src="../evil.png"/>')
    elif case == "absolute-src":
        entries["stack.xml"] = _xml('<layer name="a" src="/etc/passwd"/>')
    elif case == "too-deep-stack":  # nested groups are read back, but only so deep
        deep = MAX_GROUP_DEPTH + 1
        entries["stack.xml"] = _xml("<stack>" * deep + '<layer name="a" src="data/a.png"/>' + "</stack>" * deep)
    elif case == "unknown-op":
        entries["stack.xml"] = _xml(layer.format(op="svg:vivid-light"))
    elif case == "bomb-layer":
        entries["data/a.png"] = pngcraft.header_bomb()
    elif case == "dtd":
        entries["stack.xml"] = b'<?xml version="1.0"?><!DOCTYPE a [<!ENTITY x "y">]><image w="4" h="3"><stack/></image>'
    elif case == "lone-dodge":  # the helper half of a multiplier above 1, with no multiply below it
        entries["data/_dodge/a.png"] = entries.pop("data/a.png")
        entries["stack.xml"] = _xml('<layer name="a" src="data/_dodge/a.png" composite-op="svg:color-dodge"/>')
    elif case == "missing-src":
        entries["stack.xml"] = _xml('<layer name="a" src="data/zzz.png"/>')
    path = tmp_path / "in.ora"
    if case == "not-zip":
        path.write_bytes(b"PK but not really a zip")
    elif case == "no-mimetype":
        with zipfile.ZipFile(path, "w") as zf:
            for name, data in entries.items():
                zf.writestr(name, data)
    else:
        _zip(path, entries)
    code, out, err = run(capsys, "import-ora", path, "-o", tmp_path / "out")
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and err.startswith("lasagna: error: ") and "Traceback" not in err
    assert not (tmp_path / "out").exists() and not (tmp_path.parent / "evil.png").exists()


def test_unwritable_output_leaves_nothing(tmp_path, capsys):
    if os.geteuid() == 0:
        pytest.skip("root writes anywhere")
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    code, _, err = run(capsys, "composite", BASIC, "-o", ro / "x.png")
    assert code == 2 and "writable" in err


def test_output_under_a_file_is_refused(tmp_path, capsys):
    (tmp_path / "file").write_bytes(b"x")
    for argv in (
        ["composite", BASIC, "-o", tmp_path / "file/x.png"],
        ["export", BASIC, "--layers", tmp_path / "file/d"],
        ["demo", "-o", tmp_path / "file/demo"],
    ):
        code, _, err = run(capsys, *argv)
        assert code == 2 and "not a writable folder" in err and len(err.splitlines()) == 1
    assert (tmp_path / "file").read_bytes() == b"x"


def test_output_is_a_folder(tmp_path, capsys):
    code, _, err = run(capsys, "composite", BASIC, "-o", tmp_path)
    assert code == 2 and "is a folder" in err


def test_usage_error_is_one_line(capsys):
    code, _, err = run(capsys, "composite")
    assert code == 2 and len(err.strip().splitlines()) == 1


def test_keyboard_interrupt_exits_130(monkeypatch, capsys):
    from lasagna.cli import validate

    def boom(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(validate, "run", boom)
    code, out, err = run(capsys, "validate", BASIC)
    assert code == 130 and err == ""


def test_console_script_runs():
    """The installed entry point (a subprocess: the real exit code and stderr)."""
    exe = Path(sys.executable).with_name("lasagna")
    if not exe.exists():
        pytest.skip("lasagna console script not installed in this environment")
    proc = subprocess.run(
        [str(exe), "validate", "/nonexistent/stack"], capture_output=True, text=True, timeout=HANG_SECONDS
    )
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr


def test_help_lists_every_subcommand(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for name in ("composite", "export", "validate", "schema", "import-ora", "demo", "world"):
        assert name in out


@pytest.mark.parametrize("argv", [[name] for name in COMMANDS] + [["prior", "add"]], ids=" ".join)
def test_every_subcommands_help_ends_with_an_example(capsys, argv):
    """Each ``--help`` closes with ``example:`` and a command line of that very subcommand (issue 27)."""
    assert main([*argv, "--help"]) == 0
    out = capsys.readouterr().out
    example = out.split("\nexample:\n", 1)[-1] if "\nexample:\n" in out else ""
    assert example.startswith(f"  lasagna {' '.join(argv)} "), out[-400:]


@pytest.mark.parametrize("torchrun", [False, True])
def test_process_exit_flushes_and_keeps_the_status(torchrun):
    """``process_exit`` (the end of ``python -m lasagna.cli`` and of the ``lasagna`` script): the status is the
    process's, and what was printed reaches a pipe also where a torchrun worker ends by ``os._exit`` (which skips
    interpreter teardown, and with it the flush of block-buffered output)."""
    env = {k: v for k, v in os.environ.items() if k not in ("WORLD_SIZE", "TORCHELASTIC_RUN_ID")}
    if torchrun:
        env.update(WORLD_SIZE="2", TORCHELASTIC_RUN_ID="test")
    code = "import sys; from lasagna.cli import process_exit; print('out'); print('err', file=sys.stderr); "
    code += "process_exit(3)"
    root = Path(__file__).parents[2]
    done = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=HANG_SECONDS, cwd=root
    )
    assert (done.returncode, done.stdout, done.stderr.strip().splitlines()[-1]) == (3, "out\n", "err")
