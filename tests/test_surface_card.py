"""benchmarks/surface_card.py: the command a card prints trains what the run's train_config.json records — parsed by
`lasagna train-surface`'s own argument parser, every recorded setting comes back (a card whose command drops a flag
would not reproduce its weights)."""

import argparse
import shlex
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import surface_card  # noqa: E402

from lasagna.cli.train_surface import add_arguments  # noqa: E402

BASE = {
    "lr": 0.0003,
    "warmup_steps": 50,
    "max_minutes": 25.0,
    "batch_size": 32,
    "lights": 3,
    "split": "train",
    "world_seed": 47,
    "zoom": 3.0,
    "init_from": "runs/lit-light/surface",
    "light_given": 0.75,
    "light_jitter": 10.0,
    "light_weight": 0.1,
    "stray": 0.0,
    "shadows": 0.0,
    "rest": 0.0,
    "height_weight": 0.0,
    "relief": 0.5,
    "walls_only": 0.5,
    "scene_bank": 0,
}
NET = {"input": "lit", "output": "height", "channels": [32, 64, 128], "blocks": 2, "silhouette": True}


def parsed(cfg: dict) -> argparse.Namespace:
    words = shlex.split(surface_card.command(cfg, Path("runs/x")))
    assert words[:2] == ["lasagna", "train-surface"]
    p = argparse.ArgumentParser()
    add_arguments(p)
    return p.parse_args(words[2:])


@pytest.mark.parametrize(
    "changes",
    [
        {},  # round 17's M: told the light, walls alone and relief walls, warm-up 50
        {
            "light_given": 0.5,
            "light_jitter": 4.0,
            "light_weight": 1.0,
            "stray": 0.25,
            "scene_bank": 64,
            "shadows": 0.5,
            "rest": 1.0,
            "height_weight": 4.0,
        },
        {"warmup_steps": 100, "relief": 0.0, "walls_only": 0.0, "init_from": None, "world_seed": 7, "zoom": 1.0},
    ],
)
@pytest.mark.parametrize("light_input", [True, False])
def test_the_cards_command_parses_back_to_the_recorded_config(changes, light_input):
    cfg = {**BASE, **changes, "net": {**NET, "working_size": 32, "light_input": light_input}}
    args = parsed(cfg)
    assert args.light_input == light_input and args.silhouette and args.input == "lit"
    assert args.out == "runs/x" and args.channels == "32,64,128" and args.blocks == 2 and args.working_size == 32
    assert args.lr == pytest.approx(cfg["lr"], rel=1e-12) and args.minutes == cfg["max_minutes"]
    assert args.warmup == cfg["warmup_steps"] and args.batch_size == 32 and args.lights == 3
    assert args.world_seed == cfg["world_seed"] and args.zoom == cfg["zoom"] and args.init_from == cfg["init_from"]
    for key in ("light_weight", "stray", "shadows", "rest", "height_weight", "relief", "walls_only", "scene_bank"):
        assert getattr(args, key) == cfg[key], key
    if light_input:  # what the scenes were told is read only by an estimator that reads a light
        assert args.light_given == cfg["light_given"] and args.light_jitter == cfg["light_jitter"]
