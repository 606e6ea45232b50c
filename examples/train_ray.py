"""Train the small flow network of train_flow.py with Ray Train, streaming samples from a Ray dataset.

    python examples/train_ray.py --steps 100                      # a local Ray cluster on this machine
    python examples/train_ray.py --steps 100 --address auto       # the cluster this node joined (ray start)

The samples are rendered by ``flowsynth.distributed.ray_dataset`` actors (one CPU each) and reach each
training worker through ``ray.train.get_dataset_shard("train").iter_torch_batches(...)``; nothing is
written to disk. Each worker reports its training loss, and worker 0 the held-out end-point error (EPE)
before and after. Needs the ray extra (``bash scripts/setup.sh --ray``); cluster set-up: docs/distributed.md.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import tempfile
from pathlib import Path

import torch

import flowsynth as fs

_spec = importlib.util.spec_from_file_location("train_flow", Path(__file__).resolve().parent / "train_flow.py")
train_flow = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(train_flow)
TinyFlowNet, epe = train_flow.TinyFlowNet, train_flow.epe

OUTPUTS = ["rgb", "flow_fw", "valid_fw"]


def _pairs(batch: dict) -> tuple[torch.Tensor, ...]:
    """(img1, img2) (B, 3, H, W) in [0, 1], flow (B, 2, H, W) [px], valid (B, 1, H, W) float."""
    return batch["rgb"][:, 0], batch["rgb"][:, 1], batch["flow_fw"][:, 0], batch["valid_fw"][:, 0].float()


def train_loop_per_worker(config: dict) -> None:
    """One Ray Train worker: stream its shard, train, report {"step", "loss_first", "loss_last"}; worker 0
    also the held-out EPEs [px] and a checkpoint holding ``model.pt``."""
    import ray.train
    import ray.train.torch

    torch.manual_seed(config["seed"])
    net = ray.train.torch.prepare_model(TinyFlowNet())
    opt = torch.optim.Adam(net.parameters(), lr=config["lr"])
    rank = ray.train.get_context().get_world_rank()
    held_out = None
    if rank == 0:  # the same held-out samples whatever the number of workers
        ds = fs.datasets.BouncingThings(config["cfg"], outputs=OUTPUTS, seed=config["seed"] + 1, threads=1)
        held_out = [_pairs(torch.utils.data.default_collate([ds.sample(i) for i in range(b * 4, b * 4 + 4)]))
                    for b in range(config["eval_batches"])]

    def evaluate() -> float | None:
        if held_out is None:
            return None
        with torch.no_grad():
            return float(sum(epe(net(a, b), f, v) for a, b, f, v in held_out) / len(held_out))

    before = evaluate()
    shard = ray.train.get_dataset_shard("train")
    step, losses = 0, []
    for batch in shard.iter_torch_batches(batch_size=config["batch_size"], drop_last=True):
        a, b, f, v = _pairs(batch)
        loss = epe(net(a, b), f, v)
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        losses.append(loss.item())
    metrics = {"step": step, "loss_first": losses[0], "loss_last": losses[-1]}
    if rank != 0:
        ray.train.report(metrics)
        return
    metrics.update(epe_before=before, epe_after=evaluate())
    with tempfile.TemporaryDirectory() as tmp:  # the trained weights: Result.checkpoint / model.pt
        torch.save(getattr(net, "module", net).state_dict(), Path(tmp) / "model.pt")
        ray.train.report(metrics, checkpoint=ray.train.Checkpoint.from_directory(tmp))


def _ship_by_value() -> None:
    """Workers cannot import the example scripts: send train_flow (and this file, when imported) by value."""
    from ray import cloudpickle

    sys.modules.setdefault("train_flow", train_flow)
    cloudpickle.register_pickle_by_value(train_flow)
    if __name__ != "__main__" and __name__ in sys.modules:
        cloudpickle.register_pickle_by_value(sys.modules[__name__])


def train(steps: int = 100, *, width: int = 64, height: int = 48, batch_size: int = 4, num_workers: int = 1,
          actors: int | None = None, lr: float = 2e-3, eval_batches: int = 2, seed: int = 0,
          address: str | None = None, storage_path: str | None = None) -> dict:
    """Train TinyFlowNet for ``steps`` steps of ``batch_size`` per worker on ``num_workers`` Ray Train workers,
    fed by ``actors`` renderer actors (None: the CPUs left over). Returns worker 0's final report, with the
    path of the checkpoint holding the trained weights (``model.pt``)."""
    import ray
    from ray.train import RunConfig, ScalingConfig
    from ray.train.torch import TorchTrainer

    from flowsynth.distributed import connect, ray_dataset

    connect(address)
    _ship_by_value()
    cfg = fs.BouncingThingsConfig(width=width, height=height, num_frames=2, motion="kinematic",
                                  render_mode="flat", num_objects=(3, 6), min_speed=1.0, max_speed=3.0)
    if actors is None:  # one CPU per training worker, the rest render
        actors = max(int(ray.cluster_resources().get("CPU", 2)) - num_workers, 1)
    data = ray_dataset(cfg, steps * batch_size * num_workers, seed=seed, outputs=OUTPUTS, actors=actors)
    trainer = TorchTrainer(
        train_loop_per_worker,
        train_loop_config={"cfg": cfg, "seed": seed, "lr": lr, "batch_size": batch_size,
                           "eval_batches": eval_batches},
        scaling_config=ScalingConfig(num_workers=num_workers, use_gpu=False, resources_per_worker={"CPU": 1}),
        datasets={"train": data},
        run_config=RunConfig(name="flowsynth-train-ray", storage_path=storage_path),
    )
    result = trainer.fit()
    metrics = dict(result.metrics, checkpoint=result.checkpoint.path)
    print(f"{metrics['step']} steps; train EPE {metrics['loss_first']:.3f} -> {metrics['loss_last']:.3f} px; "
          f"held-out EPE {metrics['epe_before']:.3f} -> {metrics['epe_after']:.3f} px")
    return metrics


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--steps", type=int, default=100)
    p.add_argument("--width", type=int, default=64)
    p.add_argument("--height", type=int, default=48)
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument("--num-workers", type=int, default=1, help="Ray Train workers (one CPU each)")
    p.add_argument("--actors", type=int, default=None, help="renderer actors (default: the CPUs left over)")
    p.add_argument("--address", default=None, help="Ray cluster to join (default: start a local one)")
    a = p.parse_args()
    train(a.steps, width=a.width, height=a.height, batch_size=a.batch_size, num_workers=a.num_workers,
          actors=a.actors, address=a.address)
