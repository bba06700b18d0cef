"""Stack-folder transactions: two writers racing for one new folder (exactly one wins without force, nothing
lost), symbolic-link output folders refused up front, stale temporaries swept, and outputs that would
overwrite the input stack's own files refused."""

from __future__ import annotations

import os
import shutil
import threading
from pathlib import Path

import pytest
import torch

from lasagna.errors import PathError
from lasagna.io import folder as folder_module
from lasagna.io.folder import (
    check_not_input,
    check_output_folder,
    save_in_place,
    stack_sha256,
    write_stack_folder,
)
from lasagna.io.stack import Stack, load_stack
from tests.support.bounded import HANG_SECONDS

BASIC = Path(__file__).resolve().parents[2] / "examples" / "stacks" / "basic"


def _stack(value: float) -> Stack:
    return Stack.from_image(torch.full((3, 4, 5), value))


def _leftovers(parent: Path) -> list[str]:
    return [p.name for p in parent.iterdir() if ".lasagna-" in p.name]


def _race(monkeypatch, out: Path, *, force: bool, writers: int = 2) -> list[BaseException | None]:
    """``writers`` threads write a stack folder to ``out``, released together just before the swap (the
    window the early check cannot close); returns each one's exception (None for success)."""
    barrier = threading.Barrier(writers, timeout=HANG_SECONDS)
    real = folder_module.swap_in

    def swap_after_barrier(tmp, target, **kw):
        barrier.wait()
        return real(tmp, target, **kw)

    monkeypatch.setattr(folder_module, "swap_in", swap_after_barrier)
    results: list[BaseException | None] = [None] * writers

    def write(i: int) -> None:
        try:
            write_stack_folder(_stack(i / 10), out, force=force)
        except BaseException as exc:  # noqa: BLE001 - reported to the test
            results[i] = exc

    threads = [threading.Thread(target=write, args=(i,)) for i in range(writers)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return results


@pytest.mark.parametrize("attempt", range(4))
@pytest.mark.parametrize("exists", [False, True], ids=["new", "empty"])
def test_racing_writers_one_wins(tmp_path, monkeypatch, attempt, exists):
    out = tmp_path / "out"
    if exists:
        out.mkdir()
    results = _race(monkeypatch, out, force=False, writers=3)
    failures = [r for r in results if r is not None]
    assert len(failures) == 2, results
    for exc in failures:
        assert isinstance(exc, PathError) and str(exc).startswith(f"{out}: is not empty; expected a new or empty")
    winner = results.index(None)
    stack = load_stack(out)  # complete, and the winner's
    assert float(stack.tensors["base"].color.mean()) == pytest.approx(winner / 10, abs=1 / 255)
    assert _leftovers(tmp_path) == []


def test_racing_forced_writers_both_succeed_one_after_the_other(tmp_path, monkeypatch):
    out = tmp_path / "out"
    write_stack_folder(_stack(0.9), out)
    results = _race(monkeypatch, out, force=True)
    assert results == [None, None]
    last = load_stack(out).tensors["base"].color.mean().item()
    assert min(abs(last - 0.0), abs(last - 0.1)) < 1 / 255  # one of the racers', not the first stack
    assert _leftovers(tmp_path) == []


def test_symlinked_output_folder_is_refused(tmp_path):
    (tmp_path / "real").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "real")
    with pytest.raises(PathError, match=r"link: is a symbolic link \(to .*real\); expected a real folder"):
        check_output_folder(tmp_path / "link")
    with pytest.raises(PathError, match="symbolic link"):
        write_stack_folder(_stack(0.5), tmp_path / "link")
    assert (tmp_path / "link").is_symlink() and not any((tmp_path / "real").iterdir())
    assert _leftovers(tmp_path) == []
    write_stack_folder(_stack(0.5), tmp_path / "real")  # the link's target itself is fine
    assert (tmp_path / "link" / "stack.json").is_file()


