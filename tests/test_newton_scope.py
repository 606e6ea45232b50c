"""flowsynth patches Newton's private kernel factories only while it builds its own scenes (issue 41, item 5).

``physics.memoise_newton_kernel_factories`` is a re-entrant, thread-safe context manager: inside it Newton's
narrow-phase kernel factories and hull adjacency are memoised; after the last one closes, Newton's module attributes
are Newton's own function objects again (identity, the oracle here: the objects read before flowsynth touched
Newton). The memoisation itself still holds across scenes (tests/test_newton_internals.py), and the results are
unchanged (benchmarks/speed/hashes.py; a physics clip here equals one simulated with the patch disabled)."""

from __future__ import annotations

import threading

import numpy as np
import pytest

import flowsynth as fs
from flowsynth.scene import motion, physics
from flowsynth.scene.sampling import sample_layout


def _newton_attributes() -> dict[str, object]:
    from newton._src.geometry import narrow_phase
    from newton._src.sim import builder

    out = {f"narrow_phase.{n}": getattr(narrow_phase, n) for n in physics._NEWTON_KERNEL_FACTORIES}
    out.update({f"builder.{n}": getattr(builder, n) for n in physics._NEWTON_BUILDER_FUNCTIONS})
    return out


@pytest.fixture
def originals():
    """Newton's own functions, as Newton's modules define them (not wrapped by any cache)."""
    import newton  # noqa: F401  (imports the private modules below)

    attrs = _newton_attributes()
    for name, fn in attrs.items():
        assert not hasattr(fn, "cache_info") and not hasattr(fn, "__wrapped__"), f"{name} is already patched: {fn}"
    return attrs


def _cfg(**kw) -> fs.BouncingThingsConfig:
    return fs.BouncingThingsConfig(**{"width": 32, "height": 24, "num_frames": 3, "num_objects": (3, 3),
                                      "assets": ("box", "rock"), **kw})


def test_newton_is_its_own_after_flowsynth_builds_a_scene(originals):
    layout = sample_layout(_cfg(), 0, 0)
    scene = physics.NewtonScene(_cfg(), layout.assets, layout.initial, 2)
    assert _newton_attributes() == originals and all(_newton_attributes()[k] is v for k, v in originals.items())
    # ... and flowsynth's pipeline got the memoised kernels: the memo holds the very kernel object it uses
    kernel = scene.pipeline.narrow_phase.primitive_kernel
    memo = physics._NEWTON_MEMOS[("newton._src.geometry.narrow_phase", "create_narrow_phase_primitive_kernel")]
    assert memo.cache_info().currsize >= 1
    with physics.memoise_newton_kernel_factories():
        again = physics.NewtonScene(_cfg(), layout.assets, layout.initial, 2)
    assert again.pipeline.narrow_phase.primitive_kernel is kernel
    assert all(_newton_attributes()[k] is v for k, v in originals.items())


def test_a_whole_sample_leaves_newton_untouched(originals):
    ds = fs.datasets.BouncingThings(_cfg(motion="physics"), outputs=["depth"], seed=0)
    ds.sample(0)
    assert all(_newton_attributes()[k] is v for k, v in originals.items())


def test_window_is_reentrant_and_restores_on_error(originals):
    with physics.memoise_newton_kernel_factories():
        inside = _newton_attributes()
        assert all(inside[k] is not v and inside[k].__wrapped__ is v for k, v in originals.items())
        with physics.memoise_newton_kernel_factories():
            assert all(_newton_attributes()[k] is inside[k] for k in originals)
        assert all(_newton_attributes()[k] is inside[k] for k in originals)  # the outer window is still open
    assert all(_newton_attributes()[k] is v for k, v in originals.items())
    with pytest.raises(RuntimeError, match="boom"), physics.memoise_newton_kernel_factories():
        raise RuntimeError("boom")
    assert all(_newton_attributes()[k] is v for k, v in originals.items())
    with physics.memoise_newton_kernel_factories():  # the same memos across windows (the kernels they hold)
        assert all(_newton_attributes()[k] is inside[k] for k in originals)


def test_windows_of_many_threads(originals):
    """Eight threads opening and closing windows at once (a barrier starts them together): inside any window every
    attribute is the memo of Newton's function; after all have closed, Newton's functions themselves."""
    n, rounds = 8, 50
    barrier = threading.Barrier(n)
    seen: list[bool] = []
    lock = threading.Lock()

    def work() -> None:
        barrier.wait(timeout=60)
        for _ in range(rounds):
            with physics.memoise_newton_kernel_factories():
                ok = all(getattr(fn, "__wrapped__", None) is originals[name]
                         for name, fn in _newton_attributes().items())
            with lock:
                seen.append(ok)

    threads = [threading.Thread(target=work) for _ in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert len(seen) == n * rounds and all(seen)
    assert all(_newton_attributes()[k] is v for k, v in originals.items())
    assert physics._NewtonPatch.depth == 0


def test_memoisation_changes_no_trajectory(monkeypatch):
    """A physics clip with flowsynth's memoisation equals one built by Newton's own factories (the patch off)."""
    import contextlib

    cfg = _cfg(num_objects=(4, 4), assets=("box", "rock", "sphere"))
    layout = sample_layout(cfg, 3, 1)
    monkeypatch.setattr(physics, "SCENE_REUSE", False)
    memo = motion.simulate(cfg, layout.assets, layout.initial)
    monkeypatch.setattr(physics, "memoise_newton_kernel_factories", contextlib.nullcontext)
    plain = motion.simulate(cfg, layout.assets, layout.initial)
    assert memo.substeps == plain.substeps
    np.testing.assert_array_equal(memo.poses, plain.poses)
