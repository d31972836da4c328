"""One step of a fit's gradient descent (its optimisers, under their learning-rate decays), and the fit's first and
last loss (held on the device inside the optimisation loop, read once after it)."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from mapping.method.adam import Adam, CosineDecay


class Descent:
    """Optimisers and their learning-rate schedules, stepped once per loss; `losses()` after the loop."""

    def __init__(self, optimisers: Sequence[Adam], decays: Sequence[CosineDecay] = ()):
        self.optimisers, self.decays = list(optimisers), list(decays)
        self.first: torch.Tensor | None = None
        self.last: torch.Tensor | None = None

    def step(self, loss: torch.Tensor) -> None:
        for optimiser in self.optimisers:
            optimiser.zero_grad()
        loss.backward()
        for optimiser in self.optimisers:
            optimiser.step()
        for decay in self.decays:
            decay.step()
        self.last = loss.detach()
        if self.first is None:
            self.first = self.last

    def losses(self) -> tuple[float, float]:
        """(first, last) loss of the fit; (0, 0) when it took no step."""
        return (float(self.first), float(self.last)) if self.last is not None else (0.0, 0.0)