def test_write_sweeps_a_dead_writers_folders(tmp_path):
    (tmp_path / ".out.lasagna-999999999-0123abcd.tmp").mkdir()  # no such pid
    write_stack_folder(_stack(0.5), tmp_path / "out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_outputs_onto_the_input_stack_are_refused(tmp_path):
    folder = tmp_path / "s"
    shutil.copytree(BASIC, folder)
    stack = load_stack(folder)
    for name, what in [
        ("stack.json", "the input document"),
        ("layers/shade.png", r"layers\[1\].source of the input"),
        ("layers/../layers/base.png", r"layers\[0\].source of the input"),
    ]:
        with pytest.raises(PathError, match=f"is {what}; expected an output path that is not one of the stack's"):
            check_not_input([tmp_path / "x.png", folder / name], stack)
    (tmp_path / "hard.png").hardlink_to(folder / "layers" / "glow.png")
    with pytest.raises(PathError, match=r"hard\.png: is layers\[3\]\.source"):
        check_not_input([tmp_path / "hard.png"], stack)
    check_not_input([folder / "composite.png", folder / "layers" / "new.png", tmp_path / "x.png"], stack)


# ---- files the document owns: a symlink is the stack's entry, its target never written or removed ----------


def _linked(tmp_path: Path, link: str, target: str) -> Path:
    """A copy of the basic stack whose ``link`` (relative to the folder) is a symlink to ``target``."""
    folder = tmp_path / "linked"
    shutil.copytree(BASIC, folder)
    (folder / link).unlink()
    (folder / link).symlink_to(target)
    return folder


def _reads_back(folder: Path) -> None:
    stack = load_stack(folder)  # every file named is there, whole and inside the folder
    stack.render()


@pytest.mark.parametrize(
    "target, victim",
    [("glow.png", "layers/glow.png"), ("../photo.png", "photo.png")],
    ids=["another-layers-png", "a-users-file"],
)
def test_saving_in_place_without_a_linked_layer_unlinks_the_link_not_its_target(tmp_path, target, victim):
    folder = _linked(tmp_path, "layers/sticker.png", target)
    shutil.copy(BASIC / "layers" / "sticker.png", folder / "photo.png")
    kept = (folder / victim).read_bytes()
    stack = load_stack(folder)
    stack.remove_layer("sticker")
    save_in_place(stack, unchanged=dict(stack.tensors), expect_sha256=stack_sha256(folder))
    assert (folder / victim).read_bytes() == kept
    assert not os.path.lexists(folder / "layers" / "sticker.png")
    _reads_back(folder)


def test_a_file_another_layers_link_leads_to_is_kept(tmp_path):
    folder = _linked(tmp_path, "layers/glow.png", "sticker.png")  # glow's name leads to sticker's file
    stack = load_stack(folder)
    glow = stack.tensors["glow"].color.clone()
    stack.remove_layer("sticker")
    save_in_place(stack, unchanged=dict(stack.tensors), expect_sha256=stack_sha256(folder))
    assert (folder / "layers" / "sticker.png").is_file()
    assert torch.equal(load_stack(folder).tensors["glow"].color, glow)


def test_stack_save_replaces_a_linked_png_and_leaves_its_target(tmp_path):
    folder = _linked(tmp_path, "layers/sticker.png", "../photo.png")
    shutil.copy(BASIC / "layers" / "sticker.png", folder / "photo.png")
    photo = (folder / "photo.png").read_bytes()
    stack = load_stack(folder)
    new = torch.full_like(stack.tensors["sticker"].color, 0.25)
    stack.set_pixels("sticker", new, alpha=stack.tensors["sticker"].alpha)
    stack.save()
    assert (folder / "photo.png").read_bytes() == photo
    assert not (folder / "layers" / "sticker.png").is_symlink()
    assert torch.allclose(load_stack(folder).tensors["sticker"].color, new, atol=1 / 255)


def test_stack_save_of_a_layer_linked_to_another_layers_png_keeps_both(tmp_path):
    folder = _linked(tmp_path, "layers/sticker.png", "glow.png")
    stack = load_stack(folder)
    glow = stack.tensors["glow"].color.clone()
    sticker = torch.full_like(stack.tensors["sticker"].color, 0.5)
    stack.set_pixels("sticker", sticker, alpha=stack.tensors["sticker"].alpha)
    stack.save()
    back = load_stack(folder)
    assert torch.allclose(back.tensors["glow"].color, glow, atol=1 / 255)
    assert torch.allclose(back.tensors["sticker"].color, sticker, atol=1 / 255)
