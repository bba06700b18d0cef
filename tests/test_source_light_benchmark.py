"""benchmarks/source_light.py: the mixed lights carry the azimuth and elevation their names say (numpy float64), the
errors of a light against itself are zero and a flip is counted, and a run prices every light for an estimator."""

import json
import math
import sys
from pathlib import Path

import numpy as np
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import source_light  # noqa: E402


def np_light(az: float, el: float) -> np.ndarray:
    return np.array([math.sin(el) * math.cos(az), math.sin(el) * math.sin(az), math.cos(el)])


@settings(max_examples=30, deadline=None)
@given(
    angles=st.lists(
        st.tuples(st.floats(-3.1, 3.1), st.floats(0.2, 1.4), st.floats(-3.1, 3.1), st.floats(0.2, 1.4)),
        min_size=1,
        max_size=6,
    )
)
def test_the_mixed_lights_carry_the_angles_their_names_say(angles):
    fitted = torch.tensor(np.stack([np_light(a, e) for a, e, _, _ in angles]))
    true = torch.tensor(np.stack([np_light(a, e) for _, _, a, e in angles]))
    got = source_light.mixed_lights(fitted, true)
    assert list(got) == list(source_light.LIGHTS)
    for i, (fa, fe, ta, te) in enumerate(angles):
        flip = abs(math.remainder(fa - ta, 2 * math.pi)) > math.radians(source_light.FLIP_DEG)
        want = {
            "fitted": np_light(fa, fe),
            "true": np_light(ta, te),
            "true azimuth, fitted elevation": np_light(ta, fe),
            "fitted azimuth, true elevation": np_light(fa, te),
            "flips set right": np_light(ta if flip else fa, fe),
        }
        for name, light in want.items():
            np.testing.assert_allclose(got[name][i].numpy(), light, atol=1e-9)


def test_a_light_has_no_error_against_itself_and_a_turned_one_is_a_flip():
    true = torch.tensor(np.stack([np_light(0.3, 0.7), np_light(2.0, 1.1)]))
    zero = source_light.light_errors(true, true)
    assert zero["flips"] == 0 and zero["median_deg"] < 1e-3 and abs(zero["elevation_bias_deg"]) < 1e-6
    turned = torch.tensor(np.stack([np_light(0.3 + math.pi, 0.7), np_light(2.0 + 0.5, 1.1 + 0.1)]))
    got = source_light.light_errors(turned, true)
    assert got["flips"] == 1
    assert got["elevation_bias_deg"] == round(math.degrees(0.05), 2)


def test_a_run_prices_every_light(capsys):
    assert source_light.main(["--count", "2", "--size", "32"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    rows = out["rows"]
    assert [r["light"] for r in rows] == ["fitted, as read", *source_light.LIGHTS]
    by = {r["light"]: r for r in rows}
    if by["fitted, as read"]["flips"] == 0:  # no flip to set right: the same light, the same layer
        assert by["flips set right"]["db_all"] == by["fitted"]["db_all"]
    assert all(math.isfinite(r["db_all"]) and math.isfinite(r["db_objects"]) for r in rows[1:])
