"""The shared training loop's EMA: the plain average and the warm-up ramp, against a float64 re-computation."""

from __future__ import annotations

import pytest
import torch

from lasagna.training import LoopConfig, train_loop
from lasagna.training.loop import read_log


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


# ---- checkpoints: by time as well as by steps; a run killed before its first one -------------------------
class _Killed(Exception):
    pass


def _train(out, *, kill_at: int | None = None, steps: int = 12, **kw) -> torch.nn.Module:
    """Adam on a two-weight model with random draws from the loop's generator; ``kill_at``: raise there."""
    torch.manual_seed(0)
    model = torch.nn.Linear(2, 1, bias=False)

    def step_fn(net, gen, step):
        if step == kill_at:
            raise _Killed
        x = torch.randn(4, 2, generator=gen)
        return (net(x) - 1).pow(2).mean(), {}

    kw.setdefault("checkpoint_every", 1000)
    loop = LoopConfig(steps=steps, lr=0.05, progress=False, **kw)
    return train_loop(model, step_fn, loop, loop, out, checkpoint_format="test").model


def _checkpoint_step(out) -> int:
    from lasagna.io.checkpoint import load_tensors

    return int(load_tensors(out / "checkpoint.safetensors")[1]["step"])


def test_checkpoints_by_time_and_resumes_bit_for_bit(tmp_path):
    full = _train(tmp_path / "full", checkpoint_minutes=None)
    with pytest.raises(_Killed):  # every 1000 steps or ~every step by the clock: by the clock comes first
        _train(tmp_path / "split", kill_at=7, checkpoint_minutes=1e-9)
    assert _checkpoint_step(tmp_path / "split") == 7
    resumed = _train(tmp_path / "split", checkpoint_minutes=None)  # checkpoint_minutes may change on resume
    assert torch.equal(full.weight, resumed.weight)


def test_no_time_checkpoint_when_disabled(tmp_path):
    with pytest.raises(_Killed):
        _train(tmp_path, kill_at=7, checkpoint_minutes=None)
    assert not (tmp_path / "checkpoint.safetensors").exists()
    assert LoopConfig().checkpoint_minutes == 5.0


def test_a_run_killed_before_its_first_checkpoint_takes_another_config(tmp_path):
    import json

    with pytest.raises(_Killed):
        _train(tmp_path, kill_at=5, checkpoint_minutes=None, seed=1, log_every=2)
    assert [r["step"] for r in read_log(tmp_path)] == [2, 4]
    assert (tmp_path / "train_config.json").is_file() and not (tmp_path / "checkpoint.safetensors").exists()
    _train(tmp_path, checkpoint_minutes=None, seed=2)  # nothing was trained: a new config is accepted
    assert json.loads((tmp_path / "train_config.json").read_text())["seed"] == 2
    assert [r["step"] for r in read_log(tmp_path)] == [10]  # the killed run's log (steps 2, 4) is gone
    with pytest.raises(Exception, match="different seed"):  # once trained, the folder is that run's
        _train(tmp_path, checkpoint_minutes=None, seed=3)


def test_expected_stop_follows_the_budget_that_stops_first():
    from lasagna.training.loop import expected_stop

    # train-prior --minutes 40 at 0.5 s a step of 20 000: the budget stops it at step 4 800, not 20 000 (issue 27)
    assert expected_stop(20_000, 0, 100, 50.0, 40) == 100 + 4_700
    assert expected_stop(20_000, 0, 100, 50.0, None) == 20_000  # no budget: the steps
    assert expected_stop(300, 0, 100, 50.0, 40) == 300  # the steps stop it first
    assert expected_stop(20_000, 1_000, 1_000, 0.0, 40) == 20_000  # no rate yet (a resumed run's first step)
    assert expected_stop(20_000, 1_000, 1_100, 50.0, 40) == 1_100 + 4_700  # the rate of this invocation only


def test_progress_bar_total_and_postfix_follow_max_minutes(tmp_path, monkeypatch):
    """With a budget that stops the run first, the bar's total (hence tqdm's ETA) is the budget's last step."""
    import types

    import lasagna.training.loop as loop_module

    clock = types.SimpleNamespace(t=0.0)
    monkeypatch.setattr(loop_module, "time", types.SimpleNamespace(monotonic=lambda: clock.t))
    bars = []

    class Bar:  # records what the loop tells tqdm
        def __init__(self, total, initial, **kw):
            self.total, self.n, self.postfix = total, initial, {}
            bars.append(self)

        def update(self, n):
            self.n += n

        def set_postfix(self, postfix=None, refresh=True, **kw):
            self.postfix = dict(postfix or {}, **kw)

        def close(self):
            pass

    monkeypatch.setattr(loop_module, "tqdm", Bar)
    torch.manual_seed(0)
    model = torch.nn.Linear(1, 1, bias=False)

    def step_fn(net, rng, step):
        clock.t += 2.0  # two seconds a step
        return net.weight.sum(), {}

    loop = LoopConfig(steps=20_000, lr=0.01, checkpoint_every=1000, log_every=1, max_minutes=0.5, progress=True)
    result = train_loop(model, step_fn, loop, loop, tmp_path, checkpoint_format="test")
    (bar,) = bars
    assert result.stopped == "time" and result.step == 16  # 30 s: steps start at 0, 2, …, 30 s
    assert bar.total == result.step == bar.n  # the ETA ran out when the run did
    assert bar.postfix["stops"] == "0.5 min" and "loss" in bar.postfix
