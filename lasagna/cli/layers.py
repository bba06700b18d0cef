"""``lasagna layers``: list the learned-layer catalogue (presets, ready or why not; priors, correctives,
generators)."""

from __future__ import annotations

import argparse
import json

HELP = "list the learned-layer catalogue: presets, priors, correctives, generators"
EXAMPLE = "lasagna layers --json"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print the listing as JSON")


def run(args: argparse.Namespace) -> int:
    from lasagna import catalogue as cat

    found = cat.available()
    status = {name: cat.preset_status(name) for name in found["preset"]}
    broken = cat.problems()  # each broken entry in one line; the others are listed as usual
    if args.json:
        catalogues = [str(c) for c in cat.catalogues()]
        print(json.dumps({"catalogues": catalogues, **found, "status": status, "broken": broken}))
        return 0
    print(f"catalogues: {', '.join(map(str, cat.catalogues())) or '(none)'}")
    for kind in cat.KINDS:
        print(f"{kind}s: {', '.join(found[kind]) or '(none)'}")
    for name, st in status.items():
        how = f"ready ({st['method']}: {st['why']})" if st["usable"] else f"not usable: {st['why']}"
        if st["amortised"] and st["method"] != "amortised":
            how += "; --generator amortised: its generator"
        print(f"  {name}: {how}")
    for why in broken:
        print(f"broken entry: {why}")
    return 0
