"""``flowsynth tune``: the generator's own knobs fitted to a user's validation pairs by successive halving of RAFT
nets trained on each setting's data (``tune``; docs/tune.md): search space, pairs, plan, pools, resources, report."""

from flowsynth.tune.halving import TWIN, TWIN_SEED, Rung, min_budget, plan_cost, plan_rungs, search
from flowsynth.tune.pairs import LAYOUTS, find_pairs, read_pairs
from flowsynth.tune.pools import POOL_BYTES, PoolCache, PoolRenderer, pool_bytes, render_pool
from flowsynth.tune.report import markdown, plot, summarize
from flowsynth.tune.run import DEFAULT_BUDGET, DEFAULT_CANDIDATES, tune, work_dir
from flowsynth.tune.space import LAYERS, LAYERS_MOTION_SCALE, SPACE, Knob, default_point, draw_candidates, grid, \
    key_of, point_of, preset, sources
from flowsynth.tune.resources import estimate
from flowsynth.tune.trainer import QUICK, RECIPE, EnsembleTrainer, Pair, Recipe

__all__ = ["DEFAULT_BUDGET", "DEFAULT_CANDIDATES", "LAYERS", "LAYERS_MOTION_SCALE", "LAYOUTS", "POOL_BYTES", "QUICK",
           "RECIPE", "SPACE", "TWIN", "TWIN_SEED", "EnsembleTrainer", "Knob", "Pair", "PoolCache", "PoolRenderer",
           "Recipe", "Rung", "default_point", "draw_candidates", "estimate", "find_pairs", "grid", "key_of",
           "markdown", "min_budget", "plan_cost", "plan_rungs", "plot", "point_of", "pool_bytes", "preset",
           "read_pairs", "render_pool", "search", "sources", "summarize", "tune", "work_dir"]
