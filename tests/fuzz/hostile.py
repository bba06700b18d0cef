"""Hostile inputs for the fuzz suite (tests/fuzz/test_hostile.py, benchmarks/hostile.py): hypothesis
strategies for stack folders, PNG files and .ora archives (valid ones, then mutated), and a forked
worker that runs the real CLI on each under a memory ceiling and a CPU-time limit.

A case is ``(files, commands)``: ``files`` maps a relative path to bytes (written to a fresh folder),
``commands`` are argv lists for ``lasagna.cli.main`` in which ``{d}`` stands for that folder. The
contract checked for every command (``check``): exit status 0 or 2, at most one error line, never
"internal error" or "Traceback", and an answer within ``CASE_CPU_SECONDS`` of CPU time per command.
(Warnings, one line each, may precede the error line.)
"""

from __future__ import annotations

import io
import json
import multiprocessing
import os
import resource
import signal
import struct
import sys
import tempfile
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np
from hypothesis import strategies as st
from PIL import Image

from tests.support import bounded

# Per case: the child may grow its address space this far past what the fork inherited (the budget
# of lasagna.limits is 8 GiB, so any large allocation must have been refused before it is tried), and
# may use this many seconds of CPU time per command (RLIMIT_CPU, not the wall clock: a loaded 2-core
# machine stretched a PNG case past a 60 s wall-clock limit; the slowest command here, a tiny-catalogue
# edit, uses about a second of CPU).
HEADROOM_BYTES = 3 * 2**29  # 1.5 GiB
CASE_CPU_SECONDS = 20
# A case that has not answered after this many wall-clock seconds is hung without spending CPU (a deadlock).
HANG_SECONDS = bounded.HANG_SECONDS

Case = tuple[dict[str, bytes], list[list[str]]]

# ---- the worker ---------------------------------------------------------------------------------------


def _vm_size() -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError("no VmSize in /proc/self/status")


def _child(conn, folder: str, commands: list[list[str]], env: dict[str, str]) -> None:
    try:
        limit = _vm_size() + HEADROOM_BYTES
        resource.setrlimit(resource.RLIMIT_AS, (limit, resource.getrlimit(resource.RLIMIT_AS)[1]))
        cpu = CASE_CPU_SECONDS * len(commands)  # a forked child starts at zero CPU time
        resource.setrlimit(resource.RLIMIT_CORE, (0, 0))  # SIGXCPU's default action dumps core
        resource.setrlimit(resource.RLIMIT_CPU, (cpu, cpu + 1))  # SIGXCPU, then SIGKILL a second later
        os.environ.update(env)
        # libgomp is not fork-safe: a child forked while the parent's OpenMP pool runs (any torch op on 2+ threads
        # before the fork, e.g. `-m slow` at OMP_NUM_THREADS=2) deadlocks in its first parallel region. The child
        # computes on one thread, whatever ``env`` says (the CLI's --threads default is at most $OMP_NUM_THREADS).
        os.environ["OMP_NUM_THREADS"] = "1"
        import torch

        torch.set_num_threads(1)
        from lasagna.cli import main

        results = []
        for argv in commands:
            out, err = io.StringIO(), io.StringIO()
            sys.stdout, sys.stderr = out, err
            try:
                code = main([a.replace("{d}", folder) for a in argv])
            except BaseException as exc:  # noqa: BLE001 (anything escaping main is a failure to report)
                code = f"escaped {type(exc).__name__}: {exc}"
            sys.stdout, sys.stderr = sys.__stdout__, sys.__stderr__
            results.append((argv, code, out.getvalue(), err.getvalue()))
        conn.send(results)
    finally:
        conn.close()
        os._exit(0)  # never run the parent's (pytest's) exit handlers


