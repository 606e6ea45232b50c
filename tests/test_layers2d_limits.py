"""fs.datasets.Layers at its limits: the largest motion_scale a config takes gives finite outputs even for the most
extreme draw (every range at its end), the next value is refused; a texture_dir bank lists and reads its folder once.

Oracles: a generator that returns the ends of every range drawn from (the largest zoom, shift and rotation a draw can
have), and the same generator at ten times the bound, which overflows (so the finiteness check can fail); for the
bank, the number of listings and file reads counted, and files added and changed after the first read."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest
import torch
from PIL import Image

import flowsynth as fs
from flowsynth.datasets import LAYERS_OUTPUTS, Layers, LayersConfig, layers_pairs
from flowsynth.datasets.layer_draws import draw_pair
from flowsynth.datasets.layer_render import render_layers
from flowsynth.datasets.layers import MAX_MOTION

W, H = 48, 32


class Ends:
    """A stand-in for a numpy Generator that draws the upper (``top``) or lower end of every range, and normal
    values of 8 standard deviations: the largest zoom (or shrink), rotation and shift ``draw_pair`` can make."""

    def __init__(self, top: bool) -> None:
        self.top = top

    def integers(self, low, high=None):
        low, high = (0, low) if high is None else (low, high)
        return high - 1 if self.top else low

    def uniform(self, low=0.0, high=1.0, size=None):
        v = high if self.top else low
        return v if size is None else np.full(size, float(v))

    def normal(self, size=None):
        v = 8.0 if self.top else -8.0
        return v if size is None else np.full(size, v)


def _sources(n: int = 3) -> torch.Tensor:
    return torch.rand(n, 3, H, W, generator=torch.Generator().manual_seed(0))


def _extreme(scale: float, frames: int, top: bool) -> dict:
    src = _sources()
    keys = LAYERS_OUTPUTS if frames > 1 else ("rgb", "instance", "category")  # one frame has no pairs
    return render_layers(draw_pair(Ends(top), W, H, len(src), scale), src.__getitem__, W, H, frames, keys)


def _finite(out: dict) -> bool:
    return all(bool(torch.isfinite(v).all()) for v in out.values() if v.is_floating_point())


@pytest.mark.parametrize("frames", [1, 2, 3])
def test_the_largest_motion_scale_gives_finite_outputs_and_the_next_is_refused(frames):
    """motion_scale x max(frames - 1, 1) = MAX_MOTION: a config takes it, the most extreme draws (zooming in and out,
    an ellipse and a polygon) render every output finite and their provenance is strict JSON; the next float up is
    a ConfigError, in a config and in layers_pairs."""
    largest = MAX_MOTION / max(frames - 1, 1)
    assert LayersConfig(num_frames=frames, motion_scale=largest).motion_scale == largest
    with pytest.raises(fs.ConfigError, match="motion_scale x max"):
        LayersConfig(num_frames=frames, motion_scale=float(np.nextafter(largest, np.inf)))
    for top in (True, False):
        assert _finite(_extreme(largest, frames, top))
        json.dumps(draw_pair(Ends(top), W, H, 3, largest).to_dict(), allow_nan=False)
    if frames == 2:
        assert layers_pairs(1, 0, _sources(), largest)["flow_fw"].isfinite().all()
        with pytest.raises(fs.ConfigError, match="motion_scale"):
            layers_pairs(1, 0, _sources(), float(np.nextafter(largest, np.inf)))


def test_past_the_bound_the_extreme_draw_overflows():
    """The check above can fail: at ten times the bound the largest zoom, e^200, overflows float32's flow."""
    assert not _finite(_extreme(10 * MAX_MOTION, 2, top=True))


def test_a_stream_at_the_bound_is_finite(tmp_path):
    d = tmp_path / "photos"
    d.mkdir()
    for k in range(2):
        Image.fromarray(np.random.default_rng(k).integers(0, 256, (40, 60, 3), dtype=np.uint8)).save(d / f"{k}.png")
    ds = Layers(LayersConfig(width=W, height=H, num_frames=3, motion_scale=MAX_MOTION / 2, texture_dir=str(d)),
                [*LAYERS_OUTPUTS, "provenance"], seed=0)
    for i in range(4):
        s = ds.sample(i)
        assert _finite({k: v for k, v in s.items() if isinstance(v, torch.Tensor)})
        json.loads(s["provenance"], parse_constant=lambda c: pytest.fail(f"provenance holds {c}"))


def test_a_texture_dir_bank_reads_its_folder_once(tmp_path, monkeypatch):
    """The folder is listed once and each image read once however many samples and lookups follow; files added or
    changed later are not seen by that stream (a new one sees them); a pickled bank carries its listing, not its
    images: it reads the listed files again, once."""
    import flowsynth.appearance
    import flowsynth.io

    d = tmp_path / "photos"
    d.mkdir()
    for k in range(3):
        Image.fromarray(np.random.default_rng(k).integers(0, 256, (40, 60, 3), dtype=np.uint8)).save(d / f"{k}.png")
    calls = {"list": 0, "read": 0}
    list_textures, read_rgb_png = flowsynth.appearance.list_textures, flowsynth.io.read_rgb_png

    def counted_list(folder):
        calls["list"] += 1
        return list_textures(folder)

    def counted_read(path):
        calls["read"] += 1
        return read_rgb_png(path)

    monkeypatch.setattr(flowsynth.appearance, "list_textures", counted_list)
    monkeypatch.setattr(flowsynth.io, "read_rgb_png", counted_read)
    cfg = LayersConfig(width=W, height=H, texture_dir=str(d))
    ds = Layers(cfg, ["rgb"], seed=0)
    first = [ds.sample(i)["rgb"] for i in range(5)]
    images = [ds.textures[j].clone() for j in range(len(ds.textures))]
    assert calls == {"list": 1, "read": 3} and len(images) == 3
    for k in (0, 3, 4):  # 0.png changes to grey 0.2, two files are added
        Image.fromarray(np.full((40, 60, 3), 51, np.uint8)).save(d / f"{k}.png")
    assert len(ds.textures) == 3 and all(torch.equal(ds.textures[j], images[j]) for j in range(3))
    assert all(torch.equal(ds.sample(i)["rgb"], first[i]) for i in range(5))
    assert calls == {"list": 1, "read": 3}
    blob = pickle.dumps(ds.textures)
    assert len(blob) < 4096 < sum(im.numel() * 4 for im in images)
    copy = pickle.loads(blob)
    assert len(copy) == 3 and torch.allclose(copy[0], torch.full((3, H, W), 0.2))
    assert torch.equal(copy[1], images[1]) and torch.equal(copy[2], images[2])
    assert calls == {"list": 1, "read": 6}
    assert len(Layers(cfg, ["rgb"]).textures) == 5 and calls["list"] == 2
