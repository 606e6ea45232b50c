"""One rank of ``tests/test_webdataset.py``'s process-group test, started as ``mp.spawn`` users start ranks: no
``RANK`` / ``WORLD_SIZE`` in the environment, the rank given to ``init_process_group`` alone.

    python tests/shards_rank_program.py ROOT RANK PORT OUT

It joins a 2-rank gloo group over tcp://127.0.0.1:PORT, reads the webdataset shards under ROOT through
``fs.datasets.loader`` (2 forkserver workers, which have no process group) and writes the indices it got to OUT.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import torch
import torch.distributed as dist


class Indices(torch.utils.data.IterableDataset):
    """The shards' samples' indices (an iterable dataset over ``Shards``)."""

    def __init__(self, shards) -> None:
        self.shards = shards

    def __iter__(self):
        for s in self.shards:
            yield int(s["index"])


if __name__ == "__main__":
    import flowsynth as fs
    from flowsynth.datasets import Shards

    root, rank, port, out = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), Path(sys.argv[4])
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=2)
    got = list(fs.datasets.loader(Indices(Shards(root, seed=1)), batch_size=None, num_workers=2, timeout=600))
    out.write_text(json.dumps([int(i) for i in got]))
    dist.destroy_process_group()
