"""The learners' Adam against torch's fused Adam: the same numbers bit for bit, the same saved state."""

import torch

from layered.learners.adam import Adam
from layered.learners.td3 import mlp


def _net(seed):
    torch.manual_seed(seed)
    return mlp((5, 16, 16, 2))


def _steps(net, opt, steps, seed, skip=()):
    """`steps` steps on random batches; in the steps of `skip` only the last layer has a gradient."""
    g = torch.Generator().manual_seed(seed)
    for t in range(steps):
        opt.zero_grad(set_to_none=True)
        x = torch.randn(8, 5, generator=g)
        out = net(x).square().mean()
        if t in skip:
            out = net[-1](torch.randn(8, 16, generator=g)).square().mean()
        out.backward()
        opt.step()


def test_steps_are_torch_fused_adams_bit_for_bit_and_the_state_is_saved_as_it_saves_it():
    ours, theirs = _net(0), _net(0)
    mine, reference = Adam(ours.parameters(), 3e-3), torch.optim.Adam(theirs.parameters(), lr=3e-3, fused=True)
    _steps(ours, mine, 7, seed=1, skip={0, 4})  # the first layers' moments are made at their first gradient
    _steps(theirs, reference, 7, seed=1, skip={0, 4})
    for a, b in zip(ours.parameters(), theirs.parameters(), strict=True):
        assert torch.equal(a, b)
    saved, expected = mine.state_dict(), reference.state_dict()
    assert saved["param_groups"] == expected["param_groups"]
    assert saved["state"].keys() == expected["state"].keys()
    for i, moments in expected["state"].items():
        assert saved["state"][i].keys() == moments.keys()
        assert all(torch.equal(saved["state"][i][name], value) for name, value in moments.items())
    assert expected["state"][0]["step"].item() == 5  # (the first layer had no gradient in two of the seven)


def test_a_loaded_state_continues_as_the_saved_optimiser_would_at_the_rate_given_here():
    ours, theirs = _net(2), _net(2)
    reference = torch.optim.Adam(theirs.parameters(), lr=1e-3, fused=True)
    _steps(theirs, reference, 3, seed=5)
    ours.load_state_dict(theirs.state_dict())
    mine = Adam(ours.parameters(), 1e-3)
    mine.load_state_dict(reference.state_dict())
    _steps(ours, mine, 4, seed=6)
    _steps(theirs, reference, 4, seed=6)
    for a, b in zip(ours.parameters(), theirs.parameters(), strict=True):
        assert torch.equal(a, b)
    # the loaded tensors are copies: stepping does not write into the state it was given
    assert reference.state_dict()["state"][0]["step"].item() == 7
    slower = Adam(ours.parameters(), 1e-4)
    slower.load_state_dict(mine.state_dict())
    assert slower.state_dict()["param_groups"][0]["lr"] == 1e-4