def run_case(files: dict[str, bytes], commands: list[list[str]], env: dict[str, str] | None = None) -> list:
    """Write ``files`` to a fresh folder and run ``commands`` there in a forked child (module docstring).
    Returns ``[(argv, status, stdout, stderr)]``; a hang or a crash is an AssertionError."""
    ctx = multiprocessing.get_context("fork")
    with tempfile.TemporaryDirectory(prefix="lasagna-fuzz-") as folder:
        for rel, data in files.items():
            path = Path(folder, rel)
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)
        receive, send = ctx.Pipe(duplex=False)
        proc = ctx.Process(target=_child, args=(send, folder, commands, env or {}))
        proc.start()
        send.close()
        try:
            if not receive.poll(HANG_SECONDS):
                raise AssertionError(f"no answer within {HANG_SECONDS} s (a hang): {commands}")
            try:
                results = receive.recv()
            except EOFError:
                proc.join(5)
                if proc.exitcode in (-signal.SIGXCPU, -signal.SIGKILL):
                    cpu = CASE_CPU_SECONDS * len(commands)
                    raise AssertionError(f"no answer within {cpu} CPU seconds (a hang): {commands}") from None
                raise AssertionError(f"the worker died (exit {proc.exitcode}): {commands}") from None
        finally:
            if proc.is_alive():
                proc.kill()
            proc.join(5)
            receive.close()
    return results


def check(results: list) -> None:
    """The contract for every command's result (module docstring). Warnings (``lasagna: warning: …``, one
    line each: e.g. a layer OpenRaster cannot express) are allowed beside the one error line."""
    for argv, code, out, err in results:
        where = f"lasagna {' '.join(argv)}"
        assert code in (0, 2), f"{where}: exit {code!r}; stderr: {err}"
        assert "internal error" not in err and "Traceback" not in err, f"{where}: {err}"
        errors = [line for line in err.splitlines() if not line.startswith("lasagna: warning: ")]
        assert len(errors) <= 1, f"{where}: stderr has {len(errors)} lines that are not warnings:\n{err}"
        if code == 2:
            assert errors and errors[0].startswith("lasagna"), f"{where}: exit 2 without a message; stderr: {err!r}"


# ---- hostile values -------------------------------------------------------------------------------------

HOSTILE_PATHS = [
    "../x.png",
    "layers/../../x.png",
    "/etc/passwd",
    "/dev/zero",
    "C:\\x.png",
    "\\\\server\\share\\x.png",
    "~/x.png",
    "layers/",
    "layers/a.png/",
    "layers/a.png\x00.txt",
    "a" * 5000 + ".png",
    "/".join(["d"] * 300) + "/x.png",
    "layers/ä\u202e.png",
    "",
    ".",
    "stack.json",
]

HUGE_NUMBERS = [
    -1,
    0,
    1,
    2**31 - 1,
    2**31,
    2**53 + 1,
    2**63,
    -(2**63),
    10**19,
    65536,
    32768,
    32769,
    1e308,
    -1e308,
    5e-324,
]

leaf_values = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.sampled_from(HUGE_NUMBERS),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
    st.text(alphabet=st.characters(min_codepoint=0x300, max_codepoint=0x10FFFF), max_size=8),
    st.sampled_from(HOSTILE_PATHS),
    st.sampled_from(["normal", "multiply", "plus", "pixels", "solid", "learned", "srgb", "linear", "layer"]),
)
hostile_values = st.recursive(
    leaf_values,
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=8), inner, max_size=4)),
    max_leaves=8,
)


class Pairs(list):
    """A JSON object as a list of (key, value) pairs, so a key can appear twice."""


def dumps(value: Any) -> str:
    """JSON text of ``value`` (``Pairs`` as objects, duplicates kept; NaN and ±Infinity as Python writes them)."""
    if isinstance(value, Pairs):
        return "{" + ", ".join(f"{json.dumps(str(k))}: {dumps(v)}" for k, v in value) + "}"
    if isinstance(value, dict):
        return dumps(Pairs(value.items()))
    if isinstance(value, list):
        return "[" + ", ".join(dumps(v) for v in value) + "]"
    return json.dumps(value)


