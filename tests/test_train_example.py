"""The example training script learns: a few dozen steps reduce the held-out end-point error."""

import importlib.util
from pathlib import Path


def test_training_reduces_held_out_epe():
    path = Path(__file__).resolve().parents[1] / "examples" / "train_flow.py"
    spec = importlib.util.spec_from_file_location("train_flow", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    result = mod.train(steps=40, width=32, height=24, batch_size=4, workers=2, eval_batches=3, log_every=20)
    assert result["after"] < 0.9 * result["before"], result
    assert len(result["history"]) == 40


def test_workers_start_as_fs_datasets_loader_starts_them():
    """The example's batches come from fs.datasets.loader, as the README recommends: its workers start with
    forkserver or spawn (never fork, which CUDA does not survive), and stay for the next epoch."""
    import flowsynth as fs

    path = Path(__file__).resolve().parents[1] / "examples" / "train_flow.py"
    spec = importlib.util.spec_from_file_location("train_flow", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    cfg = fs.BouncingThingsConfig(width=32, height=24, num_frames=2, motion="kinematic", num_objects=(1, 2),
                                  max_objects=2)
    dl = mod.loader(cfg, 0, 2, 1)
    assert dl.multiprocessing_context.get_start_method() in ("forkserver", "spawn")
    assert dl.persistent_workers and dl.num_workers == 1
    a, b, flow, valid = next(mod.batches(cfg, 0, 2, 0))
    want = fs.datasets.BouncingThings(cfg, outputs=["rgb", "flow_fw", "valid_fw"], seed=0).sample(0)
    assert a.shape == (2, 3, 24, 32) and flow.shape == (2, 2, 24, 32) and valid.dtype.is_floating_point
    assert (flow[0] == want["flow_fw"][0]).all() and (a[0] == want["rgb"][0]).all()
