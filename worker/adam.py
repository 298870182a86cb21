"""Adam (Kingma and Ba, ICLR 2015, Algorithm 1), the optimizer of every learner's networks (paper Eq. 4 and 7).

Why not ``torch.optim.Adam``: its ``step()`` imports ``torch._dynamo`` (about 2 s of CPU, on top of torch's own 3 s),
and every worker process paid that at its first update. This class does the same arithmetic, operation by operation
and in the same order, as torch's single-tensor path, which is the one torch takes for CPU tensors, so that a run
gives the same numbers bit for bit (``tests/worker/test_adam.py`` steps both side by side). Its ``state_dict`` has
torch's layout, so that model files written with either optimizer load with either.

Only what the learners use: one parameter group, no weight decay, no AMSGrad, no closure.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import torch

#: What torch's Adam records per parameter group besides ``lr`` and ``params`` (the values of a plain
#: ``torch.optim.Adam(params, lr)``; kept so that torch can load our state and reports the same settings).
_GROUP_DEFAULTS: dict[str, Any] = {
    "betas": (0.9, 0.999), "eps": 1e-8, "weight_decay": 0, "amsgrad": False, "maximize": False, "foreach": None,
    "capturable": False, "differentiable": False, "fused": None, "decoupled_weight_decay": False,
}


class Adam:
    """Adam over ``params`` with learning rate ``lr`` (Algorithm 1 of Kingma and Ba; torch's update order)."""

    def __init__(self, params: Iterable[torch.Tensor], lr: float) -> None:
        group: dict[str, Any] = {"params": list(params), "lr": lr, **_GROUP_DEFAULTS}
        self.param_groups: list[dict[str, Any]] = [group]
        self.state: dict[torch.Tensor, dict[str, torch.Tensor]] = {}

    def zero_grad(self) -> None:
        """Forget every parameter's gradient (``None``, as torch's default)."""
        for group in self.param_groups:
            for p in group["params"]:
                p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        """One Adam step with each parameter's ``.grad`` (parameters without one are left alone)."""
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            lr, eps = group["lr"], group["eps"]
            for p in group["params"]:
                if p.grad is None:
                    continue
                state = self.state.get(p)
                if state is None:
                    state = self.state[p] = {"step": torch.tensor(0.0, dtype=torch.float32),
                                             "exp_avg": torch.zeros_like(p), "exp_avg_sq": torch.zeros_like(p)}
                grad, m, v, step_t = p.grad, state["exp_avg"], state["exp_avg_sq"], state["step"]
                step_t += 1
                m.lerp_(grad, 1 - beta1)                                   # m_t = b1 m + (1 - b1) g
                v.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)         # v_t = b2 v + (1 - b2) g^2
                step = step_t.item()
                bias_correction1 = 1 - beta1 ** step
                bias_correction2 = 1 - beta2 ** step
                denom = (v.sqrt() / bias_correction2 ** 0.5).add_(eps)      # sqrt(v_hat) + eps
                p.addcdiv_(m, denom, value=-(lr / bias_correction1))        # theta -= lr m_hat / denom

    def state_dict(self) -> dict[str, Any]:
        """torch's layout: per-parameter state by index over the groups' parameters, and the groups' settings."""
        index: dict[torch.Tensor, int] = {}
        groups = []
        for group in self.param_groups:
            ids = [index.setdefault(p, len(index)) for p in group["params"]]
            groups.append({**{k: v for k, v in group.items() if k != "params"}, "params": ids})
        state = {index[p]: dict(s) for p, s in self.state.items()}
        return {"state": state, "param_groups": groups}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Take a ``state_dict`` of this class or of ``torch.optim.Adam`` over the same parameters (copies)."""
        saved_groups = state_dict["param_groups"]
        if len(saved_groups) != len(self.param_groups) or any(
                len(s["params"]) != len(g["params"]) for s, g in zip(saved_groups, self.param_groups, strict=True)):
            raise ValueError("the optimizer state does not match this optimizer's parameters")
        by_id = {i: p for s, g in zip(saved_groups, self.param_groups, strict=True)
                 for i, p in zip(s["params"], g["params"], strict=True)}
        self.state = {}
        for i, saved in state_dict["state"].items():
            p = by_id[int(i)]
            self.state[p] = {k: (v.detach().clone() if k == "step" else v.detach().to(p.dtype).clone())
                             for k, v in saved.items()}
        for s, g in zip(saved_groups, self.param_groups, strict=True):
            g.update({k: v for k, v in s.items() if k != "params"})
