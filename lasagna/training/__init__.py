"""The training tier (above ``lasagna.world``): the one resumable loop and the trainers built on it.

    loop.py        train_loop, LoopConfig: Adam, EMA, lr schedules, time budget, resume bit for bit, DDP
    prior.py       train_prior: a conditional UNet prior on world batches (``lasagna train-prior``)
    corrective.py  train_corrective (the LMC-SDS b̂ network), fit_spectral (closed form)
                   (``lasagna train-corrective``)
    generator.py   train_layer_generator: a preset's amortised layer generator (``lasagna train-layer``)
    tasks.py       the world tasks (relight, colorize, light): base layers, labels and true layers

Checkpoints and run folders are written in ``lasagna.io.checkpoint``'s formats.
"""

from lasagna.document.preset import TASK_FOR_BLEND
from lasagna.training.corrective import CorrectiveTrainConfig, fit_spectral, train_corrective
from lasagna.training.generator import AmortisedConfig, AmortisedResult, train_layer_generator
from lasagna.training.loop import LoopConfig, LoopResult, cumulative_seconds, read_log, train_loop
from lasagna.training.prior import PriorTrainConfig, train_prior
from lasagna.training.tasks import TASKS, Task, task_batch

__all__ = [
    "AmortisedConfig",
    "AmortisedResult",
    "CorrectiveTrainConfig",
    "LoopConfig",
    "LoopResult",
    "PriorTrainConfig",
    "TASKS",
    "TASK_FOR_BLEND",
    "Task",
    "cumulative_seconds",
    "fit_spectral",
    "read_log",
    "task_batch",
    "train_corrective",
    "train_layer_generator",
    "train_loop",
    "train_prior",
]
