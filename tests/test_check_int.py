"""One integer check at every public entry point: ``options.check_int``.

Each entry point takes a numpy integer where it takes a Python int, and refuses a bool, a float and a string the
same way: a ConfigError whose message names the field and shows the value. Where accepting the value would start
real work (an export, a tune, a Ray pool, statistics), a later argument is made invalid on purpose, so the call
stops at that argument's own check: the integer passed its check.
"""

from __future__ import annotations

import numpy as np
import pytest

from flowsynth.datasets import BouncingThings, DeviceBatches, Layers, LayersConfig, Mixture, Shards, loader
from flowsynth.errors import ConfigError
from flowsynth.export import export_dataset
from flowsynth.io import layouts
from flowsynth.options import check_int
from flowsynth.parallel import resolve_threads
from flowsynth.scene import BouncingThingsConfig, Camera, Scene
from flowsynth.scene.sampling import make_rng
from flowsynth.stats import dataset_stats
from flowsynth.tune import PoolRenderer, Recipe, tune

TINY = BouncingThingsConfig(width=32, height=32, num_frames=2)
TINY_2D = LayersConfig(width=32, height=32, num_frames=2)


def _shards(tmp_path, v):
    (tmp_path / "a.tar").write_bytes(b"")
    return Shards(tmp_path / "a.tar", buffer=v)


def _export(tmp_path, v):
    return export_dataset(TINY, tmp_path / "out", v, engine="no such engine", progress=False)


def _stats(tmp_path, v):
    return dataset_stats(BouncingThingsConfig(width=32, height=32, num_frames=1), v)


def _ray(tmp_path, v):
    from flowsynth.distributed import ray_dataset

    return ray_dataset(TINY, v, outputs=("no such output",))


def _tune(tmp_path, v):
    return tune(tmp_path / "no such folder", tmp_path / "work", candidates=v, precision="no such precision")


# (id, the field the message names, the call with the value, a good value, what a later check says, or None where
# the call with a good value returns)
ENTRIES = [
    ("BouncingThingsConfig", "num_frames", lambda p, v: BouncingThingsConfig(num_frames=v), 3, None),
    ("LayersConfig", "width", lambda p, v: LayersConfig(width=v), 64, None),
    ("BouncingThings", "seed", lambda p, v: BouncingThings(TINY, seed=v), 5, None),
    ("BouncingThings.sample", "sample index", lambda p, v: BouncingThings(TINY).sample(v), 0, None),
    ("Layers", "start", lambda p, v: Layers(LayersConfig(width=64, height=64), start=v), 2, None),
    ("Mixture", "seed", lambda p, v: Mixture({"a": TINY, "b": TINY_2D}, seed=v), 7, None),
    ("Mixture.curriculum", "until",
     lambda p, v: Mixture({"a": TINY, "b": TINY_2D}, [(v, {"a": 1}), (None, {"b": 1})]), 4, None),
    ("DeviceBatches", "batch_size", lambda p, v: DeviceBatches(TINY, batch_size=v), 2, None),
    ("loader", "num_workers", lambda p, v: loader(BouncingThings(TINY), num_workers=v), 0, None),
    ("Shards", "buffer", _shards, 4, None),
    ("webdataset layout", "shard_size", lambda p, v: layouts.get("webdataset", shard_size=v), 8, None),
    ("Camera.from_fov", "width", lambda p, v: Camera.from_fov(v, 48), 64, None),
    ("Scene", "num_frames", lambda p, v: Scene(Camera.from_fov(32, 32), v), 2, None),
    ("make_rng", "index", lambda p, v: make_rng(0, v), 3, None),
    ("resolve_threads", "threads", lambda p, v: resolve_threads(v), 1, None),
    ("export_dataset", "num", _export, 1, "engine"),
    ("dataset_stats", "num", _stats, 1, "statistics need flow"),
    ("ray_dataset", "num_samples", _ray, 1, "no such output"),
    ("tune.Recipe", "batch", lambda p, v: Recipe(batch=v), 4, None),
    ("tune.PoolRenderer", "workers", lambda p, v: PoolRenderer(v), 0, None),
    ("tune", "candidates", _tune, 4, "precision"),
]
IDS = [e[0] for e in ENTRIES]


@pytest.mark.parametrize(("field", "call", "good", "later"), [e[1:] for e in ENTRIES], ids=IDS)
def test_every_entry_point_takes_a_numpy_integer(tmp_path, field, call, good, later):
    if later is None:
        call(tmp_path, np.int64(good))
        return
    with pytest.raises(ConfigError) as e:
        call(tmp_path, np.int64(good))
    assert later in str(e.value) and f"{field} must be an integer" not in str(e.value), str(e.value)


@pytest.mark.parametrize("bad", [True, 2.0, "2"], ids=["bool", "float", "str"])
@pytest.mark.parametrize(("field", "call", "good", "later"), [e[1:] for e in ENTRIES], ids=IDS)
def test_every_entry_point_refuses_a_non_integer_the_same_way(tmp_path, field, call, good, later, bad):
    with pytest.raises(ConfigError) as e:
        call(tmp_path, bad)
    msg = str(e.value)
    assert field in msg and "must be an integer" in msg and repr(bad) in msg, msg


def test_check_int_is_the_rule():
    assert check_int("n", np.int32(3), 1) == 3 and type(check_int("n", np.uint8(3), 1)) is int
    assert check_int("n", 5, 0, 5) == 5
    for bad in (True, np.bool_(True), 1.0, np.float64(1.0), "1", None, np.array([1, 2])):
        with pytest.raises(ConfigError, match="n must be an integer"):
            check_int("n", bad, 0)
    with pytest.raises(ConfigError, match=r"n must be an integer in \[0, 5\], got 6"):
        check_int("n", 6, 0, 5)
