"""Non-ASCII names in the editor (#28, defect 16): a layer's name is free text (``café.png``, ``写真.png``, a
solid named ``Ébauche``), its id is derived safely (``lasagna.document.types.unique_id``, accents folded to
ASCII first), and the page's percent-encoded UTF-8 name arrives whole. A stack folder with a Unicode name
exports with a Content-Disposition a browser decodes (RFC 5987 ``filename*``)."""

from __future__ import annotations

import io
import shutil
import unicodedata
from urllib.parse import quote, unquote

import pytest
from PIL import Image

pytest.importorskip("starlette")
pytest.importorskip("httpx")

from starlette.testclient import TestClient  # noqa: E402

from lasagna.document.types import check_id  # noqa: E402
from lasagna.io.stack import load_stack  # noqa: E402
from lasagna.serve.app import create_app  # noqa: E402
from lasagna.serve.session import EditSession  # noqa: E402
from tests.support.tinylayers import ROOT  # noqa: E402

TOKEN = "test-token"
H = {"X-Lasagna-Token": TOKEN}


def make_client(tmp_path, name="basic"):
    folder = tmp_path / name
    shutil.copytree(ROOT / "examples" / "stacks" / "basic", folder)
    return TestClient(create_app(EditSession(folder), TOKEN, ["testserver"]), raise_server_exceptions=False), folder


def png_bytes() -> bytes:
    buf = io.BytesIO()
    Image.new("RGBA", (20, 10), (10, 200, 30, 255)).save(buf, "PNG")
    return buf.getvalue()


def version(client) -> int:
    return client.get("/api/state", headers=H).json()["version"]


def upload(client, name: str):
    """As the page sends it: ``new URLSearchParams({version, name})``, UTF-8 percent-encoded."""
    url = f"/api/upload?version={version(client)}&name={quote(name, safe='')}"
    return client.post(url, headers=H, content=png_bytes())


@pytest.mark.parametrize(
    "file, name, id",
    [
        ("café.png", "café", "cafe"),
        (unicodedata.normalize("NFD", "café.png"), unicodedata.normalize("NFD", "café"), "cafe"),  # macOS
        ("写真.png", "写真", "layer"),
        ("Фото 2024.jpg.png", "Фото 2024.jpg", "2024.jpg"),
        ("con.png", "con", "con_"),
        ("holiday 🏖.png", "holiday 🏖", "holiday"),
    ],
)
def test_uploads_with_unicode_names_keep_the_name_and_get_a_safe_id(tmp_path, file, name, id):
    client, folder = make_client(tmp_path)
    r = upload(client, file)
    assert r.status_code == 200, r.text
    top = r.json()["document"]["layers"][-1]
    assert top["name"] == name and top["id"].startswith(id) and check_id(top["id"]) == top["id"]
    r = client.post("/api/change", headers=H, json={"op": "save", "version": version(client)})
    assert r.status_code == 200, r.text
    assert load_stack(folder).document.layer(top["id"]).name == name


def test_two_uploads_of_one_unicode_name_get_two_ids(tmp_path):
    client, _ = make_client(tmp_path)
    ids = [upload(client, "写真.png").json()["document"]["layers"][-1]["id"] for _ in range(2)]
    assert len(set(ids)) == 2


def test_a_solid_named_ebauche(tmp_path):
    client, _ = make_client(tmp_path)
    body = {"op": "solid", "version": version(client), "color": [1, 0.5, 0], "name": "Ébauche"}
    r = client.post("/api/change", headers=H, json=body)
    assert r.status_code == 200, r.text
    top = r.json()["document"]["layers"][-1]
    assert (top["name"], top["id"]) == ("Ébauche", "ebauche")


def test_a_unicode_stack_folder_exports_with_its_name(tmp_path):
    client, _ = make_client(tmp_path, "写真.stack")
    r = client.get("/api/export/png", headers=H)
    assert r.status_code == 200, r.text
    disposition = r.headers["content-disposition"]
    assert disposition.startswith('attachment; filename="__.stack.png"; filename*=UTF-8')
    assert unquote(disposition.split("''", 1)[1]) == "写真.stack.png"
