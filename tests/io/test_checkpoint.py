"""Saving and loading networks (lasagna.io.checkpoint): round trips, errors that name the file, atomicity."""

from __future__ import annotations

import json

import pytest
import torch

from lasagna.errors import LasagnaError
from lasagna.io import checkpoint as io
from lasagna.priors.unet import ScheduleConfig, UNetPrior
from tests.priors.test_unet import randomize, toy_config


@pytest.fixture()
def saved(tmp_path):
    prior = randomize(
        UNetPrior(toy_config(schedule=ScheduleConfig(kind="cosine", num_steps=500), prediction="epsilon"))
    )
    prior.save_pretrained(tmp_path / "p")
    return prior, tmp_path / "p"


class TestSavePretrained:
    def test_round_trip_same_outputs(self, saved):
        prior, path = saved
        loaded = UNetPrior.from_pretrained(path)
        assert not loaded.training
        assert loaded.config == prior.config
        assert loaded.vocabulary == prior.vocabulary and loaded.schedule.num_steps == 500
        torch.testing.assert_close(loaded.schedule.alphas_cumprod, prior.schedule.alphas_cumprod, atol=0, rtol=0)
        z, t, img = torch.randn(2, 3, 8, 8), torch.tensor([3, 444]), torch.rand(2, 3, 8, 8)
        lab = torch.tensor([0, 3])
        with torch.no_grad():
            torch.testing.assert_close(loaded._eps(z, t, lab, img), prior._eps(z, t, lab, img), atol=0, rtol=0)

    def test_config_json_is_self_describing(self, saved):
        _, path = saved
        doc = json.loads((path / "config.json").read_text())
        assert doc["format"] == "lasagna.unet_prior" and doc["version"] == 1
        cfg = doc["config"]
        assert cfg["vocabulary"] == ["left", "right", "top"]
        assert cfg["schedule"] == {"num_steps": 500, "kind": "cosine", "beta_start": 1e-4, "beta_end": 0.02}
        assert cfg["prediction"] == "epsilon" and cfg["channels"] == [8, 16]
        tensors, meta = io.load_tensors(path / "model.safetensors")
        assert meta["format"] == "lasagna.unet_prior"
        assert all(t.dtype == torch.float32 for t in tensors.values())

    def test_dtype_on_load(self, saved):
        _, path = saved
        loaded = UNetPrior.from_pretrained(path, dtype=torch.float64)
        assert next(loaded.parameters()).dtype == torch.float64


class TestErrors:
    def test_missing_folder(self, tmp_path):
        with pytest.raises(LasagnaError, match="config.json not found"):
            UNetPrior.from_pretrained(tmp_path / "nothing")

    def test_missing_weights(self, saved):
        _, path = saved
        (path / "model.safetensors").unlink()
        with pytest.raises(LasagnaError, match="model.safetensors: file not found"):
            UNetPrior.from_pretrained(path)

    def test_wrong_format_and_version(self, saved):
        _, path = saved
        doc = json.loads((path / "config.json").read_text())
        (path / "config.json").write_text(json.dumps({**doc, "format": "lasagna.corrective"}))
        with pytest.raises(LasagnaError, match="format is 'lasagna.corrective'; expected 'lasagna.unet_prior'"):
            UNetPrior.from_pretrained(path)
        (path / "config.json").write_text(json.dumps({**doc, "version": 9}))
        with pytest.raises(LasagnaError, match="version is 9; expected 1"):
            UNetPrior.from_pretrained(path)

    def test_invalid_json_and_config(self, saved):
        _, path = saved
        doc = json.loads((path / "config.json").read_text())
        (path / "config.json").write_text("{not json")
        with pytest.raises(LasagnaError, match="not valid JSON"):
            UNetPrior.from_pretrained(path)
        doc["config"]["res_blocks"] = 0
        (path / "config.json").write_text(json.dumps(doc))
        with pytest.raises(LasagnaError, match=r"config\.res_blocks"):
            UNetPrior.from_pretrained(path)

    def test_weights_that_do_not_match_the_config(self, saved, tmp_path):
        _, path = saved
        other = UNetPrior(toy_config(channels=(8, 16, 32)))
        io.save_tensors(path / "model.safetensors", other.state_dict(), {"format": "lasagna.unet_prior"})
        with pytest.raises(LasagnaError, match="weights do not match the config"):
            UNetPrior.from_pretrained(path)
        wider = UNetPrior(toy_config(channels=(12, 16)))
        io.save_tensors(path / "model.safetensors", wider.state_dict(), {"format": "lasagna.unet_prior"})
        with pytest.raises(LasagnaError, match="has shape"):
            UNetPrior.from_pretrained(path)

    def test_truncated_weights(self, saved):
        _, path = saved
        data = (path / "model.safetensors").read_bytes()
        (path / "model.safetensors").write_bytes(data[: len(data) // 2])
        with pytest.raises(LasagnaError, match="cannot read safetensors"):
            UNetPrior.from_pretrained(path)


class TestAtomic:
    def test_failed_save_leaves_previous_files(self, saved, monkeypatch):
        prior, path = saved
        before = {p.name: p.read_bytes() for p in path.iterdir()}

        def boom(*a, **k):
            raise RuntimeError("disk full")

        monkeypatch.setattr(io, "_st_save", boom)
        with pytest.raises(RuntimeError, match="disk full"):
            randomize(UNetPrior(prior.config), seed=5).save_pretrained(path)
        after = {p.name: p.read_bytes() for p in path.iterdir()}
        assert after == before  # untouched, and no temporary file left behind

    def test_tensors_and_metadata_round_trip(self, tmp_path):
        tensors = {"a": torch.arange(6.0).reshape(2, 3), "b": torch.tensor([1, 2], dtype=torch.int64)}
        io.save_tensors(tmp_path / "x.safetensors", tensors, {"step": "12"})
        back, meta = io.load_tensors(tmp_path / "x.safetensors")
        assert meta == {"step": "12"}
        assert set(back) == {"a", "b"} and torch.equal(back["a"], tensors["a"]) and torch.equal(back["b"], tensors["b"])
        assert [p.name for p in tmp_path.iterdir()] == ["x.safetensors"]
