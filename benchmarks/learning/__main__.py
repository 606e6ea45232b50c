"""``python benchmarks/learning [...]``: the learning benchmark's command line (``learning.cli``)."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: _common and this package

from learning.cli import main

if __name__ == "__main__":
    main()
