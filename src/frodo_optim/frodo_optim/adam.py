"""Adam (Kingma & Ba 2015) for the optimiser stages' few parameter tensors.

The same update as `torch.optim.Adam` with its defaults (betas 0.9 / 0.999, eps 1e-8, no weight decay, the
single-tensor path torch takes on the CPU), bit for bit on the CPU (test_adam.py). Why not torch's: its first
`Optimizer` of a process imports torch._dynamo (1.5-2 s on a 2-core CPU, in every process that refines an
object: `frodo reconstruct`, each optimiser node and worker), and its per-step bookkeeping is built for many
parameters, not the three or four of a pose and a code.
"""
from __future__ import annotations

from typing import Iterable

import torch


class Adam:
    """Adam over parameter groups [{'params': [tensor, ...], 'lr': float}, ...] (`torch.optim.Adam`'s form).

    `zero_grad()` sets the gradients to None; `step()` updates every parameter that has a gradient."""

    def __init__(self, groups: Iterable[dict], betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        self.groups = [(list(group['params']), float(group['lr'])) for group in groups]
        self.beta1, self.beta2 = (float(b) for b in betas)
        self.eps = float(eps)
        self.steps: dict[int, int] = {}
        self.moments: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}

    def zero_grad(self) -> None:
        for params, _ in self.groups:
            for p in params:
                p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        b1, b2 = self.beta1, self.beta2
        for params, lr in self.groups:
            for p in params:
                if p.grad is None:
                    continue
                key = id(p)
                if key not in self.moments:
                    self.moments[key] = (torch.zeros_like(p), torch.zeros_like(p))
                m, v = self.moments[key]
                step = self.steps.get(key, 0) + 1
                self.steps[key] = step
                m.lerp_(p.grad, 1 - b1)
                v.mul_(b2).addcmul_(p.grad, p.grad, value=1 - b2)
                # torch keeps the step count as a float: the same powers
                denom = (v.sqrt() / (1 - b2 ** float(step)) ** 0.5).add_(self.eps)
                p.addcdiv_(m, denom, value=-(lr / (1 - b1 ** float(step))))
