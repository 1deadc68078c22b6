"""The stages' Adam makes torch.optim.Adam's steps, bit for bit on the CPU, without importing torch._dynamo."""
import subprocess
import sys

import torch

from frodo_optim.adam import Adam


def _run(make_optimiser, steps: int = 60) -> list[torch.Tensor]:
    gen = torch.Generator().manual_seed(3)
    a = torch.randn(64, generator=gen).requires_grad_(True)
    b = torch.randn(3, generator=gen).requires_grad_(True)
    c = torch.tensor(0.3, requires_grad=True)
    unused = torch.zeros(2, requires_grad=True)            # no gradient: left as it is
    target = torch.randn(64, generator=gen)
    opt = make_optimiser([{'params': [a], 'lr': 0.02}, {'params': [b, unused], 'lr': 0.005},
                          {'params': [c], 'lr': 0.01}])
    for _ in range(steps):
        opt.zero_grad()
        loss = ((a - target) ** 2).sum() + (b.sin() * c).sum() + torch.exp(c) + (a[:3] * b).sum()
        loss.backward()
        opt.step()
    return [a.detach(), b.detach(), c.detach(), unused.detach()]


def test_the_same_steps_as_torch_adam():
    ours, theirs = _run(Adam), _run(torch.optim.Adam)
    for x, y in zip(ours, theirs):
        assert torch.equal(x, y)
    assert torch.equal(ours[3], torch.zeros(2))


def test_it_does_not_import_torch_dynamo():
    code = ('import sys, torch\nfrom frodo_optim.adam import Adam\n'
            'p = torch.zeros(3, requires_grad=True)\nopt = Adam([{"params": [p], "lr": 0.1}])\n'
            'p.sum().backward()\nopt.step()\nprint("torch._dynamo" in sys.modules)')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == 'False'
