"""Tests of lasagna.document (the document tier)."""
