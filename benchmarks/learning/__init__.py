"""The learning benchmark: RAFT-small trained from scratch on each arm's pairs, judged on real flow (decision 0023).
Imports run one way: ``sets`` (pairs flowsynth does not render) -> ``protocol`` (the judge's numbers, judges, score
and file names) -> ``pools`` (the arms' training pools) -> ``trainers`` (train and test nets) -> ``runs`` (the
protocol's runs) -> ``ensemble_rate`` (a speed benchmark) -> ``summary``, ``diagnose``, ``checkpoints`` (readings) ->
``cli`` (the command line; ``python benchmarks/learning``). ``magnitudes.py`` is a script beside them."""