def _paths(value: Any, prefix: tuple = ()) -> list[tuple]:
    out = [prefix]
    if isinstance(value, dict):
        for k, v in value.items():
            out += _paths(v, (*prefix, k))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            out += _paths(v, (*prefix, i))
    return out


@st.composite
def mutated_json(draw, document: Any, max_mutations: int = 3) -> str:
    """``document`` with 0..max_mutations mutations (drop, duplicate key, wrong type, hostile value, deep
    nesting), as JSON text; sometimes the text itself is cut or given a byte that is not UTF-8."""
    doc = json.loads(json.dumps(document))
    wrap = 0  # very deep nesting is added to the text at the end: built as structure, the harness itself recurses
    for _ in range(draw(st.integers(0, max_mutations))):
        path = draw(st.sampled_from(_paths(doc)))
        parent, key = (None, None) if not path else (_get(doc, path[:-1]), path[-1])
        kind = draw(st.sampled_from(["drop", "replace", "replace", "nest", "duplicate", "add"]))
        if parent is None:
            if kind == "replace":
                doc = draw(hostile_values)
            continue
        if kind == "drop":
            del parent[key]
        elif kind == "replace":
            parent[key] = draw(hostile_values)
        elif kind == "nest":
            depth = draw(st.sampled_from([2, 10, 63, 64, 65, 1000]))
            if depth > 100:
                wrap = max(wrap, depth)
                continue
            value = parent[key]
            for _ in range(depth):
                value = [value]
            parent[key] = value
        elif kind == "duplicate" and isinstance(parent, dict):
            parent[key] = _Dup(parent[key], draw(hostile_values))
        elif kind == "add" and isinstance(parent, dict):
            parent[draw(st.text(max_size=10))] = draw(hostile_values)
    text = dumps(_undup(doc))
    text = "[" * wrap + text + "]" * wrap
    tail = draw(st.sampled_from(["", "", "", "", "cut", "latin1", "bom", "garbage"]))
    if tail == "cut" and text:
        text = text[: draw(st.integers(0, len(text) - 1))]
    elif tail == "latin1":
        return text + "\udcff"  # written with surrogateescape: one byte 0xff
    elif tail == "bom":
        text = "\ufeff" + text
    elif tail == "garbage":
        text += draw(st.text(max_size=5))
    return text


class _Dup:
    def __init__(self, first, second):
        self.first, self.second = first, second


def _undup(value: Any) -> Any:
    if isinstance(value, _Dup):  # a duplicated key's value that a later mutation moved out of its object
        return _undup(value.first)
    if isinstance(value, dict):
        pairs = Pairs()
        for k, v in value.items():
            if isinstance(v, _Dup):
                pairs += [(k, _undup(v.first)), (k, _undup(v.second))]
            else:
                pairs.append((k, _undup(v)))
        return pairs
    if isinstance(value, list):
        return [_undup(v) for v in value]
    return value


def _get(value: Any, path: tuple) -> Any:
    for key in path:
        value = value[key]
    return value


def text_bytes(text: str) -> bytes:
    return text.encode("utf-8", "surrogateescape")


# ---- PNGs -----------------------------------------------------------------------------------------------

PNG_MODES = ["L", "LA", "RGB", "RGBA", "P", "I;16", "1"]


