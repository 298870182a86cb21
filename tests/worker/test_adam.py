"""worker.adam.Adam against torch.optim.Adam: the same numbers bit for bit, and each reads the other's state."""

from __future__ import annotations

import io
import subprocess
import sys

import pytest
import torch
from torch import nn

from worker.adam import Adam


def _nets(seed: int) -> tuple[nn.Module, nn.Module]:
    torch.manual_seed(seed)
    net = nn.Sequential(nn.Linear(5, 16), nn.Tanh(), nn.Linear(16, 3))
    twin = nn.Sequential(nn.Linear(5, 16), nn.Tanh(), nn.Linear(16, 3))
    twin.load_state_dict(net.state_dict())
    return net, twin


def _through_a_file(state: dict) -> dict:
    """A state dict as a model file gives it back (torch's Adam keeps a loaded ``step`` tensor without copying)."""
    buf = io.BytesIO()
    torch.save(state, buf)
    buf.seek(0)
    return torch.load(buf)


def _step(net: nn.Module, opt: Adam | torch.optim.Adam, x: torch.Tensor, skip_bias: bool = False) -> None:
    opt.zero_grad()
    net(x).pow(2).mean().backward()
    if skip_bias:  # a parameter without a gradient is left alone (and gets no state) by both
        net[2].bias.grad = None
    opt.step()


@pytest.mark.parametrize("lr", [3e-4, 1e-3, 0.1])
def test_the_same_steps_give_the_same_parameters_bit_for_bit(lr: float) -> None:
    ours_net, torch_net = _nets(0)
    ours, theirs = Adam(ours_net.parameters(), lr=lr), torch.optim.Adam(torch_net.parameters(), lr=lr)
    gen = torch.Generator().manual_seed(1)
    for i in range(200):
        x = torch.randn(32, 5, generator=gen) * (1 + i % 7)
        _step(ours_net, ours, x, skip_bias=i < 3)
        _step(torch_net, theirs, x, skip_bias=i < 3)
    for a, b in zip(ours_net.parameters(), torch_net.parameters(), strict=True):
        assert torch.equal(a, b)
    for a, b in zip(ours.state.values(), theirs.state.values(), strict=True):
        assert all(torch.equal(a[k], b[k]) for k in ("step", "exp_avg", "exp_avg_sq"))


def test_each_reads_the_others_state_and_goes_on_identically() -> None:
    src_net, _ = _nets(2)
    src = torch.optim.Adam(src_net.parameters(), lr=1e-3)
    for _ in range(5):
        _step(src_net, src, torch.randn(8, 5))
    saved = _through_a_file(src.state_dict())
    assert set(saved["param_groups"][0]) <= set(Adam(src_net.parameters(), lr=1e-3).state_dict()["param_groups"][0])

    ours_net, torch_net = _nets(3)
    ours_net.load_state_dict(src_net.state_dict())
    torch_net.load_state_dict(src_net.state_dict())
    ours, theirs = Adam(ours_net.parameters(), lr=5.0), torch.optim.Adam(torch_net.parameters(), lr=5.0)
    ours.load_state_dict(saved)  # torch's state into ours: lr and moments come from the file
    theirs.load_state_dict(_through_a_file(ours.state_dict()))  # and ours back into torch
    assert ours.param_groups[0]["lr"] == theirs.param_groups[0]["lr"] == 1e-3
    x = torch.randn(8, 5)
    _step(ours_net, ours, x)
    _step(torch_net, theirs, x)
    for a, b in zip(ours_net.parameters(), torch_net.parameters(), strict=True):
        assert torch.equal(a, b)
    # the loaded state is a copy: stepping did not change the file's tensors
    assert torch.equal(saved["state"][0]["step"], torch.tensor(5.0))


def test_a_state_for_other_parameters_is_refused() -> None:
    net, _ = _nets(4)
    other = Adam(nn.Linear(5, 2).parameters(), lr=1e-3)
    with pytest.raises(ValueError, match="does not match"):
        Adam(net.parameters(), lr=1e-3).load_state_dict(other.state_dict())


def test_a_learner_update_does_not_import_torch_dynamo() -> None:
    """What the class is for: a worker process no longer pays for torch._dynamo's import at its first update."""
    code = ("import sys, torch; from worker.adam import Adam; net = torch.nn.Linear(3, 1); "
            "opt = Adam(net.parameters(), lr=1e-3); net(torch.ones(1, 3)).sum().backward(); opt.step(); "
            "print('torch._dynamo' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
