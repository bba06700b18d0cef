"""Edits at scale (``lasagna.batch``, ``lasagna edit`` with many inputs) on the tiny catalogue
(tests/support/tinylayers.py): inputs and names, skipping complete outputs and finishing after a kill, failures
per input, equality with one-at-a-time ``edit``, and two processes against one.

Batched forward passes and float order, measured here (``test_batched_forward_within_tolerance``): a
batch of 4 differs from four single passes by at most a few float32 ulps of the generator's output
(2.4e-7 for the shipped shading generator at 64²), i.e. at most one 16-bit code of the stored layer.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from lasagna.batch import collect_inputs, edit_many, is_complete, output_names, shard
from lasagna.cli import main
from lasagna.editing import edit
from lasagna.errors import LasagnaError, PathError
from lasagna.request import EditRequest
from tests.support.bounded import HANG_SECONDS
from tests.support.tinylayers import ROOT


@pytest.fixture(autouse=True)
def _catalogue(tiny, monkeypatch):
    monkeypatch.setenv("LASAGNA_LAYERS", str(tiny))


def _images(folder: Path, count: int, size: tuple[int, int] = (12, 16), suffix: str = ".png") -> list[Path]:
    """``count`` small random RGB images ``img-<k>`` in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(count)
    paths = []
    for k in range(count):
        path = folder / f"img-{k}{suffix}"
        Image.fromarray(rng.integers(0, 256, (*size, 3), dtype=np.uint8)).save(path)
        paths.append(path)
    return paths


def _files(folder: Path) -> dict[str, bytes]:
    """A stack folder's files by relative path; stack.json without its metadata (times), stack.ora left out."""
    found = {}
    for p in sorted(folder.rglob("*")):
        rel = p.relative_to(folder).as_posix()
        if p.is_file() and rel != "stack.ora":
            data = p.read_bytes()
            if rel == "stack.json":
                doc = json.loads(data)
                doc.pop("metadata", None)
                data = json.dumps(doc, sort_keys=True).encode()
            found[rel] = data
    return found


def run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


# ---- inputs and names -------------------------------------------------------------------------------


class TestInputs:
    def test_folder_glob_and_files_sorted_and_deduplicated(self, tmp_path):
        a = _images(tmp_path / "a", 3)
        b = _images(tmp_path / "b" / "deep", 2, suffix=".jpg")
        (tmp_path / "a" / "notes.txt").write_text("not an image")
        found = collect_inputs([tmp_path / "a", str(tmp_path / "b" / "**" / "*.jpg"), a[1]])
        assert found == sorted(a + b, key=lambda p: os.path.abspath(p))

    def test_a_stack_folder_is_one_input_and_a_folder_of_stacks_lists_them(self, tmp_path, capsys):
        _images(tmp_path / "in", 1)
        assert run(capsys, "edit", tmp_path / "in" / "img-0.png", "--condition", "left", "-o", tmp_path / "s")[0] == 0
        assert collect_inputs([tmp_path / "s"]) == [tmp_path / "s"]
        shutil.copytree(tmp_path / "s", tmp_path / "stacks" / "one")
        assert collect_inputs(tmp_path / "stacks") == [tmp_path / "stacks" / "one"]
        assert output_names([tmp_path / "s", tmp_path / "s" / "stack.json"]) == ["s", "s-2"]

    def test_unique_stems_in_sorted_order(self, tmp_path):
        for name in ("a.png", "a.jpg", "A.webp", "b.png"):
            (tmp_path / name).touch()
        found = collect_inputs(str(tmp_path / "*"))
        assert [p.name for p in found] == ["A.webp", "a.jpg", "a.png", "b.png"]
        assert output_names(found) == ["A", "a-2", "a-3", "b"]  # case-insensitive: A and a are one folder on macOS
        assert output_names([torch.zeros(3, 4, 4)] * 12)[:2] == ["image-01", "image-02"]

    def test_a_pattern_or_folder_finding_nothing_is_refused(self, tmp_path):
        (tmp_path / "empty").mkdir()
        with pytest.raises(PathError, match="matches no image file or stack folder"):
            collect_inputs(str(tmp_path / "*.png"))
        with pytest.raises(PathError, match="holds no image file or stack folder"):
            collect_inputs(tmp_path / "empty")

    def test_shards_are_chunks_dealt_round_robin(self):
        assert shard(5, 1, 1, 2) == [[1], [3]]  # inputs[rank::world]
        assert shard(7, 2, 0, 2) == [[0, 1], [4, 5]] and shard(7, 2, 1, 2) == [[2, 3], [6]]
        every = sorted(i for r in range(3) for c in shard(10, 3, r, 3) for i in c)
        assert every == list(range(10))


