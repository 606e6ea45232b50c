"""flowsynth.nets: torchvision's RAFT-small on demand, and a named error where torchvision is missing."""

import sys

import pytest
import torch

import flowsynth as fs
from flowsynth import nets


def test_raft_small_is_torchvisions_and_runs():
    net = nets.raft_small()
    assert sum(p.numel() for p in net.parameters()) == 990_162  # torchvision's raft_small: 0.99 M parameters
    img = torch.rand(1, 3, 128, 128) * 2 - 1
    with torch.no_grad():
        flows = net(img, img, num_flow_updates=2)
    assert len(flows) == 2 and flows[-1].shape == (1, 2, 128, 128) and torch.isfinite(flows[-1]).all()


def test_missing_torchvision_is_a_named_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "torchvision.models.optical_flow", None)  # import fails as if not installed
    with pytest.raises(fs.errors.DependencyError, match="pip install"):
        nets.raft_small()
