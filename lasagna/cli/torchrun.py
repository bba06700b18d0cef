"""The module ``torchrun`` starts to train a layer generator on several processes (not a ``lasagna``
subcommand: torchrun needs a module to run, and every process reads the same config file)::

    python -m torch.distributed.run --nproc_per_node=N -m lasagna.cli.torchrun --config C.json --out DIR

``C.json`` is an ``AmortisedConfig`` (``lasagna.training.generator``); the run is resumable like
``lasagna train-layer``'s. Rank 0 prints the metrics as one JSON line; bad input is one line, exit 2.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from pydantic import ValidationError

from lasagna.cli.common import device_argument
from lasagna.errors import LasagnaError, describe_validation_error


def main(argv: list[str] | None = None) -> int:
    from lasagna.training.generator import AmortisedConfig, train_layer_generator

    p = argparse.ArgumentParser(
        prog="python -m lasagna.cli.torchrun", description="Train a layer generator (resumable; torchrun-ready)."
    )
    p.add_argument("--config", required=True, help="AmortisedConfig as JSON")
    p.add_argument("--out", required=True, help="run folder; run again with the same folder to resume")
    device_argument(p, default=None, help="torch device (default cuda if available, else cpu)")
    args = p.parse_args(argv)
    try:
        config = AmortisedConfig.model_validate_json(Path(args.config).read_text(encoding="utf-8"))
        result = train_layer_generator(config, args.out, device=args.device)
    except ValidationError as exc:
        print(f"error: {describe_validation_error(exc, args.config)}", file=sys.stderr)
        return 2
    except (LasagnaError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if os.environ.get("RANK", "0") == "0":  # the process group is closed by now: torchrun's variable says who
        print(json.dumps(result.metrics))
    return 0


if __name__ == "__main__":
    sys.exit(main())
