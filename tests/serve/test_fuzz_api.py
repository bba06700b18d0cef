"""Malformed editor requests (#28, defect 14): every one is a 4xx of one line naming the field, what it
expected and what it was given; numbers are strict (``"0.5"`` and ``true`` are not numbers). Then a
bounded hypothesis fuzz of every route with the token: random paths, query strings, JSON and raw bodies
never get a 5xx, and the session still answers ``/api/state`` afterwards."""

from __future__ import annotations

import json
import shutil
import string
from urllib.parse import quote

import pytest

pytest.importorskip("starlette")
pytest.importorskip("httpx")

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from starlette.testclient import TestClient  # noqa: E402

from lasagna.serve.app import create_app  # noqa: E402
from lasagna.serve.bodies import CHANGES  # noqa: E402
from lasagna.serve.session import EditSession  # noqa: E402
from tests.support.tinylayers import ROOT  # noqa: E402

TOKEN = "test-token"
H = {"X-Lasagna-Token": TOKEN}


@pytest.fixture(scope="module")
def client(tmp_path_factory, tiny):
    root = tmp_path_factory.mktemp("fuzz-api")
    mp = pytest.MonkeyPatch()
    mp.setenv("LASAGNA_LAYERS", str(tiny))
    folder = root / "basic"
    shutil.copytree(ROOT / "examples" / "stacks" / "basic", folder)
    yield TestClient(create_app(EditSession(folder), TOKEN, ["testserver"]), raise_server_exceptions=False)
    mp.undo()


def version(client) -> int:
    r = client.get("/api/state", headers=H)
    assert r.status_code == 200, r.text
    return r.json()["version"]


def one_line_4xx(r) -> str:
    assert 400 <= r.status_code < 500, (r.status_code, r.text)
    message = r.json()["error"]
    assert "\n" not in message and "Traceback" not in message and "internal error" not in message
    return message


# ---- the requests, one by one ---------------------------------------------------------------


@pytest.mark.parametrize(
    "raw, words",
    [
        ("[" * 100_000 + "]" * 100_000, "nested more than 64"),
        ('{"op": "undo", "version": ' + "1" * 5000 + "}", "5000 digits"),
        ('{"op": "solid", "version": 1, "color": [1e400, 0, 0]}', "finite number"),
        ('{"op": "undo", "version": NaN}', "finite number"),
        ('{"op": "undo", "op": "redo", "version": 1}', "duplicate key"),
        ("\xff", "not UTF-8"),
    ],
    ids=["nested", "digits", "1e400", "nan", "duplicate", "not-utf8"],
)
def test_hostile_json_is_refused_before_parsing(client, raw, words):
    r = client.post("/api/change", headers={**H, "content-type": "application/json"}, content=raw.encode("latin-1"))
    assert words in one_line_4xx(r)


@pytest.mark.parametrize("op", [["solid"], {"x": 1}, 3, None, True])
def test_an_op_that_is_not_a_name_is_400(client, op):
    r = client.post("/api/change", headers=H, json={"op": op, "version": version(client)})
    message = one_line_4xx(r)
    assert message.startswith("op: unknown op") and "expected one of set, move" in message


@pytest.mark.parametrize(
    "color, field, given",
    [
        ("a", "color", "'a'"),
        (None, "color", "None"),
        ("0.5", "color", "'0.5'"),
        (True, "color", "True"),
        (0.5, "color", "0.5"),
        ([True, 0, 0], "color[0]", "True"),
        (["0.5", 0, 0], "color[0]", "'0.5'"),
        ([0, None, 0], "color[1]", "None"),
        ([0, 0, "a"], "color[2]", "'a'"),
        ([0, 0, 2], "color[2]", "2"),
        ([0, 0], "color", "2 items"),
    ],
)
def test_a_bad_colour_names_the_field_what_was_expected_and_what_was_given(client, color, field, given):
    v = version(client)
    r = client.post("/api/change", headers=H, json={"op": "solid", "version": v, "color": color})
    message = one_line_4xx(r)
    assert message.startswith(f"{field}: ") and given in message and "expected" in message
    assert version(client) == v  # nothing was added


@pytest.mark.parametrize(
    "body, field",
    [
        ({"op": "undo", "version": "1"}, "version"),
        ({"op": "undo", "version": True}, "version"),
        ({"op": "undo", "version": 1.0}, "version"),
        ({"op": "move", "id": "glow", "index": True}, "index"),
        ({"op": "move", "id": "glow", "index": "0"}, "index"),
        ({"op": "delete", "id": ["glow"]}, "id"),
        ({"op": "set", "id": "glow", "changes": "opacity"}, "changes"),
        ({"op": "solid", "color": [1, 0, 0], "name": 7}, "name"),
        ({"op": "solid", "color": [1, 0, 0], "blend": ["multiply"]}, "blend"),
        ({"op": "learned", "preset": 1, "condition": "x"}, "preset"),
        ({"op": "learned", "preset": "shading", "condition": "x", "method": "fast"}, "method"),
        ({"op": "undo", "extra": 1}, "extra"),
        ({"op": "light", "id": "glow", "light": 45}, "light"),
        ({"op": "light", "id": "glow", "light": "left", "ambient": "0.5"}, "ambient"),
    ],
)
def test_strict_types_in_change_bodies(client, body, field):
    body = {"version": version(client), **body}
    assert one_line_4xx(client.post("/api/change", headers=H, json=body)).startswith(f"{field}: ")


