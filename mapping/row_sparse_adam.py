"""Adam for per-vertex parameter tables that touches only the rows a step used (lazy, per-row step count).

Moment buffers are allocated only for rows that have ever been updated, so a long route's never-seen
vertices cost no optimiser memory, and a step costs O(rows used), not O(route).
"""

from __future__ import annotations

import torch


class RowSparseAdam:
    def __init__(self, table: torch.Tensor, lr: float, betas=(0.9, 0.999), eps: float = 1e-8):
        self.table = table  # (N, D), updated in place
        self.lr, self.betas, self.eps = lr, betas, eps
        self.slot = torch.full((len(table),), -1, dtype=torch.int64)
        width = table.shape[1]
        self.m = torch.zeros(0, width)
        self.v = torch.zeros(0, width)
        self.t = torch.zeros(0)
        self.used = 0

    def _slots(self, rows: torch.Tensor) -> torch.Tensor:
        new = rows[self.slot[rows] < 0]
        if len(new):
            need = self.used + len(new)
            if need > len(self.m):
                grow = max(need, 2 * len(self.m), 1024) - len(self.m)
                self.m = torch.cat([self.m, self.m.new_zeros(grow, self.m.shape[1])])
                self.v = torch.cat([self.v, self.v.new_zeros(grow, self.v.shape[1])])
                self.t = torch.cat([self.t, self.t.new_zeros(grow)])
            self.slot[new] = torch.arange(self.used, need)
            self.used = need
        return self.slot[rows]

    def step(self, rows: torch.Tensor, grad: torch.Tensor) -> None:
        """rows: unique row ids (M,); grad: their gradient (M, D)."""
        b1, b2 = self.betas
        s = self._slots(rows)
        t = self.t[s] + 1
        m = self.m[s].mul_(b1).add_(grad, alpha=1 - b1)
        v = self.v[s].mul_(b2).addcmul_(grad, grad, value=1 - b2)
        self.m[s], self.v[s], self.t[s] = m, v, t
        m_hat = m / (1 - b1**t)[:, None]
        v_hat = v / (1 - b2**t)[:, None]
        self.table[rows] -= self.lr * m_hat / (v_hat.sqrt() + self.eps)

    def state_dict(self) -> dict:
        used = torch.nonzero(self.slot >= 0)[:, 0]
        s = self.slot[used]
        return {"rows": used, "m": self.m[s], "v": self.v[s], "t": self.t[s]}