def png_of(mode: str, w: int, h: int, seed: int) -> bytes:
    """A valid small PNG written by Pillow."""
    rng = np.random.default_rng(seed)
    if mode == "I;16":
        im = Image.fromarray(rng.integers(0, 65536, (h, w)).astype(np.uint16))
    elif mode == "1":
        im = Image.fromarray(rng.integers(0, 2, (h, w)).astype(bool))
    elif mode == "P":
        im = Image.fromarray(rng.integers(0, 4, (h, w)).astype(np.uint8), mode="P")
        im.putpalette(list(rng.integers(0, 256, 12)))
    else:
        planes = {"L": 1, "LA": 2, "RGB": 3, "RGBA": 4}[mode]
        codes = rng.integers(0, 256, (h, w, planes)).astype(np.uint8)
        im = Image.fromarray(codes[:, :, 0] if planes == 1 else codes, mode=mode)
    buf = io.BytesIO()
    kwargs = {"transparency": 1} if mode == "P" and seed % 2 else {}
    im.save(buf, format="PNG", **kwargs)
    return buf.getvalue()


def _chunk_offsets(data: bytes) -> list[int]:
    out, pos = [], 8
    while pos + 8 <= len(data):
        out.append(pos)
        pos += 12 + struct.unpack(">I", data[pos : pos + 4])[0]
    return out


@st.composite
def png_files(draw) -> bytes:
    """A valid PNG, then 0..3 of: byte flips, truncation, a chunk's length field rewritten, IHDR's size
    rewritten (up to 2³¹−1, CRC fixed or not), an extra chunk, bytes appended."""
    data = bytearray(
        png_of(
            draw(st.sampled_from(PNG_MODES)), draw(st.integers(1, 9)), draw(st.integers(1, 9)), draw(st.integers(0, 9))
        )
    )
    for _ in range(draw(st.integers(0, 3))):
        kind = draw(st.sampled_from(["flip", "cut", "length", "ihdr", "ihdr", "chunk", "append"]))
        if kind == "flip" and data:
            i = draw(st.integers(0, len(data) - 1))
            data[i] ^= draw(st.integers(1, 255))
        elif kind == "cut" and data:
            del data[draw(st.integers(0, len(data) - 1)) :]
        elif kind == "length" and _chunk_offsets(bytes(data)):
            pos = draw(st.sampled_from(_chunk_offsets(bytes(data))))
            data[pos : pos + 4] = struct.pack(">I", draw(st.sampled_from([0, 1, 13, 2**31 - 1, 2**32 - 1, 1 << 20])))
        elif kind == "ihdr" and len(data) >= 33:
            side = st.sampled_from([0, 1, 2, 255, 32768, 32769, 65535, 2**24, 2**31 - 1])
            data[16:24] = struct.pack(">II", draw(side), draw(side))
            if draw(st.booleans()):
                data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
        elif kind == "chunk" and len(data) >= 33:
            ctype = draw(st.sampled_from([b"tEXt", b"iCCP", b"PLTE", b"tRNS", b"IDAT", b"sBIT", b"zTXt", b"abCD"]))
            body = draw(st.binary(max_size=32))
            piece = struct.pack(">I", len(body)) + ctype + body + struct.pack(">I", zlib.crc32(ctype + body))
            data[33:33] = piece
        elif kind == "append":
            data += draw(st.binary(max_size=64))
    return bytes(data)


# ---- stack folders --------------------------------------------------------------------------------------


@st.composite
def stack_documents(draw) -> dict[str, Any]:
    """A valid small stack (a pixels base, maybe a 16-bit ranged layer with a mask, a solid, a learned
    layer waiting to be rendered) and the PNGs it names."""
    w, h = draw(st.integers(1, 12)), draw(st.integers(1, 12))
    files = {"layers/a.png": png_of("RGB", w, h, draw(st.integers(0, 9)))}
    layers: list[dict] = [{"id": "a", "kind": "pixels", "source": "layers/a.png"}]
    if draw(st.booleans()):
        bw, bh = draw(st.integers(1, 12)), draw(st.integers(1, 12))
        files["layers/b.png"] = png_of("I;16", bw, bh, 1)
        files["masks/b.png"] = png_of("L", bw, bh, 2)
        layers.append(
            {
                "id": "b",
                "kind": "pixels",
                "source": "layers/b.png",
                "mask": "masks/b.png",
                "blend": "multiply",
                "range": [0.0, 2.0],
                "opacity": 0.5,
                "offset": {"x": draw(st.integers(-4, 12)), "y": draw(st.integers(-4, 12))},
            }
        )
    if draw(st.booleans()):
        layers.append({"id": "s", "kind": "solid", "color": [0.2, 0.4, 0.6, 0.5], "blend": "screen"})
    if draw(st.booleans()):
        layers.append(
            {
                "id": "l",
                "kind": "learned",
                "preset": "shading",
                "condition": {"label": "left"},
                "conditioned_on": "a",
                "blend": "multiply",
                "range": [0, 2],
            }
        )
    doc = {
        "format": "lasagna.stack",
        "version": 1,
        "canvas": {"width": w, "height": h, "background": [0.1, 0.2, 0.3]},
        "blend_space": draw(st.sampled_from(["srgb", "linear"])),
        "clamp": "layer",
        "layers": layers,
    }
    return {"doc": doc, "files": files}


