"""The import rule of docs/ARCHITECTURE.md, measured from the code: every module of ``lasagna/`` is parsed
with ``ast`` (imports inside functions and ``TYPE_CHECKING`` blocks included, and ``importlib.import_module``
of a constant name), and the test fails on a module that imports a tier above its own, on any import cycle
between modules, and on a module no tier claims. ``TIERS`` below is the one statement of the order.

Also here: the names the issue asked to be declared once are declared once (blend names, loss names,
the CLI's choices built from them).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "lasagna"

# Lowest first. A module may import its own tier and those before it, never one after it.
TIERS: tuple[tuple[str, tuple[str, ...]], ...] = (
    (
        "ground floor",
        ("lasagna.errors", "lasagna.numerics", "lasagna.atomic", "lasagna.limits", "lasagna.heap", "lasagna.version"),
    ),
    ("document", ("lasagna.document",)),
    ("compose", ("lasagna.compose",)),
    ("io", ("lasagna.io",)),
    ("export", ("lasagna.export",)),
    ("priors", ("lasagna.priors",)),
    ("losses", ("lasagna.losses",)),
    ("generators", ("lasagna.generators",)),
    ("distill", ("lasagna.distill",)),
    ("world", ("lasagna.world",)),
    ("catalogue", ("lasagna.catalogue", "lasagna.components")),
    ("training", ("lasagna.training",)),
    (
        "user API",
        (
            "lasagna.request",
            "lasagna.learned",
            "lasagna.recipe",
            "lasagna.editing",
            "lasagna.batch_records",
            "lasagna.batch",
            "lasagna.demo",
            "lasagna.api",
        ),
    ),
    ("editor", ("lasagna.serve",)),
    ("cli", ("lasagna.cli",)),
    ("package root", ("lasagna",)),  # lasagna/__init__.py: lazy names of lasagna.api
)


def modules() -> dict[str, Path]:
    found = {}
    for path in PACKAGE.rglob("*.py"):
        parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        found[".".join(parts)] = path
    return found


MODULES = modules()


def _resolve(name: str) -> str | None:
    """The module (or package) of ``lasagna`` that ``name`` is or lies in."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def imports(module: str) -> set[str]:
    """Every ``lasagna`` module ``module`` imports, wherever the import statement stands."""
    path = MODULES[module]
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: set[str | None] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            found.update(_resolve(a.name) for a in node.names if a.name.split(".")[0] == "lasagna")
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join(parent + ([base] if base else []))
            if base.split(".")[0] != "lasagna":
                continue
            for alias in node.names:  # ``from lasagna import catalogue`` imports the module lasagna.catalogue
                target = f"{base}.{alias.name}"
                found.add(target if target in MODULES else _resolve(base))
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "import_module"
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and str(node.args[0].value).startswith("lasagna")
        ):
            found.add(_resolve(str(node.args[0].value)))
    found.discard(None)
    found.discard(module)
    return found  # type: ignore[return-value]


GRAPH = {m: imports(m) for m in MODULES}


def tier_of(module: str) -> int | None:
    """Index in ``TIERS`` of the longest prefix that claims ``module``."""
    best, length = None, -1
    for i, (_, prefixes) in enumerate(TIERS):
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > length:
                best, length = i, len(prefix)
    return best


def test_every_module_has_a_tier():
    assert [m for m in MODULES if tier_of(m) is None] == []


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    """One line per import of a module of a higher tier than the importer's."""
    upward = []
    for module, targets in sorted(graph.items()):
        mine = tier_of(module)
        for target in sorted(targets):
            theirs = tier_of(target)
            if theirs is not None and mine is not None and theirs > mine:
                upward.append(f"{module} ({TIERS[mine][0]}) imports {target} ({TIERS[theirs][0]})")
    return upward


def test_no_module_imports_a_tier_above_its_own():
    upward = upward_imports(GRAPH)
    assert upward == [], "imports up the tiers:\n" + "\n".join(upward)


def test_an_upward_import_is_caught():
    graph = {"lasagna.document.models": {"lasagna.io.stack"}, "lasagna.cli.edit": {"lasagna.editing"}}
    assert upward_imports(graph) == ["lasagna.document.models (document) imports lasagna.io.stack (io)"]


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_cycles():
    assert _cycles(GRAPH) == []


def test_the_cycle_finder_finds_cycles():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_function_level_imports_are_seen():
    assert "lasagna.training.prior" in GRAPH["lasagna.cli.train_prior"]  # imported inside add_arguments/run


# ---- one place for each name -------------------------------------------------------------------------


def test_blend_names_are_the_documents():
    from lasagna.compose import blend
    from lasagna.document.blend import BLEND_MODES
    from lasagna.generators.layer import LayerSpec

    assert blend.BLEND_MODES is BLEND_MODES
    assert set(blend.KERNELS) == set(blend.KERNELS_INPLACE) == set(blend.BLEND_FUNC) == set(BLEND_MODES)
    assert LayerSpec.model_fields["blend"].annotation.__args__ == BLEND_MODES


def test_loss_names_are_the_registry_and_the_clis_choices():
    import argparse

    from lasagna.cli import edit, train_layer
    from lasagna.document.preset import LOSS_NAMES
    from lasagna.losses import available_losses

    assert sorted(LOSS_NAMES) == available_losses()
    for command in (edit, train_layer):
        parser = argparse.ArgumentParser()
        command.add_arguments(parser)
        (loss,) = [a for a in parser._actions if a.dest == "loss"]
        assert tuple(loss.choices) == LOSS_NAMES


@pytest.mark.parametrize("name", ["io", "train", "corrective_train", "amortised", "tasks", "cli_learned"])
def test_old_homes_are_gone(name):
    """The concepts that moved (issue 13) have one home each; their old modules are not left behind."""
    old = {
        "io": "lasagna.priors.io",
        "train": "lasagna.priors.train",
        "corrective_train": "lasagna.losses.corrective_train",
        "amortised": "lasagna.distill.amortised",
        "tasks": "lasagna.distill.tasks",
        "cli_learned": "lasagna.cli_learned",
    }[name]
    assert old not in MODULES
