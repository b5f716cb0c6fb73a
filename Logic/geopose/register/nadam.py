"""The test-time optimiser: NAdam (Dozat 2016) under a one-cycle learning-rate schedule (Smith 2018).

The arithmetic of ``torch.optim.NAdam`` at its defaults with ``torch.optim.lr_scheduler.OneCycleLR`` (cosine,
two phases, no momentum cycling), step for step and bit for bit (``Testing/Python/test_tto.py`` runs both).
Written out because the first use of any ``torch.optim`` optimiser imports ``torch._dynamo``: about 1 s
of a fresh process's registration on 2 cores, for a two-tensor update.
"""

from __future__ import annotations

import math
from typing import Sequence

__all__ = ["OneCycleNAdam"]


class OneCycleNAdam:
    """NAdam over ``groups`` (``[{"params": [tensor, ...], "lr": peak learning rate}, ...]``, each rate in its
    parameters' own units: rad for a rotation, mm for a shift), each group's
    learning rate rising from ``peak / div_factor`` to its peak over the first ``pct_start`` of
    ``total_steps`` and falling to ``peak / div_factor / final_div_factor`` by the last (cosine).
    :attr:`learning_rates` are those the next :meth:`step` uses."""

    def __init__(self, groups: Sequence[dict], total_steps: int, pct_start: float, div_factor: float,
                 final_div_factor: float, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8,
                 momentum_decay: float = 4e-3) -> None:
        import torch

        if total_steps < 1:
            raise ValueError(f"total_steps must be >= 1, got {total_steps}")
        self.total_steps, self.betas, self.eps, self.momentum_decay = int(total_steps), betas, eps, momentum_decay
        self.phase_ends = (float(pct_start * total_steps) - 1, float(total_steps - 1))
        self.groups = []
        for g in groups:
            peak = float(g["lr"])
            start = peak / div_factor
            params = list(g["params"])
            state = [{"step": 0, "mu_product": torch.ones((), dtype=torch.float32),
                      "exp_avg": torch.zeros_like(p, memory_format=torch.preserve_format),
                      "exp_avg_sq": torch.zeros_like(p, memory_format=torch.preserve_format)} for p in params]
            self.groups.append({"params": params, "state": state, "lrs": (start, peak, start / final_div_factor)})
        self.steps_taken = 0

    @property
    def learning_rates(self) -> list[float]:
        """Each group's learning rate at the next step."""
        return [self._lr(g["lrs"], self.steps_taken) for g in self.groups]

    def _lr(self, lrs: tuple[float, float, float], step: int) -> float:
        """OneCycleLR's cosine anneal at ``step``: ``lrs`` = (start, peak, end). A phase of no length counts as
        done (where ``OneCycleLR`` divides by zero)."""
        warm_end, last = self.phase_ends
        if step <= warm_end:
            begin, end, start_step, end_step = lrs[0], lrs[1], 0.0, warm_end
        else:
            begin, end, start_step, end_step = lrs[1], lrs[2], warm_end, last
        pct = (step - start_step) / (end_step - start_step) if end_step != start_step else 1.0
        return end + (begin - end) / 2.0 * (math.cos(math.pi * pct) + 1)

    def zero_grad(self) -> None:
        """Drop every parameter's gradient (as ``torch.optim``'s ``zero_grad``)."""
        for g in self.groups:
            for p in g["params"]:
                p.grad = None

    def step(self) -> None:
        """One NAdam update of every parameter with a gradient, at the current learning rates."""
        import torch

        if self.steps_taken >= self.total_steps:
            raise ValueError(f"the schedule has {self.total_steps} steps; all were taken")
        beta1, beta2 = self.betas
        with torch.no_grad():
            for g, lr in zip(self.groups, self.learning_rates):
                for p, s in zip(g["params"], g["state"]):
                    if p.grad is None:
                        continue
                    s["step"] += 1
                    step = float(s["step"])
                    mu = beta1 * (1.0 - 0.5 * (0.96 ** (step * self.momentum_decay)))
                    mu_next = beta1 * (1.0 - 0.5 * (0.96 ** ((step + 1) * self.momentum_decay)))
                    s["mu_product"] *= mu
                    mu_product = s["mu_product"].item()
                    s["exp_avg"].lerp_(p.grad, 1 - beta1)
                    s["exp_avg_sq"].mul_(beta2).addcmul_(p.grad, p.grad, value=1 - beta2)
                    denom = s["exp_avg_sq"].div(1 - beta2 ** step).sqrt().add_(self.eps)
                    p.addcdiv_(p.grad, denom, value=-lr * (1.0 - mu) / (1.0 - mu_product))
                    p.addcdiv_(s["exp_avg"], denom, value=(-lr * mu_next) / (1.0 - mu_product * mu_next))
        self.steps_taken += 1