@st.composite
def stack_cases(draw) -> Case:
    """(a) a stack folder, valid or near-valid: the document mutated, sometimes a PNG too."""
    base = draw(stack_documents())
    files = dict(base["files"])
    files["stack.json"] = text_bytes(draw(mutated_json(base["doc"])))
    if draw(st.integers(0, 4)) == 0:
        files[draw(st.sampled_from(sorted(base["files"])))] = draw(png_files())
    commands = [
        ["validate", "{d}"],
        ["composite", "{d}", "-o", "{d}/out/c.png"],
        ["export", "{d}", "--ora", "{d}/out/x.ora"],
    ]
    return files, commands


@st.composite
def png_cases(draw) -> Case:
    """(b) PNG bytes as a stack's layer and mask and as ``lasagna edit``'s input image."""
    data = draw(png_files())
    doc = {
        "format": "lasagna.stack",
        "version": 1,
        "canvas": {"width": 8, "height": 8},
        "layers": [{"id": "a", "kind": "pixels", "source": "a.png", "blend": "multiply", "range": [0, 2]}],
    }
    files = {"stack.json": json.dumps(doc).encode(), "a.png": data, "x.png": data}
    commands = [
        ["validate", "{d}"],
        ["composite", "{d}", "-o", "{d}/out/c.png"],
        ["edit", "{d}/x.png", "--condition", "left", "-o", "{d}/edited", "--no-ora"],
    ]
    return files, commands


# ---- .ora archives --------------------------------------------------------------------------------------


def base_oras() -> list[dict[str, bytes]]:
    """The entries of a few valid .ora files written by ``lasagna.export.ora`` from small random stacks."""
    from lasagna.export.ora import encode_ora
    from lasagna.io.stack import load_stack
    from tests.support.stackcraft import random_stack

    out = []
    with tempfile.TemporaryDirectory() as folder:
        for seed in range(3):
            stack = load_stack(random_stack(Path(folder, str(seed)), seed, unit_only=True, n_layers=2))
            with zipfile.ZipFile(io.BytesIO(encode_ora(stack, warn=lambda m: None))) as zf:
                out.append({i.filename: zf.read(i) for i in zf.infolist()})
    return out


_ORA_ATTRS = ["w", "h", "x", "y", "opacity", "visibility", "composite-op", "src", "name", "version"]
_ORA_VALUES = [
    "0",
    "-1",
    "1e999",
    "nan",
    "inf",
    "2147483647",
    "99999999999999999999999",
    "0.5",
    "hidden",
    "svg:color-dodge",
    "svg:bogus",
    "../x.png",
    "/etc/passwd",
    "data/a.png",
    "mergedimage.png",
    "stack.xml",
    "",
    "é\u202e",
]


