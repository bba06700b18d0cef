"""Every `lasagna` command of the README's shell blocks names only paths a user has (issue #27): a path it reads is
in the checkout (examples, layers, …) or is a catalogue name, so the command also runs outside the checkout from an
installed wheel — where ``layers/<name>`` does not exist but the name ``<name>`` resolves (``lasagna.catalogue``).

The fast part, here: parse the commands, check their read paths and that no two write one output. Running them all
from the wheel installed by name in a fresh venv, outside the checkout, is ``tests/test_readme_installed.py`` (slow).
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

from lasagna import catalogue

ROOT = Path(__file__).resolve().parents[1]

# Options whose value is written, or is a user's own file the README only shows (a diffusers folder, a photo).
WRITES = {
    "-o",
    "--output",
    "--out",
    "--sheet",
    "--json-out",
    "--ora",
    "--psd",
    "--layers",
    "--normal-map",
    "--height-map",
}
USERS_OWN = ("/models/", "runs/", "out/", "shots/", "big/", "photos/", "photo.png", "a.png")  # prefixes


def readme_commands() -> list[list[str]]:
    """The argument lists of the `lasagna …` lines in README.md's ```sh blocks (continuations joined, comments cut)."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    commands = []
    for block in re.findall(r"```sh\n(.*?)```", text, re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.split(" # ")[0].strip()
            if line.startswith("lasagna "):
                commands.append(shlex.split(line)[1:])
    return commands


def read_paths(args: list[str]) -> list[str]:
    """The arguments of a command that name a file or folder it reads from the checkout."""
    out = []
    for prev, arg in zip(["", *args], args):
        if prev in WRITES or arg.startswith("-") or "/" not in arg or "=" in arg:
            continue
        if arg.startswith(USERS_OWN) or any(c in arg for c in "*?"):
            continue
        out.append(arg)
    return out


def test_the_readme_has_commands():
    assert len(readme_commands()) >= 10


def test_every_path_a_readme_command_reads_is_in_the_checkout_and_no_catalogue_entry_is_named_by_path():
    kinds = ("prior", "corrective", "preset", "generator", "estimator")
    names = {n for kind in kinds for n in catalogue.available()[kind]}
    bad = []
    for args in readme_commands():
        for path in read_paths(args):
            parts = Path(path).parts
            if parts[0] == "layers" and len(parts) == 2 and parts[1] in names:
                bad.append(f"{' '.join(args)}: {path} (outside the checkout there is no layers/; name {parts[1]})")
            elif not (ROOT / path).exists():
                bad.append(f"{' '.join(args)}: {path} does not exist in the checkout")
    assert not bad, "\n".join(bad)


def test_no_two_readme_commands_write_one_output():
    """Run in order, as tests/test_readme_installed.py runs them, a second command writing the folder or file an
    earlier one wrote is refused ("is not empty; expected a new or empty folder")."""
    seen: dict[str, str] = {}
    repeated = []
    for args in readme_commands():
        for prev, arg in zip(args, args[1:]):
            if prev in ("-o", "--output", "--out"):
                if arg in seen:
                    repeated.append(f"{' '.join(args)}: {arg} (also written by: {seen[arg]})")
                seen[arg] = " ".join(args)
    assert not repeated, "\n".join(repeated)
