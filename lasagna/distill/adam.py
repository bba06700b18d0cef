"""Adam for the short optimisations of an edit, without ``torch.optim``'s first-call cost.

``torch.optim.Optimizer`` wraps its ``__init__`` (and ``step``, ``zero_grad``, ``load_state_dict``) in
``torch._disable_dynamo``, which imports ``torch._dynamo`` on the first call of the process: 1.1–1.4 s on the
project's 2-vCPU boxes, as long as the 150 steps of a whole 512² relight edit (``benchmarks/cold_edit.py``). A
command-line edit pays it every time; nothing here uses dynamo.

``Adam`` is the same optimiser without that wrapper: its step calls torch's own functional Adam
(``torch.optim.adam.adam``, the single-tensor form ``torch.optim.Adam`` itself runs on the CPU), so each update is
torch's, bit for bit (``tests/distill/test_adam.py``), and its ``state_dict`` has ``torch.optim.Adam``'s layout, so
a checkpoint written with either loads into the other (``lasagna.io.checkpoint``). Only what the per-image runs use
is offered: one group, no weight decay, no AMSGrad. Training (``lasagna.training``) keeps ``torch.optim.Adam``: its
runs are minutes long, and its checkpoints are read by ``torch.optim``'s own code.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable
from typing import Any

import torch
from torch import Tensor
from torch.optim.adam import adam as functional_adam

# torch.optim.Adam's defaults (Kingma & Ba 2015, Algorithm 1: β₁ 0.9, β₂ 0.999, ε 10⁻⁸).
BETAS = (0.9, 0.999)
EPS = 1e-8


def _step_dtype() -> torch.dtype:
    """torch.optim's scalar dtype: float64 under a float64 default dtype, else float32."""
    return torch.float64 if torch.get_default_dtype() == torch.float64 else torch.float32


class Adam:
    """``torch.optim.Adam(params, lr)`` for one parameter group (module docstring): ``param_groups[0]["lr"]`` may
    be set between steps (a schedule), ``zero_grad``, ``step``, ``state_dict`` and ``load_state_dict`` as torch's."""

    def __init__(self, params: Iterable[Tensor], lr: float, betas: tuple[float, float] = BETAS, eps: float = EPS):
        params = list(params)
        if not params:
            raise ValueError("optimizer got an empty parameter list")
        self.param_groups: list[dict[str, Any]] = [
            {
                "params": params,
                "lr": lr,
                "betas": tuple(betas),
                "eps": eps,
                "weight_decay": 0,
                "amsgrad": False,
                "maximize": False,
                "foreach": None,
                "capturable": False,
                "differentiable": False,
                "fused": None,
                "decoupled_weight_decay": False,
            }
        ]
        self.state: dict[Tensor, dict[str, Tensor]] = {}

    @property
    def params(self) -> list[Tensor]:
        return self.param_groups[0]["params"]

    def zero_grad(self, set_to_none: bool = True) -> None:
        for p in self.params:
            if set_to_none:
                p.grad = None
            elif p.grad is not None:
                p.grad.detach_().zero_()

    @torch.no_grad()
    def step(self) -> None:
        group = self.param_groups[0]
        params, grads, avgs, avg_sqs, steps = [], [], [], [], []
        for p in self.params:
            if p.grad is None:
                continue
            state = self.state.get(p)
            if state is None:  # as torch.optim.Adam._init_group: the step count a CPU scalar of the default dtype
                state = self.state[p] = {
                    "step": torch.tensor(0.0, dtype=_step_dtype()),
                    "exp_avg": torch.zeros_like(p, memory_format=torch.preserve_format),
                    "exp_avg_sq": torch.zeros_like(p, memory_format=torch.preserve_format),
                }
            params.append(p)
            grads.append(p.grad)
            avgs.append(state["exp_avg"])
            avg_sqs.append(state["exp_avg_sq"])
            steps.append(state["step"])
        if not params:
            return
        beta1, beta2 = group["betas"]
        functional_adam(
            params,
            grads,
            avgs,
            avg_sqs,
            [],
            steps,
            foreach=False,
            capturable=False,
            differentiable=False,
            fused=None,
            grad_scale=None,
            found_inf=None,
            has_complex=any(torch.is_complex(p) for p in params),
            amsgrad=False,
            beta1=beta1,
            beta2=beta2,
            lr=group["lr"],
            weight_decay=0.0,
            eps=group["eps"],
            maximize=False,
        )

    def state_dict(self) -> dict[str, Any]:
        """``torch.optim.Adam.state_dict()``'s layout: state keyed by the parameter's index."""
        index = {id(p): i for i, p in enumerate(self.params)}
        state = {index[id(p)]: dict(s) for p, s in self.state.items()}
        group = {k: v for k, v in self.param_groups[0].items() if k != "params"}
        group["params"] = list(range(len(self.params)))
        return {"state": state, "param_groups": [group]}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Restore a ``state_dict`` of this class or of ``torch.optim.Adam`` over the same parameters."""
        groups = state_dict["param_groups"]
        if len(groups) != 1 or len(groups[0]["params"]) != len(self.params):
            raise ValueError("loaded state dict has a different number of parameter groups or parameters")
        if groups[0].get("amsgrad") or groups[0].get("weight_decay"):
            raise ValueError("loaded state dict uses AMSGrad or weight decay, which this Adam does not offer")
        self.param_groups[0].update({k: copy.deepcopy(v) for k, v in groups[0].items() if k != "params"})
        self.param_groups[0]["betas"] = tuple(self.param_groups[0]["betas"])
        self.state = {}
        for i, p in enumerate(self.params):
            s = state_dict["state"].get(i, state_dict["state"].get(str(i)))
            if s is None:
                continue
            step = s["step"]
            self.state[p] = {
                "step": (step if torch.is_tensor(step) else torch.tensor(float(step))).to(_step_dtype()).cpu(),
                "exp_avg": s["exp_avg"].to(device=p.device, dtype=p.dtype),
                "exp_avg_sq": s["exp_avg_sq"].to(device=p.device, dtype=p.dtype),
            }
