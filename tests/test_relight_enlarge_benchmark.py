"""benchmarks/relight_enlarge.py: the intercepted enlargement is the edit's own (the shipped row measures exactly
the layer `lasagna.edit` returns), every candidate enlarges the same working-size ratio, and the run ends with its
one JSON line."""

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import relight_enlarge  # noqa: E402
from relight_candidates import measure  # noqa: E402
from surface import scenes  # noqa: E402

from lasagna import edit  # noqa: E402
from lasagna.world.tasks import relight_sources, relighting  # noqa: E402


def test_the_shipped_row_is_the_edits_own_layer(tmp_path, capsys):
    out = tmp_path / "rows.json"
    assert relight_enlarge.main(["--count", "1", "--sizes", "96", "--json-out", str(out)]) == 0
    rows = json.loads(out.read_text())
    grid = len(relight_enlarge.RADII) * len(relight_enlarge.EPSILONS)
    assert len(rows) == 1 + grid + len(relight_enlarge.BILATERAL_SIGMAS)
    shipped = [r for r in rows if r["shipped"]]
    assert len(shipped) == 1 and shipped[0]["method"] == "guided r1 eps0.001"
    scene, labels = scenes("select", 1, 0, 96)
    rel = relighting(scene, relight_sources(scene.params))
    layer = edit(rel.base.float()[0], "relight", labels[0]).layer[:1][None]
    assert abs(measure("edit", scene, rel, layer, None, 96)["db_all"] - shipped[0]["db_all"]) < 2e-3
    # One ratio under every enlargement: the candidates differ from each other, the wall leak is measured for each.
    assert len({r["db_all"] for r in rows}) > 1 and all(r["leak_db"] > 0 for r in rows)
    last = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert last["benchmark"] == "relight_enlarge" and last["rows"] == len(rows)
