"""``flowsynth tune``: the generator's own knobs fitted to a user's validation pairs, by successive halving of RAFT
nets trained at once on each setting's data (``tune``; docs/tune.md): the search space (``SPACE``), the validation
pairs' reader (``read_pairs``), the plan and search (``plan_rungs``, ``search``), the trainer and the report."""

from flowsynth.tune.halving import TWIN, TWIN_SEED, Rung, min_budget, plan_cost, plan_rungs, search
from flowsynth.tune.pairs import LAYOUTS, read_pairs
from flowsynth.tune.report import markdown, plot, summarize
from flowsynth.tune.run import DEFAULT_BUDGET, DEFAULT_CANDIDATES, tune, work_dir
from flowsynth.tune.space import LAYERS, LAYERS_MOTION_SCALE, SPACE, Knob, default_point, draw_candidates, grid, \
    key_of, point_of, preset, sources
from flowsynth.tune.trainer import QUICK, RECIPE, EnsembleTrainer, Pair, Recipe, render_pool

__all__ = ["DEFAULT_BUDGET", "DEFAULT_CANDIDATES", "LAYERS", "LAYERS_MOTION_SCALE", "LAYOUTS", "QUICK", "RECIPE",
           "SPACE", "TWIN", "TWIN_SEED", "EnsembleTrainer", "Knob", "Pair", "Recipe", "Rung", "default_point",
           "draw_candidates", "grid", "key_of", "markdown", "min_budget", "plan_cost", "plan_rungs", "plot",
           "point_of", "preset", "read_pairs", "render_pool", "search", "sources", "summarize", "tune", "work_dir"]
