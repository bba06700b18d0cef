"""The package version, for ``lasagna --version`` and the records an edit writes (pyproject.toml states the same)."""

__version__ = "0.1.0"