# ---- resumption and failures ---------------------------------------------------------------------------


def _dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_rerun_after_a_kill_finishes_the_rest_and_redoes_nothing(tmp_path, capsys):
    images = _images(tmp_path / "in", 4)
    out = tmp_path / "out"
    code, stdout, err = run(capsys, "edit", tmp_path / "in", "--condition", "left", "-o", out)
    assert code == 0, err
    assert stdout.strip().splitlines()[-1].startswith(f"{out}/: edited 4, skipped 0 (complete), failed 0")
    assert all(is_complete(out / p.stem) for p in images)
    # A kill: two outputs never renamed into place, one of them left as its dead writer's temporary folder.
    shutil.rmtree(out / "img-1")
    shutil.rmtree(out / "img-3")
    litter = out / f".img-3.lasagna-{_dead_pid()}-0badf00d.tmp"
    (litter / "layers").mkdir(parents=True)
    (litter / "stack.json").write_text("{")
    kept = {n: ((out / n / "stack.json").stat().st_ino, (out / n).stat().st_mtime_ns) for n in ("img-0", "img-2")}
    code, stdout, err = run(capsys, "edit", str(tmp_path / "in" / "*.png"), "--condition", "left", "-o", out)
    assert code == 0, err
    assert stdout.strip().splitlines()[-1].startswith(f"{out}/: edited 2, skipped 2 (complete), failed 0")
    for name in ("img-0", "img-2"):  # not rewritten: the same files
        assert ((out / name / "stack.json").stat().st_ino, (out / name).stat().st_mtime_ns) == kept[name]
    assert all(is_complete(out / p.stem) for p in images)
    assert sorted(p.name for p in out.iterdir()) == [p.stem for p in images]  # the litter swept
    # --force redoes them all
    assert run(capsys, "edit", tmp_path / "in", "--condition", "left", "-o", out, "--force")[1].count("edited 4")


def test_an_interrupted_run_leaves_complete_outputs_only(tmp_path, monkeypatch):
    """Ctrl-C (or SIGTERM, which the CLI raises as Ctrl-C) while staged folders wait for their commit: the one
    renamed in is complete, the rest are removed, and the next run finishes them."""
    import lasagna.batch

    monkeypatch.setattr(lasagna.batch, "COMMIT_EVERY", 100)
    monkeypatch.setattr(lasagna.batch, "COMMIT_SECONDS", 100.0)
    images = _images(tmp_path / "in", 4)

    def interrupt(outcome):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        edit_many(images, "shading", "left", tmp_path / "out", progress=interrupt)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["img-0"] and is_complete(tmp_path / "out" / "img-0")
    report = edit_many(images, "shading", "left", tmp_path / "out")
    assert report.summary() == "edited 3, skipped 1 (complete), failed 0"


def test_one_corrupt_input_fails_alone(tmp_path, capsys):
    _images(tmp_path / "in", 3)
    bad = tmp_path / "in" / "img-1.png"
    bad.write_bytes(bad.read_bytes()[:60])  # truncated
    out = tmp_path / "out"
    code, stdout, err = run(capsys, "edit", tmp_path / "in", "--condition", "left", "-o", out)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"lasagna: error: {bad}: ") and "expected" in lines[0]
    assert "edited 2, skipped 0 (complete), failed 1" in stdout
    assert is_complete(out / "img-0") and is_complete(out / "img-2") and not (out / "img-1").exists()
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == []


def test_a_fifo_among_the_inputs_fails_alone(tmp_path, capsys):
    """Issue #28 (3): a named pipe is one line, not a read that blocks the batch forever; the others are edited."""
    import threading

    images = _images(tmp_path / "in", 2)
    fifo = tmp_path / "in" / "pipe.png"
    os.mkfifo(fifo)
    box: list = []
    argv = ["edit", *images, fifo, "--condition", "left", "-o", tmp_path / "out"]
    thread = threading.Thread(target=lambda: box.append(run(capsys, *argv)), daemon=True)
    thread.start()
    thread.join(120)  # a hang guard, not a timing
    assert box, "the batch blocked on the FIFO"
    code, stdout, err = box[0]
    assert code == 2
    assert err.strip().splitlines() == [
        f"lasagna: error: {fifo}: is not a regular file (a named pipe (FIFO)); expected an image file or a stack folder"
    ]
    assert "edited 2, skipped 0 (complete), failed 1" in stdout
    assert all(is_complete(tmp_path / "out" / p.stem) for p in images)


