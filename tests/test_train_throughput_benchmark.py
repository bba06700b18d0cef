"""benchmarks/train_throughput.py times the training step's own two parts (`step_scenes`, `step_loss` and its
backward), from fresh scenes and from a scene bank, and reports scenes per second as the batch over their sum."""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import train_throughput  # noqa: E402


def test_rows_time_both_parts_and_scenes_per_second_is_the_batch_over_their_sum(capsys):
    assert (
        train_throughput.main(
            [
                "--device",
                "cpu",
                "--batches",
                "2",
                "--zooms",
                "1",
                "2",
                "--repeats",
                "1",
                "--channels",
                "8,16",
                "--bank",
                "6",
            ]
        )
        == 0
    )
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert [(r["batch"], r["zoom"], r["render_on"]) for r in out["rows"]] == [
        (2, 1.0, "device"),
        (2, 1.0, "bank"),
        (2, 2.0, "device"),
        (2, 2.0, "bank"),
    ]
    assert all(r["bank"] == 6 and r["bank_build_s"] > 0 for r in out["rows"] if r["render_on"] == "bank")
    for r in out["rows"]:
        assert r["render_s"] > 0 and r["net_s"] > 0
        assert abs(r["scenes_per_s"] - 2 / (r["render_s"] + r["net_s"])) < 0.05 * r["scenes_per_s"] + 0.1
