"""One rank of ``tests/test_ranks.py``, started by torchrun (``RANK``, ``WORLD_SIZE``, ``MASTER_ADDR`` ... in its
environment): ``python -m torch.distributed.run --nproc-per-node 2 tests/ranks_program.py KIND OUT``.

It joins a gloo process group and reads a stream of KIND (bouncing, layers, mixture: ``LENGTH`` samples an epoch;
device: ``DeviceBatches``) for two epochs, and writes ``OUT/rank{r}.json`` with the indices it got:

- ``loader``: two epochs through ``fs.datasets.loader`` (2 forkserver workers, persistent);
- ``stateful``: two epochs through torchdata's ``StatefulDataLoader`` (2 spawned workers): two batches, then its
  ``state_dict`` (saved to ``OUT/state{r}.pt``), then a fresh loader over a fresh stream resumed from that state
  reads the rest of epoch 0 and epoch 1; ``saved`` holds the indices read before the state was taken;
- device: ``loader`` is two epochs of ``DeviceBatches`` with 2 scene workers, ``saved`` the indices of its first
  batch, whose ``state_dict`` is saved and resumed in a fresh ``DeviceBatches`` (no workers) for ``stateful``.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import torch
import torch.distributed as dist

LENGTH = 16  # samples an epoch: 4 per shard of 2 ranks x 2 workers
BATCH = 2


def stream(kind: str):
    import flowsynth as fs
    from flowsynth.datasets import BouncingThings, Layers, LayersConfig, Mixture

    things = fs.BouncingThingsConfig(width=32, height=32, num_frames=2, num_objects=(1, 2), max_objects=2,
                                     motion="kinematic")
    layers = LayersConfig(width=32, height=32, texture_bank=2)
    if kind == "bouncing":
        return BouncingThings(things, ["depth"], seed=3, length=LENGTH)
    if kind == "layers":
        return Layers(layers, ["flow_fw"], seed=3, length=LENGTH)
    if kind == "mixture":
        return Mixture({"things": things, "layers": layers}, outputs=["flow_fw"], seed=3, length=LENGTH)
    raise ValueError(kind)


def indices(batches) -> list[int]:
    return [i for b in batches for i in b["index"].tolist()]


def read_stream(kind: str, out: Path, rank: int) -> dict:
    import flowsynth as fs
    from torchdata.stateful_dataloader import StatefulDataLoader

    ld = fs.datasets.loader(stream(kind), batch_size=BATCH, num_workers=2)
    got = {"loader": [indices(ld), indices(ld)]}
    del ld
    first = StatefulDataLoader(stream(kind), batch_size=BATCH, num_workers=2, multiprocessing_context="spawn")
    it = iter(first)
    saved = indices([next(it), next(it)])
    state = first.state_dict()
    del it, first
    torch.save(state, out / f"state{rank}.pt")
    resumed = StatefulDataLoader(stream(kind), batch_size=BATCH, num_workers=2, multiprocessing_context="spawn",
                                 persistent_workers=True)
    resumed.load_state_dict(state)
    got.update(saved=saved, stateful=[saved + indices(resumed), indices(resumed)])
    return got


def read_device(out: Path, rank: int) -> dict:
    import flowsynth as fs
    from flowsynth.datasets import DeviceBatches

    cfg = fs.BouncingThingsConfig(width=32, height=24, num_frames=2, num_objects=(1, 2), max_objects=2,
                                  motion="kinematic")
    batches = DeviceBatches(cfg, ["depth"], BATCH, 2, seed=3, length=LENGTH)
    it = iter(batches)
    head = next(it)
    state = batches.state_dict()
    torch.save(state, out / f"state{rank}.pt")
    got = {"loader": [indices([head, *it]), indices(batches)], "saved": head["index"].tolist()}
    batches.close()
    resumed = DeviceBatches(cfg, ["depth"], BATCH, 0, seed=3, length=LENGTH)
    resumed.load_state_dict(state)
    got["stateful"] = [got["saved"] + indices(resumed), indices(resumed)]
    return got


def main(kind: str, out: str) -> None:
    dist.init_process_group("gloo")
    rank, out = dist.get_rank(), Path(out)
    got = read_device(out, rank) if kind == "device" else read_stream(kind, out, rank)
    got.update(rank=rank, world_size=dist.get_world_size())
    (out / f"rank{rank}.json").write_text(json.dumps(got))
    dist.barrier()
    dist.destroy_process_group()


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
