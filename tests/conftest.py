"""Shared test set-up: the hypothesis profile, and the small scenes most tests render.

Fixtures (use them instead of copying the values into a new test file):

- ``small_flags``: CLI flags of a 32x24, 2-frame, kinematic scene of 2-3 objects
  (``main(["export", ..., *small_flags])``).
- ``small_config``: the same scene as a ``BouncingThingsConfig``; ``dataclasses.replace(small_config, num_frames=6)``
  for a variant.
- ``layout_config``: 48x32, 3 frames, 3-4 objects moving 2-3 m/s: enough motion for the export layouts' tests.
- ``ray_cluster``: a local 2-CPU Ray cluster for one test module (the ``ray`` module; skipped without Ray).
- ``photos``: a folder of 2 small patterned images, a Layers source's ``texture_dir`` (no default bank to render); a
  module may define its own ``photos`` instead.

Geometry helpers (poses, rotations, a quad mesh, brute-force flow) are plain functions in ``tests/oracle.py``.

Hypothesis runs derandomized by default (profile ``ci``: every run tries the same examples, so a failure
reproduces, and hypothesis then keeps no example database). ``HYPOTHESIS_PROFILE=dev`` turns the randomness back on
for a local search for new counterexamples, with the database that replays them. Whatever hypothesis stores lives
under the repository's ignored ``.cache/hypothesis``, as scripts/test.sh says of every cache (never ``.hypothesis/``
in the working directory).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

import pytest
from hypothesis import settings
from hypothesis.configuration import set_hypothesis_home_dir
from hypothesis.database import DirectoryBasedExampleDatabase

if TYPE_CHECKING:  # flowsynth is imported by the fixtures: a broken library must not stop test collection
    import flowsynth as fs

ROOT = Path(__file__).resolve().parents[1]
# Everything hypothesis stores (its example database, and the constants it collects from the code under test) goes to
# .cache/hypothesis instead of a .hypothesis/ folder in the working directory.
set_hypothesis_home_dir(ROOT / ".cache" / "hypothesis")
_DATABASE = DirectoryBasedExampleDatabase(str(ROOT / ".cache" / "hypothesis" / "examples"))

# deadline None: a derandomized example must not fail because a shared 2-core machine ran it slowly
settings.register_profile("ci", derandomize=True, database=None, deadline=None)
settings.register_profile("dev", derandomize=False, database=_DATABASE, deadline=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

@pytest.fixture
def photos(tmp_path) -> str:
    """A folder of 2 small patterned images: a Layers source's texture_dir (no default bank to render)."""
    import numpy as np
    from PIL import Image

    d = tmp_path / "photos"
    d.mkdir()
    ys, xs = np.mgrid[0:40, 0:60]
    Image.fromarray(np.stack([xs * 4, ys * 6, (xs + ys) % 256], -1).astype(np.uint8)).save(d / "a.png")
    Image.fromarray(((xs * ys) % 256).astype(np.uint8)).save(d / "b.png")
    return str(d)


SMALL_FLAGS = ("--width", "32", "--height", "24", "--num-frames", "2", "--motion", "kinematic",
               "--num-objects", "2,3", "--max-objects", "4")


@pytest.fixture
def small_flags() -> list[str]:
    """CLI flags of the small scene (a fresh list: a test may extend it)."""
    return list(SMALL_FLAGS)


@pytest.fixture
def small_config() -> fs.BouncingThingsConfig:
    """The small scene of ``small_flags`` as a config: 32x24, 2 frames, kinematic, 2-3 objects (at most 4)."""
    import flowsynth as fs

    return fs.BouncingThingsConfig(width=32, height=24, num_frames=2, motion="kinematic", num_objects=(2, 3),
                                   max_objects=4)


@pytest.fixture
def layout_config() -> fs.BouncingThingsConfig:
    """48x32, 3 frames, kinematic, 3-4 objects at 2-3 m/s: the export layouts' round-trip scene."""
    import flowsynth as fs

    return fs.BouncingThingsConfig(width=48, height=32, num_frames=3, motion="kinematic", num_objects=(3, 4),
                                   max_objects=4, min_speed=2.0, max_speed=3.0)


@pytest.fixture(scope="module")
def ray_cluster():
    """A local Ray cluster of 2 CPUs for the test module, whose workers import this checkout's flowsynth (the raylet
    and every worker it starts inherit PYTHONPATH); skipped without the ray extra. Yields the ``ray`` module."""
    ray = pytest.importorskip("ray", reason="Ray tests need the ray extra (bash scripts/setup.sh --ray)")
    old = os.environ.get("PYTHONPATH")
    os.environ["PYTHONPATH"] = str(ROOT)
    try:
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
        yield ray
    finally:
        ray.shutdown()
        if old is None:
            os.environ.pop("PYTHONPATH", None)
        else:
            os.environ["PYTHONPATH"] = old


@pytest.fixture
def one_torch_thread():
    """torch on one thread for the test: on a busy machine, OpenMP threads that wait for each other spin, and small
    convolutions ran 10 to 30 times slower on two threads than on one. The caller's thread count comes back after."""
    import torch

    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)
