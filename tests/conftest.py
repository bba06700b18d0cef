"""Fixtures every test module may use.

``tiny``: the tiny learned-layer catalogue (tests/support/tinylayers.py: the bundled presets with a short
distill, random priors, correctives, a generator and surface estimators), built once per session — it
used to be built by each of eleven modules. It is shared, so it is read-only: a test that needs a changed
preset copies it first (``tiny_variant``); the session fails at the end if anything changed it.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.support.tinylayers import fingerprint, tiny_catalogue


@pytest.fixture(scope="session")
def tiny(tmp_path_factory) -> Path:
    folder = tiny_catalogue(tmp_path_factory.mktemp("tiny") / "layers")
    built = fingerprint(folder)
    yield folder
    assert fingerprint(folder) == built, f"a test changed the shared tiny catalogue {folder}; copy it first"