@pytest.mark.parametrize(
    "body, field",
    [({"kind": "refine", "id": "glow", "steps": "3"}, "steps"), ({"kind": ["refine"], "id": "glow"}, "kind")],
)
def test_strict_types_in_job_bodies(client, body, field):
    r = client.post("/api/jobs", headers=H, json={"version": version(client), **body})
    assert one_line_4xx(r).startswith(f"{field}: ")


def test_empty_bodies_take_no_fields(client):
    assert one_line_4xx(client.post("/api/reload", headers=H, json={"x": 1})).startswith("x: unknown field")


def test_well_typed_integers_for_floats_are_accepted(client):
    """The page sends ``[1, 0, 0]`` for pure red (JSON has one number type): an integer is a number."""
    v = version(client)
    r = client.post("/api/change", headers=H, json={"op": "solid", "version": v, "color": [1, 0, 0]})
    assert r.status_code == 200, r.text
    assert r.json()["document"]["layers"][-1]["color"] == [1.0, 0.0, 0.0]


# ---- fuzz ---------------------------------------------------------------------------------------------

ROUTES = [
    ("GET", "/"),
    ("GET", "/static/{}"),
    ("GET", "/api/state"),
    ("GET", "/api/view"),
    ("GET", "/api/layers/{}/thumb.png"),
    ("GET", "/api/layers/{}/normals"),
    ("GET", "/api/export/{}"),
    ("GET", "/api/jobs/{}/events"),
    ("POST", "/api/change"),
    ("POST", "/api/upload"),
    ("POST", "/api/reload"),
    ("POST", "/api/jobs"),
    ("POST", "/api/jobs/{}/cancel"),
    ("GET", "/api/{}"),
    ("POST", "/{}"),
]
LAYER_IDS = ["background", "glow", "sticker", "nope", ""]
QUERY_KEYS = ["level", "opacity", "light", "solo", "upto", "version", "name", "x"]

scalars = st.none() | st.booleans() | st.integers(-(10**25), 10**25) | st.floats() | st.text(max_size=12)
json_values = st.recursive(
    scalars, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4)
)
field_values = json_values | st.sampled_from(LAYER_IDS) | st.lists(st.floats(0, 1), min_size=3, max_size=4)


@st.composite
def op_bodies(draw):
    """An /api/change-shaped object: a real op (usually), a nearly right version and fields of any type."""
    body = draw(st.dictionaries(st.sampled_from(sorted({"id", "changes", "index", "color", "name", "blend",
                                                        "preset", "condition", "on", "method", "steps", "kind",
                                                        "light", "source_light", "ambient"})),
                                field_values, max_size=5))  # fmt: skip
    body["op"] = draw(st.sampled_from(list(CHANGES)) | json_values)
    if draw(st.booleans()):
        body["version"] = draw(st.sampled_from(["current", 0, -1, "1", True, 1.5, None]))
    return body


def _raw(body) -> bytes:
    try:
        return json.dumps(body, allow_nan=True).encode()
    except (TypeError, ValueError):
        return b"{}"


bodies = (
    op_bodies().map(_raw)
    | json_values.map(_raw)
    | st.binary(max_size=64)
    | st.sampled_from([b"", b"{", b"[" * 200, b'{"a": 1e999}', b'{"version": 99999999999999999999999}'])
)
segments = st.sampled_from(LAYER_IDS + ["ora", "psd", "png", "app.js", "..", "%00", "caf\u00e9"]) | st.text(
    string.printable, max_size=12
)
queries = st.lists(st.tuples(st.sampled_from(QUERY_KEYS), st.text(max_size=12)), max_size=4)


@settings(
    max_examples=200,
    derandomize=True,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
@given(route=st.sampled_from(ROUTES), segment=segments, query=queries, body=bodies)
def test_fuzz_every_route_never_errs_500(client, route, segment, query, body):
    method, template = route
    path = template.format(quote(segment, safe="%") or "_")  # any text, as a page's URL would carry it
    if b'"current"' in body:
        body = body.replace(b'"current"', str(version(client)).encode())
    r = client.request(method, path, headers={**H, "content-type": "application/json"}, params=query, content=body)
    assert r.status_code < 500, (method, path, query, body[:200], r.status_code, r.text[:300])
    if r.status_code >= 400:
        one_line_4xx(r)
    version(client)  # the session still answers
