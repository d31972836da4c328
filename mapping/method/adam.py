"""Adam and its cosine learning-rate decay for the map's fits, computed as torch.optim.Adam (its single-tensor path,
the one it takes for CPU tensors) and torch.optim.lr_scheduler.CosineAnnealingLR compute them, step for step and bit
for bit (tests/mapping/test_adam.py), without torch.optim: constructing a torch.optim optimiser imports
torch._dynamo (torch/_compile.py's lazy import in `add_param_group`), 2.7-2.9 s of every process that fits a map on
these machines, for a compiler the fits never use.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import torch


@dataclass
class ParamGroup:
    """Parameters that share a learning rate, with each one's Adam state (steps taken, first and second moments)."""

    params: list[torch.Tensor]
    lr: float
    steps: list[int]
    exp_avg: list[torch.Tensor | None]
    exp_avg_sq: list[torch.Tensor | None]

    @staticmethod
    def of(params: Iterable[torch.Tensor], lr: float) -> ParamGroup:
        params = list(params)
        return ParamGroup(params, float(lr), [0] * len(params), [None] * len(params), [None] * len(params))


class Adam:
    """Adam (no weight decay, no AMSGrad) over groups of (parameters, learning rate)."""

    def __init__(self, groups: Sequence[tuple[Iterable[torch.Tensor], float]],
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        self.groups = [ParamGroup.of(params, lr) for params, lr in groups]
        self.betas, self.eps = betas, eps

    def zero_grad(self) -> None:
        for group in self.groups:
            for p in group.params:
                p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        """One step of every parameter that has a gradient (one without is left, its state too, as torch does)."""
        beta1, beta2 = self.betas
        for group in self.groups:
            for i, param in enumerate(group.params):
                if param.grad is None:
                    continue
                grad = param.grad
                if group.exp_avg[i] is None:
                    group.exp_avg[i] = torch.zeros_like(param, memory_format=torch.preserve_format)
                    group.exp_avg_sq[i] = torch.zeros_like(param, memory_format=torch.preserve_format)
                exp_avg, exp_avg_sq = group.exp_avg[i], group.exp_avg_sq[i]
                group.steps[i] += 1
                step = float(group.steps[i])
                exp_avg.lerp_(grad, 1 - beta1)
                exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
                bias_correction1 = 1 - beta1 ** step
                bias_correction2 = 1 - beta2 ** step
                step_size = group.lr / bias_correction1
                denom = (exp_avg_sq.sqrt() / bias_correction2 ** 0.5).add_(self.eps)
                param.addcdiv_(exp_avg, denom, value=-step_size)


class CosineDecay:
    """Each group's learning rate from its first value down to `eta_min` over `steps` steps along half a cosine (the
    same `eta_min` for every group), updated by CosineAnnealingLR's recursion."""

    def __init__(self, adam: Adam, steps: int, eta_min: float = 0.0):
        self.adam, self.steps, self.eta_min = adam, steps, eta_min
        self.base = [group.lr for group in adam.groups]
        self.taken = 0

    def step(self) -> None:
        self.taken += 1
        t, T = self.taken, self.steps
        for group, base in zip(self.adam.groups, self.base, strict=True):
            if (t - 1 - T) % (2 * T) == 0:  # past the end: the cosine's next half-period rises again
                group.lr = group.lr + (base - self.eta_min) * (1 - math.cos(math.pi / T)) / 2
            else:
                group.lr = (1 + math.cos(math.pi * t / T)) / (1 + math.cos(math.pi * (t - 1) / T)) \
                    * (group.lr - self.eta_min) + self.eta_min
