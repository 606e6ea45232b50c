"""flowsynth.train.nets: torchvision's RAFT-small on demand, and a named error where torchvision is missing."""

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import flowsynth as fs
from flowsynth.train import nets


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
from flowsynth.train import nets
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


# A torchvision whose import fails as a wheel built for another torch does (its operators are not registered).
FAKE_MISMATCHED = 'raise RuntimeError("operator torchvision::nms does not exist")\n'


def _fake_torchvision(tmp_path: Path, init: str) -> dict:
    """The environment of a process that finds a fake torchvision package (``init`` its __init__.py) first."""
    (tmp_path / "torchvision").mkdir()
    (tmp_path / "torchvision" / "__init__.py").write_text(init)
    (tmp_path / "torchvision" / "version.py").write_text("__version__ = '0.99.0+cu999'\n")
    return {**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{ROOT}"}


def _torch_build() -> str:
    """PyTorch's wheel index folder of this torch, from its version tag (2.13.0+cpu: cpu) or torch.version."""
    tag = torch.__version__.partition("+")[2]
    return tag or ("cpu" if torch.version.cuda is None else "cu" + torch.version.cuda.replace(".", ""))


DATASETS = """
from flowsynth.errors import DependencyError
from flowsynth.train.nets import torchvision_datasets
try:
    print(torchvision_datasets().Sintel.__name__)
except DependencyError as e:
    print("DependencyError:", e)
"""


def test_torchvision_built_for_another_torch_names_the_build_to_install(tmp_path):
    """A torchvision whose import fails on its C++ operators: torchvision_datasets raises DependencyError naming both
    versions and the pip command of the torchvision paired with this torch (torch 2.N.P: 0.(N+15).P, PyTorch's
    compatibility table), from the index of this torch's build, with --no-deps."""
    r = subprocess.run([sys.executable, "-c", DATASETS], capture_output=True, text=True, timeout=300, cwd=tmp_path,
                       env=_fake_torchvision(tmp_path, FAKE_MISMATCHED))
    assert r.returncode == 0, r.stderr[-2000:]
    out = r.stdout
    major, minor, patch = (int(x) for x in torch.__version__.partition("+")[0].split(".")[:3])
    assert out.startswith("DependencyError: torchvision 0.99.0+cu999 was built for another torch"), out
    assert torch.__version__ in out and "operator torchvision::nms does not exist" in out
    assert (f'pip install --no-deps --force-reinstall "torchvision==0.{minor + 15}.{patch}" --index-url '
            f"https://download.pytorch.org/whl/{_torch_build()}") in out, out
    assert {(2, 13): "0.28", (2, 5): "0.20", (2, 2): "0.17"}.get((major, minor), f"0.{minor + 15}") \
        == f"0.{minor + 15}"


def test_torchvision_datasets_as_installed_here(tmp_path):
    """The torchvision installed here, in a fresh process: where its plain import fails on its operators (a wheel
    built for another torch), torchvision_datasets raises the DependencyError, also after raft_small stood in for
    the operators; where it imports, it returns torchvision.datasets."""
    plain = subprocess.run([sys.executable, "-c", "import torchvision"], capture_output=True, text=True, timeout=300,
                           cwd=tmp_path)
    mismatched = plain.returncode != 0 and "torchvision::" in plain.stderr
    assert plain.returncode == 0 or mismatched, plain.stderr[-2000:]
    for before in ("", "from flowsynth.train.nets import raft_small; raft_small()\n"):
        r = subprocess.run([sys.executable, "-c", before + DATASETS], capture_output=True, text=True, timeout=600,
                           cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(ROOT)})
        assert r.returncode == 0, r.stderr[-2000:]
        if mismatched:
            assert r.stdout.startswith("DependencyError: torchvision") and "--no-deps" in r.stdout, r.stdout
        else:
            assert r.stdout.strip() == "Sintel", r.stdout


def test_missing_torchvision_datasets_is_a_named_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "torchvision", None)  # import fails as if not installed
    monkeypatch.delitem(sys.modules, nets.META, raising=False)  # as in a process where raft_small never ran
    with pytest.raises(fs.errors.DependencyError, match="not installed.*pip install --no-deps"):
        nets.torchvision_datasets()


def test_train_raft_example_exits_2_saying_what_to_install(tmp_path):
    """examples/train_raft.py --sintel ROOT with a torchvision built for another torch: exit 2, the pip command on
    stderr, no traceback."""
    (tmp_path / "sintel").mkdir()
    r = subprocess.run([sys.executable, str(ROOT / "examples" / "train_raft.py"), "--sintel", str(tmp_path / "sintel"),
                        "--steps", "1"], capture_output=True, text=True, timeout=300, cwd=tmp_path,
                       env=_fake_torchvision(tmp_path, FAKE_MISMATCHED))
    assert r.returncode == 2, r.stderr[-2000:]
    assert "--sintel: torchvision 0.99.0+cu999 was built for another torch" in r.stderr
    assert "pip install --no-deps" in r.stderr and "Traceback" not in r.stderr


def test_train_extra_declares_torchvision_and_setup_keeps_it_off_torch():
    """pyproject's train extra holds torchvision; scripts/setup.sh installs torchvision with --no-deps (so pip never
    swaps the pinned CPU torch for the CUDA build torchvision's wheel names) and not through the extra."""
    import tomllib

    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    assert [d for d in extras["train"] if d.startswith("torchvision")], extras["train"]
    setup = [line for line in (ROOT / "scripts" / "setup.sh").read_text().splitlines()
             if not line.lstrip().startswith("#")]
    assert [line for line in setup if "torchvision" in line and "--no-deps" in line]
    assert not [line for line in setup if "train" in line]
    readme = (ROOT / "README.md").read_text()
    assert "pip install 'flowsynth[train]'" in readme
