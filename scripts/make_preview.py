"""Regenerate the README's picture, docs/preview.png, from the CURRENT default BouncingThingsConfig.

    PYTHONPATH=. .venv/bin/python scripts/make_preview.py            # writes docs/preview.png (~1 min)
    PYTHONPATH=. .venv/bin/python scripts/make_preview.py --out x.png --width 64   # any `flowsynth preview` flag

It runs ``flowsynth preview`` (sample 0, seed 0) with no config flags, so the picture shows what the
defaults render (render mode, size, textures). The PNG carries the config it was made from in a tEXt
chunk ``flowsynth:config``; tests/test_cli.py fails when that differs from the current defaults.
"""

import sys
from pathlib import Path

from flowsynth.cli import main

if __name__ == "__main__":
    args = sys.argv[1:]
    if "--out" not in args:
        args = ["--out", str(Path(__file__).resolve().parents[1] / "docs" / "preview.png"), *args]
    sys.exit(main(["preview", *args]))
