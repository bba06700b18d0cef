"""The shared training loop's EMA: the plain average and the warm-up ramp, against a float64 re-computation."""

from __future__ import annotations

import pytest
import torch

from lasagna.training import LoopConfig, train_loop


def _run(tmp_path, **kw) -> tuple[list[float], float]:
    """30 Adam steps of a one-weight model; returns the weights before each step and the loop's final (EMA) weight."""
    model = torch.nn.Linear(1, 1, bias=False)
    with torch.no_grad():
        model.weight.fill_(0.5)
    seen: list[float] = []

    def step_fn(net, gen, step):
        seen.append(float(net.weight.detach().double()))
        return net.weight.sum(), {}  # a constant gradient: Adam moves the weight by lr every step

    loop = LoopConfig(steps=30, lr=0.01, checkpoint_every=1000, progress=False, **kw)
    result = train_loop(model, step_fn, loop, loop, tmp_path, checkpoint_format="test")
    return seen, float(result.model.weight.detach().double())


def _reference(seen: list[float], decay) -> float:
    after = seen[1:] + [seen[-1] + (seen[-1] - seen[-2])]  # the weight after each step
    ema = seen[0]
    for step, w in enumerate(after):
        d = decay(step)
        ema = d * ema + (1 - d) * w
    return ema


@pytest.mark.parametrize("warmup", [False, True])
def test_ema_matches_a_float64_recomputation(tmp_path, warmup):
    seen, final = _run(tmp_path, ema_decay=0.9, ema_warmup=warmup)
    decay = (lambda s: min(0.9, (1 + s) / (10 + s))) if warmup else (lambda s: 0.9)
    assert final == pytest.approx(_reference(seen, decay), abs=1e-6)


def test_warmup_forgets_the_starting_weights(tmp_path):
    seen, plain = _run(tmp_path / "plain", ema_decay=0.99)
    _, ramped = _run(tmp_path / "ramped", ema_decay=0.99, ema_warmup=True)
    last = seen[-1] - 0.01  # the raw weight after the 30th step
    # 0.99^30 = 74 % of the plain average is still the start (0.5); the ramp's average sits near recent weights.
    assert abs(plain - 0.5) < 0.3 * abs(last - 0.5)
    assert abs(ramped - last) < 0.3 * abs(last - 0.5)


def test_ema_at():
    loop = LoopConfig(ema_decay=0.999, ema_warmup=True)
    assert loop.ema_at(0) == pytest.approx(0.1) and loop.ema_at(90) == pytest.approx(91 / 100)
    assert loop.ema_at(10**6) == 0.999 and LoopConfig(ema_decay=0.999).ema_at(0) == 0.999
