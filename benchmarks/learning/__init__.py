"""The learning benchmark: RAFT-small trained from scratch on each arm's pairs, judged on real flow (decision 0023).
Imports run one way: ``sets`` (pairs flowsynth does not render) -> ``raft`` (the judge) -> ``summary``, ``diagnose``,
``checkpoints`` -> ``cli`` (the command line; ``python benchmarks/learning``). ``magnitudes.py`` is a script beside
them."""
