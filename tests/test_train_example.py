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
