"""``EnsembleTrainer``: a tune's nets trained at once (``flowsynth.train.ensemble.Ensemble``), each on the pool of its
own generator setting, and tested on the validation pairs at every checkpoint.

Each net is RAFT's recipe as the learning judge runs it (``Recipe``: its defaults are protocol 0023's): a pool of
``pool`` pairs rendered at ``res`` from the net's generator setting (a ``Mixture``'s sources) and seed, batches of
``batch`` random ``crop`` crops with flips and colour jitter (``flowsynth.train.steps.augment``) drawn from the net's
own generator, ``updates`` flow updates a step, AdamW on one one-cycle schedule of the plan's full length; tested on
every validation pair at full size with ``test_updates`` updates (``flowsynth.train.steps.predict``), the EPE over its
valid pixels.

The state splits into one part per net (weights, AdamW moments, batch generator) and a shared part (the schedule, the
optimiser's step count, the loss scaler), so a rung's survivors continue in a smaller ensemble, and a state saved at a
checkpoint continues exactly as the run that saved it would have: the same batches, the same arithmetic.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import NamedTuple

import torch

from flowsynth.errors import ConfigError
from flowsynth.options import check_int

__all__ = ["QUICK", "RECIPE", "EnsembleTrainer", "Pair", "Recipe"]


class Pair(NamedTuple):
    """A validation pair: images (1, 3, H, W) uint8 (8-bit sRGB, as the files hold them), flow (1, 2, H, W) float32
    [px] (0 where not valid), valid (1, 1, H, W) bool. ``images()``: the images as float32 in [0, 1]."""

    img1: torch.Tensor
    img2: torch.Tensor
    flow: torch.Tensor
    valid: torch.Tensor

    def images(self) -> tuple[torch.Tensor, torch.Tensor]:
        """(img1, img2) float32 in [0, 1] (uint8 / 255, on the pair's device)."""
        return self.img1.float() / 255, self.img2.float() / 255


@dataclass(frozen=True)
class Recipe:
    """How each net of a tune is trained and tested (the defaults: the learning judge's protocol 0023)."""

    res: tuple[int, int] = (256, 192)
    """(width, height) the training pairs are rendered at [px]."""
    crop: tuple[int, int] = (128, 160)
    """(height, width) of the training crops [px], multiples of 8 within ``res`` (RAFT-small: 128 or more)."""
    batch: int = 6
    """Crops per step of one net [count]."""
    updates: int = 8
    """Flow updates per training step [count]."""
    test_updates: int = 12
    """Flow updates at test [count]."""
    lr: float = 4e-4
    """Peak learning rate of the one-cycle schedule."""
    pool: int = 1200
    """Training pairs rendered per net [count]."""

    def __post_init__(self) -> None:
        for name in ("batch", "updates", "test_updates", "pool"):
            object.__setattr__(self, name, check_int(f"recipe's {name}", getattr(self, name), 1))
        if not self.lr > 0:
            raise ConfigError(f"recipe: lr must be > 0, got {self.lr!r}")
        (w, h), (ch, cw) = self.res, self.crop
        if ch % 8 or cw % 8 or not (0 < ch <= h and 0 < cw <= w):
            raise ConfigError(f"recipe: crop (h, w) = {self.crop} must be multiples of 8 within res (w, h) = "
                              f"{self.res}")

    def to_dict(self) -> dict:
        """The recipe as plain JSON values."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self).items()}


RECIPE = Recipe()
QUICK = Recipe(res=(160, 128), crop=(128, 128), batch=1, updates=2, test_updates=2, pool=2)
"""``flowsynth tune --quick``: the smallest recipe RAFT-small trains on, to check that a tune runs."""


class EnsembleTrainer:
    """The nets of a tune (the module docstring says how each is trained and tested).

    ``settings``: {key: (sources, seed)}, every net a search may ask for: its pool is pairs 0 .. ``recipe.pool``-1 of
    ``Mixture(*sources, seed=seed)`` (``flowsynth.tune.pools``), its weights are the net's initialisation under
    ``torch.manual_seed(seed)`` and its batches come from a generator seeded ``seed``. ``pairs``: {name: ``Pair``},
    kept where they are (on the CPU) and moved to ``device`` one at a time to be tested. ``steps``: the schedule's
    length (the plan's last step). ``net``: builds one net (``flowsynth.train.nets.raft_small``: RAFT-small with random
    weights). ``render``: renders a pool, ``render(sources, seed, n, out=None)`` (``flowsynth.tune.PoolRenderer``'s
    call; default a ``PoolRenderer(workers)``, whose processes render every pool of a rung and stop before it trains).
    ``cache``: a ``flowsynth.tune.PoolCache`` that keeps the pools on disk, memory-mapped (None: in memory); ``log``:
    told of each pool rendered or read. Implements ``flowsynth.tune.halving.Trainer``."""

    def __init__(self, settings: dict[str, tuple], pairs: dict[str, Pair], recipe: Recipe, steps: int, *,
                 device: str = "cpu", precision: str = "fp32", workers: int = 0, net: Callable | None = None,
                 render: Callable | None = None, cache=None, log: Callable[[str], None] = lambda line: None):
        from flowsynth.train.nets import raft_small
        from flowsynth.tune.pools import PoolRenderer

        if not pairs:
            raise ConfigError("a trainer needs at least one validation pair")
        self.settings, self.recipe, self.steps = dict(settings), recipe, steps
        self.device, self.precision, self.workers = torch.device(device), precision, workers
        self.net, self.render = net or raft_small, render or PoolRenderer(workers)
        self.cache, self.log = cache, log
        self.pairs = dict(pairs)
        self.step, self.keys, self.ens = 0, [], None
        self.nets: dict[str, dict] = {}  # key -> the net's own state, while it is not in self.ens
        self.shared: dict | None = None  # the optimiser's and schedule's shared state, while self.ens is None
        self.pools: dict[str, tuple] = {}
        self.gens: dict[str, torch.Generator] = {}

    # -- the Trainer protocol -------------------------------------------------------------------------------------
    def advance(self, keys: list[str], step: int) -> dict[str, dict[str, float]]:
        """Train the nets ``keys`` to ``step`` and return {key: {pair: EPE [px]}} (``halving.Trainer``)."""
        unknown = [k for k in keys if k not in self.settings]
        if unknown:
            raise ConfigError(f"no setting for nets {unknown}")
        if step < self.step:
            raise ConfigError(f"the nets are at step {self.step}; cannot go back to {step}")
        if keys != self.keys or self.ens is None:
            self._assemble(list(keys))
        with ThreadPoolExecutor(1) as ahead:  # the next step's batches are drawn while the nets step
            batches = ahead.submit(self._draws) if self.step < step else None
            for s in range(self.step + 1, step + 1):
                batch = batches.result()
                batches = ahead.submit(self._draws) if s < step else None  # never past ``step``: the state is exact
                self.ens.step(tuple(x.to(self.device) for x in batch))
        self.step = step
        return self._evaluate()

    def state_dict(self) -> dict:
        """{"step", "keys", "nets": {key: its own state}, "shared"}: tensors on the CPU."""
        nets, shared = self._split() if self.ens is not None else ({}, self.shared)
        return {"step": self.step, "keys": list(self.keys), "nets": {**self.nets, **nets}, "shared": shared}

    def load_state_dict(self, state: dict) -> None:
        """Continue from ``state_dict()``'s state (the pools are read from the cache, or rendered again, when first
        needed)."""
        self.step, self.keys, self.ens = state["step"], list(state["keys"]), None
        self.nets, self.shared = dict(state["nets"]), state["shared"]
        self.gens = {}
        for key, own in self.nets.items():
            self.gens[key] = torch.Generator().set_state(own["generator"])

    # -- internals ------------------------------------------------------------------------------------------------
    def _draws(self) -> tuple:
        """One step's batches: each net's draw from its pool and generator, stacked (K, B, ...)."""
        return tuple(torch.stack(x) for x in zip(*(self._draw(k) for k in self.keys)))

    def _draw(self, key: str) -> tuple:
        from flowsynth.train.steps import augment

        img1, img2, flow, valid = self.pools[key]
        g = self.gens[key]
        idx = torch.randint(len(img1), (self.recipe.batch,), generator=g)
        return augment(img1[idx], img2[idx], flow[idx], valid[idx], self.recipe.crop, g)

    def _new_net(self, key: str) -> torch.nn.Module:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(self.settings[key][1])
            return self.net()

    def _split(self) -> tuple[dict, dict]:
        """The ensemble's state as {key: its own state} and the shared state (copies on the CPU)."""
        ens = self.ens
        opt = ens.opt.state_dict()
        shapes = [p.shape for p in ens.params.values()]
        nets = {}
        for i, key in enumerate(self.keys):
            moments = {j: {m: v[i].to("cpu", copy=True) for m, v in s.items() if v.shape == shapes[j]}
                       for j, s in opt["state"].items()}
            nets[key] = {"params": {n: p[i].to("cpu", copy=True) for n, p in ens.params.items()},
                         "buffers": {n: b[i].to("cpu", copy=True) for n, b in ens.buffers.items()},
                         "moments": moments, "generator": self.gens[key].get_state()}
        common = {j: {m: v.to("cpu", copy=True) for m, v in s.items() if v.shape != shapes[j]}
                  for j, s in opt["state"].items()}
        shared = {"param_groups": opt["param_groups"], "state": common, "sched": ens.sched.state_dict(),
                  "scaler": None if ens.scaler is None else ens.scaler.state_dict()}
        return nets, shared

    def _assemble(self, keys: list[str]) -> None:
        """An ensemble of the nets ``keys``: those of the current one continue, new ones start (at step 0 only)."""
        from flowsynth.train.ensemble import Ensemble

        if self.ens is not None:
            self.nets, self.shared = self._split()
        new = [k for k in keys if k not in self.nets]
        if new and self.step > 0:
            raise ConfigError(f"nets {new} cannot join at step {self.step}: new nets start at step 0")
        modules = []
        for key in keys:
            module = self._new_net(key)
            if key in self.nets:
                module.load_state_dict({**self.nets[key]["params"], **self.nets[key]["buffers"]})
            else:
                self.gens[key] = torch.Generator().manual_seed(self.settings[key][1])
            modules.append(module.to(self.device))
        ens = Ensemble(modules, self.recipe.lr, self.steps, updates=self.recipe.updates, precision=self.precision)
        if self.shared is not None and self.shared["state"]:
            state = {j: {**common, **{m: torch.stack([self.nets[k]["moments"][j][m] for k in keys])
                                      for m in self.nets[keys[0]]["moments"][j]}}
                     for j, common in self.shared["state"].items()}
            ens.opt.load_state_dict({"state": state, "param_groups": self.shared["param_groups"]})
        if self.shared is not None:
            ens.sched.load_state_dict(self.shared["sched"])
            if ens.scaler is not None and self.shared["scaler"] is not None:
                ens.scaler.load_state_dict(self.shared["scaler"])
        self.ens, self.keys = ens, keys
        self.nets = {}  # the ensemble holds them now; nets that left it never return
        for key in [k for k in self.pools if k not in keys]:
            del self.pools[key]
            if self.cache is not None:
                self.cache.remove(*self.settings[key], self.recipe.pool)
        for key in keys:
            if key not in self.pools:
                sources, seed = self.settings[key]
                if self.cache is None:
                    self.log(f"tune: rendering a pool of {self.recipe.pool} pairs for seed {seed} in memory")
                    self.pools[key] = self.render(sources, seed, self.recipe.pool)
                else:
                    self.pools[key] = self.cache.get(sources, seed, self.recipe.pool, self.render, self.log)
        if hasattr(self.render, "close"):
            self.render.close()  # its processes would hold their memory while the nets train

    @torch.no_grad()
    def _evaluate(self) -> dict[str, dict[str, float]]:
        from flowsynth.train.steps import epe, predict

        nets = self.ens.copy_to_nets()
        out: dict[str, dict[str, float]] = {key: {} for key in self.keys}
        for name, pair in self.pairs.items():  # one pair on the device at a time
            p = Pair(*(x.to(self.device) for x in pair))
            img1, img2 = p.images()
            for key, net in zip(self.keys, nets):
                out[key][name] = epe(predict(net, img1, img2, self.recipe.test_updates), p.flow, p.valid)
        return out
