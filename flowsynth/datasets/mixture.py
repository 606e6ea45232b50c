"""``Mixture``: one ``BouncingThings`` stream drawn from several configs (presets), reproducibly, with an optional
curriculum.

Sample i comes from config k = ``source(i)``, drawn from the weights in force at index i with a generator seeded
by (seed, i) alone, and is exactly sample i of ``BouncingThings(configs[k], outputs, seed)``: a pure function of
(configs, weights, seed, i), whatever the workers, ranks or order of reading. Iteration, sharding, epochs and
``state_dict`` are ``BouncingThings``' own (this class is one).

A curriculum is a list of stages ``[(until, weights), ...]``: index i uses the weights of the first stage with
i < until (the last stage's ``until`` may be None: open-ended). "chairs, then things" is
``[(20000, {"chairs": 1}), (None, {"chairs": 1, "things": 3})]``.

All configs must give samples of one shape (width, height, num_frames and max_objects equal), so that
``default_collate`` batches a mixture; each item carries ``source`` (int64, k).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch

from flowsynth.datasets.bouncing import BouncingThings
from flowsynth.errors import ConfigError

__all__ = ["Mixture"]

MIX_SALT = 0x6D1C  # keeps the source draw apart from every other generator seeded by (seed, i)
SHAPE_FIELDS = ("width", "height", "num_frames", "max_objects")


class Mixture(BouncingThings):
    """A stream of samples from several configs.

    Args:
        configs: name -> ``BouncingThingsConfig`` (or a preset name, ``BouncingThingsConfig.preset``), or a sequence
            of either (named by their position).
        weights: name -> weight >= 0 (a missing name weighs 0; None: equal weights), or a curriculum: a list of
            ``(until, weights)`` stages (module docstring).
        outputs, seed, length, start, occlusion, device, threads: as ``BouncingThings``.

    Raises ConfigError for configs of different sample shapes, unknown names, negative or all-zero weights, or
    stages whose ``until`` do not increase.
    """

    def __init__(self, configs, weights=None, outputs: Sequence[str] = ("rgb", "flow_fw"), seed: int = 0,
                 length: int | None = None, *, start: int = 0, occlusion: str = "exact", device: str = "cpu",
                 threads: int | None = None) -> None:
        from flowsynth.scene import BouncingThingsConfig

        if isinstance(configs, Mapping):
            items = list(configs.items())
        elif isinstance(configs, Sequence) and not isinstance(configs, str):
            items = [(str(k), c) for k, c in enumerate(configs)]
        else:
            raise ConfigError(f"configs must be a dict or a list of configs or preset names, got {configs!r}")
        if not items:
            raise ConfigError("a Mixture needs at least one config")
        items = [(str(k), BouncingThingsConfig.preset(c) if isinstance(c, str) else c) for k, c in items]
        self.names = [k for k, _ in items]
        first = items[0][1]
        for name, c in items:
            if not isinstance(c, BouncingThingsConfig):
                raise ConfigError(f"config {name!r} must be a BouncingThingsConfig or a preset name, "
                                  f"got {type(c).__name__}")
            diff = [f for f in SHAPE_FIELDS if getattr(c, f) != getattr(first, f)]
            if diff:
                raise ConfigError(f"config {name!r} differs from {items[0][0]!r} in {diff}: a Mixture's samples "
                                  f"must share one shape (set {', '.join(diff)} alike)")
        self.stages = _stages(weights, self.names)
        kw = dict(seed=seed, length=length, start=start, occlusion=occlusion, device=device, threads=threads)
        super().__init__(first, outputs, **kw)
        self.parts = [BouncingThings(c, outputs, **kw) for _, c in items]
        self.configs = dict(items)

    def source(self, i: int) -> int:
        """The config index of sample ``i``."""
        if not isinstance(i, (int, np.integer)) or i < 0:
            raise ConfigError(f"sample index must be an integer >= 0, got {i!r}")
        p = next(w for until, w in self.stages if until is None or i < until)
        rng = np.random.default_rng([self.seed, int(i), MIX_SALT])
        return int(rng.choice(len(p), p=p))

    def scene(self, i: int):
        """The simulated scene behind sample ``i`` (from its source's config)."""
        return self.parts[self.source(i)].scene(i)

    def sample(self, i: int) -> dict[str, torch.Tensor]:
        """Sample ``i``: sample i of its source's ``BouncingThings``, plus ``source`` (int64)."""
        k = self.source(i)
        out = self.parts[k].sample(i)
        out["source"] = torch.tensor(k, dtype=torch.int64)
        return out


def _stages(weights, names: list[str]) -> list[tuple[int | None, np.ndarray]]:
    """[(until, probabilities over names)] from ``Mixture``'s ``weights`` argument, checked."""
    if weights is None or isinstance(weights, Mapping):
        stages = [(None, weights)]
    elif isinstance(weights, Sequence) and not isinstance(weights, str) and weights:
        stages = list(weights)
    else:
        raise ConfigError(f"weights must be None, a dict name -> weight, or a list of (until, weights) stages, "
                          f"got {weights!r}")
    out, last = [], 0
    for n, stage in enumerate(stages):
        if not (isinstance(stage, Sequence) and len(stage) == 2):
            raise ConfigError(f"curriculum stage {n} must be (until, weights), got {stage!r}")
        until, w = stage
        if until is not None and (not isinstance(until, (int, np.integer)) or until <= last):
            raise ConfigError(f"curriculum stage {n}: until must be an integer > {last} (increasing), got {until!r}")
        if until is None and n != len(stages) - 1:
            raise ConfigError(f"curriculum stage {n}: only the last stage may be open-ended (until None)")
        w = dict.fromkeys(names, 1.0) if w is None else w
        if not isinstance(w, Mapping) or set(w) - set(names):
            raise ConfigError(f"weights must name configs among {names}, got {w!r}")
        p = np.array([float(w.get(k, 0.0)) for k in names])
        if not np.all(np.isfinite(p)) or (p < 0).any() or p.sum() <= 0:
            raise ConfigError(f"weights must be finite, >= 0 and not all 0, got {w!r}")
        out.append((None if until is None else int(until), p / p.sum()))
        last = until if until is not None else last
    if out[-1][0] is not None:
        out.append((None, out[-1][1]))  # past the last stage: its weights go on
    return out