def test_a_name_with_a_newline_is_one_escaped_line(tmp_path, capsys):
    """Issue #28 (17): a failing input whose name holds a newline is still one line on stderr."""
    _images(tmp_path / "in", 1)
    bad = tmp_path / "in" / "two\nlines.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n")  # a signature and nothing else
    code, stdout, err = run(capsys, "edit", tmp_path / "in", "--condition", "left", "-o", tmp_path / "out")
    assert code == 2 and "edited 1, skipped 0 (complete), failed 1" in stdout
    (line,) = err.strip().splitlines()
    assert line.startswith(f"lasagna: error: {tmp_path}/in/two\\nlines.png: ") and "expected" in line
    assert line.count("lines.png") == 1  # the place is not repeated


def test_refusals_before_any_work(tmp_path):
    images = _images(tmp_path / "in", 2)
    with pytest.raises(LasagnaError, match="label 'nowhere'|nowhere"):
        edit_many(images, "shading", "nowhere", tmp_path / "out")
    with pytest.raises(LasagnaError, match="positive integer"):
        edit_many(images, "shading", "left", tmp_path / "out", batch_size=0)
    (tmp_path / "file").touch()
    with pytest.raises(PathError, match="not a folder"):
        edit_many(images, "shading", "left", tmp_path / "file")
    assert not (tmp_path / "out").exists()


# ---- equal to one at a time -----------------------------------------------------------------------------


# A surface layer (the shading preset's default kind) is made by its estimator, never the generator's batched pass.
@pytest.mark.parametrize(
    "options",
    [
        dict(generator="amortised"),
        dict(generator="free", optimize=2),
        dict(request=EditRequest(preset="shading", condition="top", layer_kind="surface")),
    ],
)
def test_equals_edit_one_at_a_time(tmp_path, options):
    images = _images(tmp_path / "in", 3) + _images(tmp_path / "other", 1, size=(20, 9))
    report = edit_many(images, "shading", "top", tmp_path / "many", **options)
    assert report.ok and len(report.done) == 4
    for p, name in zip(images, output_names(images)):
        alone = edit(p, "shading", "top", **options).save(tmp_path / "alone" / name)
        assert _files(tmp_path / "many" / name) == _files(alone)


def _weights(folder: Path) -> list[Path]:
    return sorted(folder.glob("*/generators/*/model.safetensors"))


def test_generator_weights_are_written_once_and_hard_linked(tmp_path, tiny, monkeypatch):
    """Every stack folder of a run carries the generator's weights, one file on disk (its link count is the
    number of folders: the run's store is gone); each folder is still edit's, and loads on its own."""
    import lasagna.io.folder as folder_mod

    monkeypatch.setattr(folder_mod, "SHARE_MIN_BYTES", 0)  # the tiny generator is smaller than the real 2 MB
    images = _images(tmp_path / "in", 3)
    assert edit_many(images, "shading", "left", tmp_path / "many", generator="amortised").ok
    weights = _weights(tmp_path / "many")
    assert len(weights) == 3 and len({os.stat(p).st_ino for p in weights}) == 1
    assert os.stat(weights[0]).st_nlink == 3
    assert weights[0].read_bytes() == (tiny / "shading" / "generator" / "model.safetensors").read_bytes()
    assert sorted(p.name for p in (tmp_path / "many").iterdir()) == [p.stem for p in images]  # no store left
    alone = edit(images[1], "shading", "left", generator="amortised").save(tmp_path / "alone")
    assert _files(tmp_path / "many" / images[1].stem) == _files(alone)
    shutil.rmtree(tmp_path / "many" / images[0].stem)  # removing one folder leaves the others whole
    assert (
        weights[1].read_bytes()
        == weights[2].read_bytes()
        == (alone / weights[1].relative_to(tmp_path / "many" / images[1].stem)).read_bytes()
    )


def test_weights_are_copied_where_links_fail(tmp_path, monkeypatch):
    import lasagna.io.folder as folder_mod

    def refuse(src, dst):
        raise OSError(1, "Operation not permitted")

    monkeypatch.setattr(folder_mod, "SHARE_MIN_BYTES", 0)
    monkeypatch.setattr(folder_mod.os, "link", refuse)
    images = _images(tmp_path / "in", 2)
    assert edit_many(images, "shading", "left", tmp_path / "many", generator="amortised").ok
    weights = _weights(tmp_path / "many")
    assert len({os.stat(p).st_ino for p in weights}) == 2 and weights[0].read_bytes() == weights[1].read_bytes()
    assert sorted(p.name for p in (tmp_path / "many").iterdir()) == [p.stem for p in images]


