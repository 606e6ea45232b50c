"""flowsynth.scene.physics uses private corners of Newton; these tests fail loudly, naming the cause, when they move.

``physics.memoise_newton_kernel_factories`` (a context manager, open while flowsynth builds a Newton scene) wraps
Newton's narrow-phase kernel factories (``newton._src.geometry.narrow_phase``) in ``functools.cache`` so every
CollisionPipeline flowsynth builds shares one set of kernels, and ``newton._src.sim.builder._convex_hull_adjacency``
so each hull's edge adjacency is computed once per process (benchmarks/accuracy/physics.py, "memoisation"); outside it
Newton's own functions are back (tests/test_newton_scope.py). That only works while
(a) those functions exist under those names and (b) Newton looks them up in those modules when called.
Either can change in any Newton release (pinned < 1.9).
"""

import flowsynth as fs
from flowsynth.scene import physics
from flowsynth.scene.sampling import sample_layout

CAUSE = ("Newton's private narrow-phase module changed: flowsynth.scene.physics.memoise_newton_kernel_factories "
         "(which memoises {names} in newton._src.geometry.narrow_phase) no longer applies, so every scene "
         "would recompile Newton's collision kernels. Update the patch for this Newton version, or drop it "
         "and re-measure benchmarks/accuracy/physics.py.")


def test_narrow_phase_factories_exist():
    from newton._src.geometry import narrow_phase
    from newton._src.sim import builder

    missing = [n for n in physics._NEWTON_KERNEL_FACTORIES if not callable(getattr(narrow_phase, n, None))]
    missing += [n for n in physics._NEWTON_BUILDER_FUNCTIONS if not callable(getattr(builder, n, None))]
    assert not missing, CAUSE.format(names=missing)


def test_hull_adjacency_computed_once_per_hull():
    """Building two models over the same hulls computes each hull's adjacency once (cache hits after)."""
    from newton._src.sim import builder

    cfg = fs.BouncingThingsConfig(num_objects=(3, 3), num_frames=2, assets=("rock",))
    layout = sample_layout(cfg, 0, 0)
    physics.NewtonScene(cfg, layout.assets, layout.initial, 2)
    with physics.memoise_newton_kernel_factories():  # the memoised function is installed only inside
        fn = builder._convex_hull_adjacency
    assert hasattr(fn, "cache_info"), CAUSE.format(names=list(physics._NEWTON_BUILDER_FUNCTIONS))
    hits = fn.cache_info().hits
    physics.NewtonScene(cfg, layout.assets, layout.initial, 2)
    assert fn.cache_info().hits > hits, CAUSE.format(names=list(physics._NEWTON_BUILDER_FUNCTIONS)) + \
        " (ModelBuilder.finalize no longer calls builder._convex_hull_adjacency)"


def test_pipelines_share_memoised_kernels():
    """Two Newton scenes built one after the other get the very same narrow-phase kernel objects."""
    cfg = fs.BouncingThingsConfig(num_objects=(3, 3), num_frames=2, assets=("box", "rock"))
    scenes = []
    for seed in (0, 1):
        layout = sample_layout(cfg, seed, 0)
        scenes.append(physics.NewtonScene(cfg, layout.assets, layout.initial, 2))
    a, b = (s.pipeline.narrow_phase for s in scenes)
    for attr in ("primitive_kernel", "narrow_phase_kernel"):
        ka, kb = getattr(a, attr, None), getattr(b, attr, None)
        assert ka is not None and ka is kb, CAUSE.format(names=list(physics._NEWTON_KERNEL_FACTORIES)) + \
            f" (NarrowPhase.{attr} differs between two pipelines)"


def test_contact_estimate_is_the_pipelines_default():
    """``physics._newton_contact_estimate`` (Newton's private estimate) is the capacity a CollisionPipeline picks when
    given none: flowsynth falls back to it, and compares its own capacity against it."""
    import newton

    cfg = fs.BouncingThingsConfig(num_objects=(5, 5), num_frames=2, assets=("box", "rock"))
    layout = sample_layout(cfg, 0, 0)
    scene = physics.NewtonScene(cfg, layout.assets, layout.initial, 2, None)
    default = newton.CollisionPipeline(scene.model, broad_phase="sap").rigid_contact_max
    assert physics._newton_contact_estimate(scene.model) == default == scene.pipeline.rigid_contact_max, (
        "Newton's private newton._src.sim.collide._estimate_rigid_contact_max moved or no longer gives "
        "CollisionPipeline's default capacity: update flowsynth.scene.physics._newton_contact_estimate")


def test_finalize_kernels_free_flight_resets_with_exist():
    """A bodies-only scene reset for another clip (flowsynth.scene.physics, free flight) writes the new masses and
    derives their inverses with the two kernels ModelBuilder.finalize uses; when they move, resets cannot match a fresh
    build (tests/test_free_flight.py would fail on bits, this names the cause)."""
    from newton._src.sim import builder

    missing = [n for n in ("validate_and_correct_inertia_kernel", "compute_body_inverses_kernel")
               if getattr(builder, n, None) is None]
    assert not missing, (f"newton._src.sim.builder no longer has {missing}: update NewtonScene._set_masses in "
                         "flowsynth/scene/physics.py for this Newton version, or set physics.FREE_FLIGHT = False")
