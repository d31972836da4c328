"""Adam for per-vertex parameter tables with the semantics of dense Adam at the cost of the rows used.

Dense Adam (what a plain PyTorch implementation of the paper does) keeps moving every row on its
momentum at every step, gradient or not. Here a row is only visited when it has a gradient; the idle
steps it missed are applied then in closed form (moments decay by beta^k; the displacement is a
geometric series: exact for the first `_EXACT_IDLE` idle steps, the tail with the bias correction of
the step after those), and `flush` settles
every row at the end. Moment buffers exist only for rows that have ever had a gradient, so a long
route's never-seen vertices cost no optimiser memory, and a step costs O(rows used), not O(route).
"""

from __future__ import annotations

import torch

_EXACT_IDLE = 48  # idle steps summed term by term (r^48 ~ 0.007 of the first term)


class RowSparseAdam:
    def __init__(self, table: torch.Tensor, lr: float, betas=(0.9, 0.999), eps: float = 1e-8):
        self.table = table  # (N, D), updated in place
        self.lr, self.betas, self.eps = lr, betas, eps
        device = table.device  # every buffer beside the table: a step reads nothing back to the host
        self.slot = torch.full((len(table),), -1, dtype=torch.int64, device=device)
        width = table.shape[1]
        self.m = torch.zeros(0, width, device=device)
        self.v = torch.zeros(0, width, device=device)
        self.last = torch.zeros(0, dtype=torch.int64, device=device)  # global step of each row's last update
        self.used = 0
        self.t = 0  # global step count
        self._cum = torch.zeros(0, _EXACT_IDLE + 1, dtype=torch.float64, device=device)

    def _slots(self, rows: torch.Tensor) -> torch.Tensor:
        new = rows[self.slot[rows] < 0]
        if len(new):
            need = self.used + len(new)
            if need > len(self.m):
                grow = max(need, 2 * len(self.m), 1024) - len(self.m)
                self.m = torch.cat([self.m, self.m.new_zeros(grow, self.m.shape[1])])
                self.v = torch.cat([self.v, self.v.new_zeros(grow, self.v.shape[1])])
                self.last = torch.cat([self.last, self.last.new_zeros(grow)])
            self.slot[new] = torch.arange(self.used, need, device=self.slot.device)
            self.last[self.used : need] = self.t - 1
            self.used = need
        return self.slot[rows]

    def _catch_up(self, rows: torch.Tensor, s: torch.Tensor, until: int) -> None:
        """Apply the zero-gradient steps last+1 .. until-1 that rows `rows` (slots `s`) missed (none idle: every
        update below is over no rows; not tested first, which would read the device back each step)."""
        b1, b2 = self.betas
        last = self.last[s]
        k = (until - 1 - last).clamp(min=0)
        idle = k > 0
        rows, s, last, k = rows[idle], s[idle], last[idle], k[idle].to(self.m.dtype)
        m, v = self.m[s], self.v[s]
        r = b1 / b2**0.5
        cum = self._idle_sums(until)
        head = cum[last, k.clamp(max=_EXACT_IDLE).long()]
        extra = (k - _EXACT_IDLE).clamp(min=0)
        first_tail = (last + _EXACT_IDLE + 1).to(torch.float64)
        tail_bias = (1 - b2**first_tail).sqrt() / (1 - b1**first_tail)
        series = (head + tail_bias * r ** (_EXACT_IDLE + 1) * (1 - r**extra) / (1 - r)).to(self.m.dtype)
        self.table[rows] -= (self.lr * series)[:, None] * m / (v.sqrt() + self.eps)
        self.m[s] = m * (b1**k)[:, None]
        self.v[s] = v * (b2**k)[:, None]
        self.last[s] = until - 1

    def _idle_sums(self, until: int) -> torch.Tensor:
        """cum[a, k] = sum_{j=1..k} r^j * bias(a + j): the displacement (in units of lr m / sqrt(v)) of
        k idle steps after global step a, for a < until and k <= _EXACT_IDLE."""
        if len(self._cum) < until:
            b1, b2 = self.betas
            n = max(until, 2 * len(self._cum), 256)
            device = self.table.device
            step = (torch.arange(n, dtype=torch.float64, device=device)[:, None]
                    + torch.arange(1, _EXACT_IDLE + 1, device=device)[None, :])
            bias = (1 - b2**step).sqrt() / (1 - b1**step)
            r = b1 / b2**0.5
            terms = (r ** torch.arange(1, _EXACT_IDLE + 1, dtype=torch.float64, device=device)) * bias
            self._cum = torch.cat([torch.zeros(n, 1, dtype=torch.float64, device=device), terms.cumsum(1)], 1)
        return self._cum

    def step(self, rows: torch.Tensor, grad: torch.Tensor) -> None:
        """One global step; rows: unique row ids (M,) that have a gradient (M, D)."""
        self.t += 1
        b1, b2 = self.betas
        s = self._slots(rows)
        self._catch_up(rows, s, self.t)
        m = self.m[s].mul_(b1).add_(grad, alpha=1 - b1)
        v = self.v[s].mul_(b2).addcmul_(grad, grad, value=1 - b2)
        self.m[s], self.v[s] = m, v
        self.last[s] = self.t
        m_hat = m / (1 - b1**self.t)
        v_hat = v / (1 - b2**self.t)
        self.table[rows] -= self.lr * m_hat / (v_hat.sqrt() + self.eps)

    def flush(self) -> None:
        """Settle every row as dense Adam would stand after the last step."""
        rows = torch.nonzero(self.slot >= 0)[:, 0]
        self._catch_up(rows, self.slot[rows], self.t + 1)

    def state_dict(self) -> dict:
        used = torch.nonzero(self.slot >= 0)[:, 0]
        s = self.slot[used]
        return {"t": self.t, "rows": used, "m": self.m[s], "v": self.v[s], "last": self.last[s]}
