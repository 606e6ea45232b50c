"""torchvision on demand: RAFT-small, the net that ``flowsynth tune``, the learning benchmark and the tests train, and
torchvision's datasets (``examples/train_raft.py --sintel``). torchvision is optional (the ``train`` extra, never a
dependency of flowsynth): each function imports it when called and raises ``DependencyError`` when it is missing or
built for another torch, with the pip command that installs the build made for this torch.
"""

from __future__ import annotations

import re
import sys
import types

from flowsynth.errors import DependencyError

__all__ = ["install_command", "raft_small", "torchvision_datasets"]

META = "torchvision._meta_registrations"  # the module that registers torchvision's C++ operators with torch
INDEX = "https://download.pytorch.org/whl/"  # PyTorch's wheel index, one folder per build (cpu, cu128, rocm6.4, ...)


def install_command() -> str:
    """The pip command that installs the torchvision build made for the torch installed here and leaves torch as it
    is: the release paired with torch's (torch 2.N.P: torchvision 0.(N+15).P), from PyTorch's index of torch's build
    (cpu, cuXYZ or rocmX.Y); ``--no-deps``, as pip would otherwise replace torch with the build torchvision names."""
    import torch

    m = re.match(r"2\.(\d+)\.(\d+)", torch.__version__)
    version = f'"torchvision==0.{int(m.group(1)) + 15}.{m.group(2)}"' if m else "torchvision"
    hip, cuda = getattr(torch.version, "hip", None), torch.version.cuda
    build = (f"rocm{'.'.join(hip.split('.')[:2])}" if hip else f"cu{cuda.replace('.', '')}" if cuda else "cpu")
    return f"pip install --no-deps --force-reinstall {version} --index-url {INDEX}{build}"


def _torchvision_version() -> str:
    """The installed torchvision's version with its build tag (0.28.0+cu130), read from its files without importing
    it (an import that failed once fails again)."""
    import importlib.metadata
    import importlib.util
    from pathlib import Path

    try:
        spec = importlib.util.find_spec("torchvision")
        text = (Path(spec.submodule_search_locations[0]) / "version.py").read_text()
        return re.search(r"__version__ = '([^']+)'", text).group(1)
    except (ImportError, ValueError, AttributeError, TypeError, IndexError, OSError):
        try:
            return importlib.metadata.version("torchvision")
        except importlib.metadata.PackageNotFoundError:
            return "(version unknown)"


def _mismatch(detail: str) -> str:
    import torch

    installed = _torchvision_version()
    return (f"torchvision {installed} was built for another torch than this one ({torch.__version__}): its C++ "
            f"operators do not load ({detail}). Install the torchvision build made for this torch: "
            f"{install_command()}")


def torchvision_datasets():
    """The ``torchvision.datasets`` module (Sintel, KittiFlow, FlyingChairs, ...), imported as it is.

    Raises:
        DependencyError: torchvision is not installed, or it was built for another torch, so that its C++ operators
            do not load (its import fails with "operator torchvision::nms does not exist", or :func:`raft_small`
            stood in for them in this process) and KittiFlow could not decode its PNGs. The message gives the pip
            command that installs the right build.
    """
    registrations = sys.modules.get(META)
    if registrations is not None and not hasattr(registrations, "register_meta"):  # raft_small's stand-in
        raise DependencyError(_mismatch("operator torchvision::nms does not exist"))
    try:
        from torchvision import datasets
    except ImportError as e:
        raise DependencyError(f"torchvision's datasets need torchvision, which is not installed ({e}): "
                              f"{install_command()}") from e
    except RuntimeError as e:
        if "torchvision::" not in str(e):
            raise
        raise DependencyError(_mismatch(str(e))) from e
    return datasets


def raft_small(weights=None):
    """torchvision's ``raft_small(weights=weights)`` (0.99 M parameters; random weights for ``None``), called as
    ``net(img1, img2, num_flow_updates=N)`` on (B, 3, H, W) images in [-1, 1] with H, W multiples of 8 and at least
    128, returning the list of its N (B, 2, H, W) flow estimates [px].

    torchvision is imported as it is. Only where that import fails on torchvision's C++ operators
    ("operator torchvision::nms does not exist": a wheel built against another torch lacks them) are the
    half-imported torchvision modules dropped and ``torchvision._meta_registrations`` stood in for by an empty module
    before a second import: the models need none of the operators. Raises DependencyError when torchvision is not
    installed.
    """
    try:
        try:
            build = _import_raft()
        except (ImportError, RuntimeError) as e:
            if "torchvision::" not in str(e):
                raise
            for name in [n for n, m in sys.modules.items() if m is not None and n.split(".")[0] == "torchvision"]:
                del sys.modules[name]
            sys.modules[META] = types.ModuleType(META)
            build = _import_raft()
    except ImportError as e:
        raise DependencyError(f"RAFT-small needs torchvision, which is not installed ({e}): {install_command()}") from e
    return build(weights=weights)


def _import_raft():
    from torchvision.models.optical_flow import raft_small as build

    return build
