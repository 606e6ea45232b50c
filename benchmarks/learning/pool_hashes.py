"""Hashes of the training pools the learning judge and ``flowsynth tune`` render: the before/after check of a change
to how their configs are made (the pairs a registered protocol trains on must keep their bytes).

    python benchmarks/learning/pool_hashes.py --out /tmp/before.json     # at the old commit
    python benchmarks/learning/pool_hashes.py --check /tmp/before.json   # at the new one: exit 1 on any difference

Hashes every arm of ``protocol.ARMS`` (``pools.build_arms``, ``--num`` pairs an arm, seed ``--seed``, at the judge's
``protocol.RES``) and the tune's pools (``flowsynth.tune.pools.render_pool`` of ``space.sources(key, res)``) for
``TUNE_KEYS`` at the tune's two sizes (``RECIPE.res`` and ``QUICK.res``): each tensor of a pool is hashed (sha256 of
its dtype, shape and bytes), a pool's hash is that of its four tensors in order. Neither size is 512 px wide, so the
scaling of ``flow_px`` from the width it is given at is exercised. Trains nothing; a few minutes on one core.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: the learning package

# the tune's points hashed: the default, and the largest motion mixed with 2D layers
TUNE_KEYS = ("default", "motion=large,layers=0.5")


def digest(tensors) -> str:
    """sha256 (first 16 hex digits) of a sequence of tensors: each one's dtype, shape and bytes, in order."""
    h = hashlib.sha256()
    for t in tensors:
        a = t.detach().cpu().contiguous().numpy()
        h.update(f"{a.dtype}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def tune_key(label: str) -> str:
    """A ``TUNE_KEYS`` entry as a point's key: "default" is the default point, else knob=label pairs over it."""
    from flowsynth.tune import default_point, key_of

    point = default_point()
    if label != "default":
        point.update(dict(kv.split("=") for kv in label.split(",")))
    return key_of(point)


def hashes(num: int, seed: int) -> dict:
    """{"learning/ARM": hash, "tune/WxH/KEY": hash} of the pools (module docstring)."""
    from flowsynth.tune import QUICK, RECIPE, render_pool, sources
    from learning.pools import build_arms
    from learning.protocol import ARMS

    arms = build_arms(list(ARMS), seed, 0, {}, num)[0]
    got = {f"learning/{name}": digest(pool) for name, pool in arms.items()}
    for res in (RECIPE.res, QUICK.res):
        for label in TUNE_KEYS:
            got[f"tune/{res[0]}x{res[1]}/{label}"] = digest(render_pool(sources(tune_key(label), res), seed, num))
    return got


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--num", type=int, default=2, help="pairs a pool (default 2)")
    p.add_argument("--seed", type=int, default=0, help="the pools' seed (default 0)")
    p.add_argument("--out", help="write the hashes to this JSON file")
    p.add_argument("--check", help="compare with this JSON file (exit 1 on any difference)")
    args = p.parse_args()
    got = hashes(args.num, args.seed)
    for name, h in got.items():
        print(f"{name:40s} {h}")
    if args.out:
        Path(args.out).write_text(json.dumps(got, indent=1))
    if args.check:
        want = json.loads(Path(args.check).read_text())
        bad = sorted(k for k in set(want) | set(got) if want.get(k) != got.get(k))
        if bad:
            print(f"DIFFERENT ({len(bad)}): " + ", ".join(bad))
            sys.exit(1)
        print(f"identical to {args.check} ({len(got)} pools)")


if __name__ == "__main__":
    main()