@st.composite
def ora_files(draw, bases: list[dict[str, bytes]]) -> bytes:
    """A valid .ora, then 0..3 of: an XML attribute rewritten, the XML cut or given a DTD or another
    encoding, an entry dropped, renamed (``..``, absolute, long) or replaced by a mutated PNG, an entry
    duplicated, a layer element repeated."""
    entries = dict(draw(st.sampled_from(bases)))
    names = [n for n in entries if n not in ("mimetype", "stack.xml")]
    for _ in range(draw(st.integers(0, 3))):
        kind = draw(st.sampled_from(["attr", "attr", "xml", "drop", "rename", "png", "repeat", "mimetype"]))
        xml = entries.get("stack.xml", b"").decode("utf-8", "replace")
        if kind == "attr":
            attr = draw(st.sampled_from(_ORA_ATTRS))
            value = draw(st.one_of(st.sampled_from(_ORA_VALUES), st.text(max_size=6).map(lambda s: s.replace('"', ""))))
            marker = f' {attr}="'
            start = xml.find(marker) + len(marker) if marker in xml else -1
            close = xml.find('"', start) if start >= 0 else -1
            if close >= 0:  # an earlier mutation may have cut the attribute
                xml = xml[:start] + value + xml[close:]
            entries["stack.xml"] = xml.encode()
        elif kind == "xml":
            how = draw(st.sampled_from(["cut", "dtd", "utf16", "latin1", "nest"]))
            if how == "cut":
                entries["stack.xml"] = xml[: draw(st.integers(0, max(0, len(xml) - 1)))].encode()
            elif how == "dtd":
                entries["stack.xml"] = xml.replace("<image", '<!DOCTYPE image [<!ENTITY e "x">]><image', 1).encode()
            elif how == "utf16":
                entries["stack.xml"] = xml.encode("utf-16")
            elif how == "latin1":
                entries["stack.xml"] = xml.replace("UTF-8", "ISO-8859-1").encode("latin-1", "replace")
            else:
                depth = draw(st.sampled_from([10, 200, 5000]))
                entries["stack.xml"] = xml.replace("<stack>", "<stack>" * depth, 1).encode()
        elif kind == "drop" and names:
            entries.pop(draw(st.sampled_from(names)), None)
        elif kind == "rename" and names:
            old = draw(st.sampled_from(names))
            new = draw(
                st.sampled_from(
                    ["../evil.png", "/abs.png", "data/" + "n" * 300 + ".png", "data\\x.png", "data/./x.png"]
                )
            )
            if old in entries:
                entries[new] = entries.pop(old)
        elif kind == "png" and names:
            entries[draw(st.sampled_from(names))] = draw(png_files())
        elif kind == "repeat":
            match = xml.find("<layer ")
            end = xml.find("/>", match) + 2 if match >= 0 else 1
            if match >= 0 and end > 1:  # an earlier mutation may have cut the element
                entries["stack.xml"] = (xml[:end] + xml[match:end] * draw(st.integers(1, 40)) + xml[end:]).encode()
        elif kind == "mimetype":
            entries["mimetype"] = draw(st.sampled_from([b"", b"image/png", b"image/openraster" * 10]))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        if "mimetype" in entries:
            zf.writestr("mimetype", entries.pop("mimetype"), compress_type=zipfile.ZIP_STORED)
        for name, data in entries.items():
            zf.writestr(name, data, compress_type=zipfile.ZIP_DEFLATED)
        if draw(st.integers(0, 9)) == 0 and names:  # a second entry of one name
            zf.writestr(names[0], png_of("L", 2, 2, 0))
    return buf.getvalue()


@st.composite
def ora_cases(draw, bases: list[dict[str, bytes]]) -> Case:
    """(c) an .ora archive through ``lasagna import-ora``."""
    return {"x.ora": draw(ora_files(bases))}, [["import-ora", "{d}/x.ora", "-o", "{d}/imported"]]


__all__ = [
    "CASE_CPU_SECONDS",
    "HANG_SECONDS",
    "check",
    "ora_cases",
    "png_cases",
    "run_case",
    "stack_cases",
    "base_oras",
]
