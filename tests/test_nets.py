"""flowsynth.nets: torchvision's RAFT-small on demand, and a named error where torchvision is missing."""

import os
import subprocess
import sys
from pathlib import Path

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


ROOT = Path(__file__).resolve().parents[1]
# In a fresh interpreter, after PATCH: with PLAIN_FIRST, whether torchvision's models import as they are or fail on
# its C++ operators; then raft_small (over what that import left behind), its parameter count, and whether the module
# that registers the operators is torchvision's own (it defines register_meta) or the empty stand-in.
PROBE = """
import sys
{patch}
if {plain_first}:
    try:
        import torchvision.models.optical_flow
        print("plain-imports")
    except RuntimeError as e:
        print("operators" if "torchvision::" in str(e) else "other")
from flowsynth import nets
net = nets.raft_small()
print(sum(p.numel() for p in net.parameters()),
      "own" if hasattr(sys.modules["torchvision._meta_registrations"], "register_meta") else "stand-in")
"""
# torchvision matching torch: its operators' registrations go through (as torch.library's would, the operators there).
MATCHING = "import torch.library\ntorch.library.register_fake = lambda *a, **k: (lambda f: f)"
# a wheel built against another torch: its C++ library does not load, so its operators do not exist.
MISMATCHED = """import torch
load = torch.ops.load_library
def refuse(path):
    if str(path).endswith(("_C.so", "_C.pyd")):
        raise OSError("undefined symbol: a torchvision wheel built against another torch")
    return load(path)
torch.ops.load_library = refuse"""


def _probe(patch: str, plain_first: bool) -> list[str]:
    code = PROBE.format(patch=patch, plain_first=plain_first)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=600, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout.split()


def test_the_stand_in_is_installed_only_where_torchvision_fails_on_its_operators():
    """Each case in a fresh interpreter, since an import of torchvision cannot be undone: where torchvision's models
    import as they are, raft_small, the first to import torchvision, leaves torchvision's own _meta_registrations in
    place; where its C++ library does not load, the plain import fails on the operators, and raft_small, after that
    half-done import, builds the net over the stand-in; as installed here, it uses the stand-in exactly when the
    plain import fails."""
    assert _probe(MATCHING, plain_first=False) == ["990162", "own"]
    assert _probe(MISMATCHED, plain_first=True) == ["operators", "990162", "stand-in"]
    plain, *built = _probe("", plain_first=True)
    assert built == ["990162", {"plain-imports": "own", "operators": "stand-in"}[plain]]