def test_batched_forward_within_tolerance(tmp_path):
    images = _images(tmp_path / "in", 4)
    edit_many(images, "shading", "left", tmp_path / "one", generator="amortised")
    report = edit_many(images, "shading", "left", tmp_path / "four", generator="amortised", batch_size=4)
    assert report.ok
    worst = 0
    for p in images:
        a, b = (np.asarray(Image.open(tmp_path / d / p.stem / "layers" / "shading-left.png")) for d in ("one", "four"))
        worst = max(worst, int(np.abs(a.astype(np.int64) - b.astype(np.int64)).max()))
    assert worst <= 1  # 16-bit codes: float order within a batch moves a value by a few ulps at most


def test_the_api_takes_tensors_and_paths(tmp_path):
    (path,) = _images(tmp_path / "in", 1)
    picture = torch.rand(3, 10, 10)
    seen = []
    report = edit_many([picture, path, picture.numpy()], "shading", "left", tmp_path / "out", progress=seen.append)
    assert [o.status for o in report.outcomes] == ["done"] * 3 and len(seen) == 3
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["image-2", "image-3", "img-0"]
    assert (
        _files(tmp_path / "out" / "image-2")["layers/base.png"]
        == _files(tmp_path / "out" / "image-3")["layers/base.png"]
    )


