"""mapping.method.adam against torch.optim: the same parameters after every step, bit for bit."""

import pytest
import torch

from mapping.method.adam import Adam, CosineDecay


def _models(seed: int) -> tuple[torch.nn.Module, torch.nn.Module]:
    torch.manual_seed(seed)
    model = torch.nn.Sequential(torch.nn.Linear(5, 16), torch.nn.ReLU(), torch.nn.Linear(16, 3))
    twin = torch.nn.Sequential(torch.nn.Linear(5, 16), torch.nn.ReLU(), torch.nn.Linear(16, 3))
    twin.load_state_dict(model.state_dict())
    return model, twin


@pytest.mark.parametrize("decay", [False, True])
def test_adam_and_its_cosine_decay_step_as_torch_optim_does_bit_for_bit(decay):
    """Two groups at different rates (the decay's one eta_min for both, as CosineAnnealingLR's), a parameter without
    a gradient on some steps (left alone, its step count too), 40 steps: every parameter equal to torch.optim's."""
    model, twin = _models(3)
    extra, extra_twin = torch.zeros(4, requires_grad=True), torch.zeros(4, requires_grad=True)
    groups = lambda m, e: [(m[0].parameters(), 0.01), (list(m[2].parameters()) + [e], 0.003)]  # noqa: E731
    ours = Adam(groups(model, extra))
    theirs = torch.optim.Adam([{"params": list(p), "lr": lr} for p, lr in groups(twin, extra_twin)])
    steps = 40
    ours_decay = CosineDecay(ours, steps, eta_min=0.0005) if decay else None
    theirs_decay = torch.optim.lr_scheduler.CosineAnnealingLR(theirs, steps, eta_min=0.0005) if decay else None
    rng = torch.Generator().manual_seed(5)
    for step in range(steps):
        x, y = torch.randn(64, 5, generator=rng), torch.randn(64, 3, generator=rng)
        for m, e, opt in ((model, extra, ours), (twin, extra_twin, theirs)):
            opt.zero_grad()
            loss = (m(x) - y).abs().mean() + ((e - 1) ** 2).sum() * (step % 3 != 0)
            loss.backward()
            if step % 3 == 0:
                e.grad = None  # no gradient this step
            opt.step()
        if decay:
            ours_decay.step()
            theirs_decay.step()
        for a, b in zip(list(model.parameters()) + [extra], list(twin.parameters()) + [extra_twin], strict=True):
            assert torch.equal(a, b), step
        assert [g.lr for g in ours.groups] == [g["lr"] for g in theirs.param_groups]
    assert ours.groups[1].steps[-1] == theirs.state[extra_twin]["step"].item() == 26
    assert not torch.equal(extra, torch.zeros(4))