# ---- processes ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "how", [["--generator", "free", "--optimize", "2"], ["--generator", "amortised", "--batch-size", "2"]]
)
def test_two_processes_equal_one(tmp_path, tiny, capsys, how):
    """torchrun --nproc_per_node=2 (gloo) against one process: per-image runs, and batches of 2 (chunks of the
    whole sorted list, so the same batches whichever process runs them)."""
    images = _images(tmp_path / "in", 5)
    argv = ["edit", str(tmp_path / "in"), "--condition", "right", *how]
    code, _, err = run(capsys, *argv, "-o", tmp_path / "one")
    assert code == 0, err
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT), "LASAGNA_LAYERS": str(tiny)}
    cmd = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", "--standalone", "-m", "lasagna.cli"]
    done = subprocess.run(
        [*cmd, *argv, "-o", str(tmp_path / "two")],
        env=env,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=HANG_SECONDS,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip().splitlines()[-1].startswith(f"{tmp_path / 'two'}/ (2 processes): edited 5, skipped 0")
    for p in images:
        assert _files(tmp_path / "two" / p.stem) == _files(tmp_path / "one" / p.stem), p.stem


# ---- outputs matched to their sources (issue #28, 4; issue #27) ------------------------------------------


def _record(folder: Path) -> dict:
    from lasagna.batch import read_record

    record = read_record(folder)
    assert record is not None, folder
    return record


def test_an_added_file_of_the_same_stem_does_not_take_the_other_ones_folder(tmp_path, capsys):
    """Issue #28 (4): photo.jpg added beside photo.png must not take photo/ (made from photo.png) and be skipped
    while photo.png is redone as photo-2/: each folder belongs to the source it records."""
    (png,) = _images(tmp_path / "in", 1)
    png = png.rename(tmp_path / "in" / "photo.png")
    out = tmp_path / "out"
    code, stdout, err = run(capsys, "edit", tmp_path / "in", "--condition", "left", "-o", out)
    assert code == 0, err
    made = (out / "photo" / "stack.json").stat().st_ino
    assert _record(out / "photo")["source"]["path"] == "photo.png"
    Image.open(png).convert("RGB").save(tmp_path / "in" / "photo.jpg")  # sorts before photo.png
    code, stdout, err = run(capsys, "edit", tmp_path / "in", "--condition", "left", "-o", out)
    assert code == 0, err
    assert "edited 1, skipped 1 (complete), failed 0" in stdout
    assert (out / "photo" / "stack.json").stat().st_ino == made  # photo.png's, untouched
    assert _record(out / "photo")["source"]["path"] == "photo.png"
    assert _record(out / "photo-2")["source"]["path"] == "photo.jpg"
    assert sorted(p.name for p in out.iterdir()) == ["photo", "photo-2"]
    # the same names however the inputs are named: a glob, the files one by one
    for argv in ([str(tmp_path / "in" / "photo.*")], [tmp_path / "in" / "photo.png", tmp_path / "in" / "photo.jpg"]):
        code, stdout, err = run(capsys, "edit", *argv, "--condition", "left", "-o", out)
        assert code == 0 and "edited 0, skipped 2 (complete), failed 0" in stdout, (stdout, err)


def test_a_rerun_asking_for_something_else_is_refused_per_file_not_skipped(tmp_path, capsys):
    """Issue #27: a re-run with another condition (or layer) must not print "skipped (complete)"."""
    images = _images(tmp_path / "in", 2)
    out = tmp_path / "out"
    assert run(capsys, "edit", tmp_path / "in", "--condition", "left", "-o", out)[0] == 0
    code, stdout, err = run(capsys, "edit", tmp_path / "in", "--condition", "right", "-o", out)
    assert code == 2 and "edited 0, skipped 0 (complete), failed 2" in stdout
    lines = err.strip().splitlines()
    assert len(lines) == 2
    for line, p in zip(lines, images):
        assert line.startswith(f"lasagna: error: {p}: {out / p.stem}: was made with condition 'left' (asked now: ")
        assert "'right'" in line and "--force redoes it" in line
    code, stdout, err = run(capsys, "edit", tmp_path / "in", "--condition", "right", "-o", out, "--force")
    assert code == 0 and "edited 2" in stdout, err
    assert _record(out / images[0].stem)["request"]["condition"] == "right"
    code, stdout, err = run(capsys, "edit", tmp_path / "in", "--condition", "right", "-o", out, "--generator", "free")
    assert code == 2 and "generator (default) (asked now: 'free')" in err


def test_a_changed_source_is_redone_in_place_and_said(tmp_path, capsys):
    images = _images(tmp_path / "in", 2)
    out = tmp_path / "out"
    assert run(capsys, "edit", tmp_path / "in", "--condition", "left", "-o", out)[0] == 0
    kept = (out / images[1].stem / "stack.json").stat().st_ino
    Image.new("RGB", (16, 12), (200, 10, 10)).save(images[0])
    code, stdout, err = run(capsys, "edit", tmp_path / "in", "--condition", "left", "-o", out)
    assert code == 0 and "edited 1, skipped 1 (complete), failed 0" in stdout, err
    assert f"{images[0]}: redone: its source changed since this output was made ({out / images[0].stem})" in stdout
    assert (
        _record(out / images[0].stem)["source"]["sha256"]
        == __import__("hashlib").sha256(images[0].read_bytes()).hexdigest()
    )
    assert (out / images[1].stem / "stack.json").stat().st_ino == kept
    assert sorted(p.name for p in out.iterdir()) == [p.stem for p in images]


def test_a_folder_without_a_record_is_never_taken(tmp_path, capsys):
    """A folder the batch did not write (by hand, an older lasagna) is left alone: its stem goes to another name."""
    (image,) = _images(tmp_path / "in", 1)
    out = tmp_path / "out"
    (out / image.stem).mkdir(parents=True)
    (out / image.stem / "notes.txt").write_text("mine")
    code, stdout, err = run(capsys, "edit", tmp_path / "in", "--condition", "left", "-o", out)
    assert code == 0, err
    assert (out / image.stem / "notes.txt").read_text() == "mine"
    assert _record(out / f"{image.stem}-2")["source"]["path"] == image.name


def test_json_reports_every_input_and_a_summary_last(tmp_path, capsys):
    """``--json``: one object per input (its input, output folder, status, seconds) then the summary object, every
    line JSON; a second run reports the inputs as skipped; one input with --json is refused in one line."""
    images = _images(tmp_path / "in", 3)
    out = tmp_path / "out"
    code, stdout, err = run(capsys, "edit", tmp_path / "in", "--condition", "left", "-o", out, "--json")
    assert code == 0, err
    lines = [json.loads(line) for line in stdout.strip().splitlines()]
    assert [(Path(o["input"]).name, o["status"]) for o in lines[:-1]] == [(p.name, "done") for p in images]
    assert all(Path(o["output"]) == out / Path(o["input"]).stem and o["seconds"] >= 0 for o in lines[:-1])
    assert lines[-1]["done"] == 3 and lines[-1]["failed"] == 0 and "edited 3" in lines[-1]["summary"]
    code, stdout, _ = run(capsys, "edit", tmp_path / "in", "--condition", "left", "-o", out, "--json")
    assert [json.loads(line)["status"] for line in stdout.strip().splitlines()[:-1]] == ["skipped"] * 3
    code, _, err = run(capsys, "edit", images[0], "--condition", "left", "-o", tmp_path / "one", "--json")
    assert code == 2 and "--json: --json reports a batch" in err and len(err.strip().splitlines()) == 1
