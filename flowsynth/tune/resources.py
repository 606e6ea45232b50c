"""What a tune needs of its machine, estimated before any work (``estimate``) and checked against what it may use
(``check``): memory (``flowsynth.memory.available_memory_bytes``; on CUDA also the device's free memory) and the
disk under the tune's folder, where its pools go.

The estimate, for rung 0 (it holds the most nets; a later rung holds fewer nets and no new pool):

- process: ``flowsynth.memory.BASE_BYTES``, the interpreter with torch, Warp and Newton loaded;
- validation pairs: their bytes as ``read_pairs`` holds them (15 a pixel: uint8 images, float32 flow, bool valid),
  sized from the image files' headers, on the host; one pair at a time is also on the device for its test;
- training (on ``device``): per net ``NET_BYTES`` + ``batch`` x crop pixels x (``PIXEL_BYTES`` + ``updates`` x
  ``UPDATE_BYTES``), every net of rung 0 at once (``flowsynth.train.ensemble.Ensemble``);
- testing (on ``device``): the largest pair, padded as ``flowsynth.train.steps.predict`` pads it: ``TEST_BASE_BYTES``,
  ``TEST_PIXEL_BYTES`` a pixel and its correlation pyramid, ``CORR_BYTES`` x (pixels / 64) ** 2;
- rendering (before training, not beside it): each rendering process's sample (``flowsynth.memory.
  sample_memory_bytes``; with ``workers`` the processes' own, else this one's beyond its base) and the chunks in
  flight;
- the pools: on disk (``flowsynth.tune.pools``: memory-mapped, so the kernel pages them in and out as memory
  allows), ``flowsynth.tune.pools.pool_bytes`` each, those not yet cached.

The training constants were fitted to RAFT-small's peak resident memory over two steps on the CPU (fp32, one torch
thread) at four shapes: (batch, crop, updates) = (6, 128x160, 8): 797 MiB a net; (6, 128x160, 2): 606; (2, 128x160,
8): 300; (1, 128x128, 2): 120; and 821 MiB a net for two nets at the first shape. Each is rounded up. The testing
constants were fitted (least squares, base + pixels + squared 1/8-scale pixels) to one pair at 12 updates at five
shapes on an AMD EPYC host, torch 2.13: 128x128 27.6 MiB, 256x256 48.2, 388x584 159.6, 400x600 172.6, 436x1024 491.9
(fit: 27.8 MiB + 125 B a pixel + 8.7 B a squared 1/8-scale pixel), then multiplied by 1.25: the CI host measured
196.5 MiB at 400x600, 14% above this one (a fit without margin said 172.8 there, the earlier model 192.8).
tests/test_tune_resources.py measures a small shape for training and 400x600 for testing against them.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from flowsynth.errors import ConfigError

__all__ = ["CORR_BYTES", "NET_BYTES", "PIXEL_BYTES", "TEST_BASE_BYTES", "TEST_PIXEL_BYTES", "UPDATE_BYTES", "check",
           "estimate", "memory_to_test", "memory_to_train"]

NET_BYTES = 64 << 20
"""Training memory of one RAFT-small net besides its batch [bytes]: weights, gradients, AdamW moments, workspace."""
PIXEL_BYTES = 4300
"""Training memory per crop pixel of a batch [bytes], besides the flow updates (fitted: 4190)."""
UPDATE_BYTES = 280
"""Training memory per crop pixel of a batch and flow update [bytes] (fitted: 272)."""
TEST_BASE_BYTES = 35 << 20
"""Test memory of one net besides its pair [bytes] (fitted: 27.8 MiB; x 1.25, module docstring)."""
TEST_PIXEL_BYTES = 160
"""Test memory per pixel of a padded validation pair [bytes] (fitted: 125; x 1.25)."""
CORR_BYTES = 11.0
"""Test memory of RAFT's correlation pyramid per squared 1/8-scale pixel [bytes] (fitted: 8.7, x 1.25; the
four float32 levels alone are 5.3: the rest is working memory of building them)."""
GIB = float(1 << 30)


def memory_to_train(recipe, nets: int) -> int:
    """Training memory of ``nets`` nets of ``recipe`` stepped at once [bytes]."""
    ch, cw = recipe.crop
    return nets * (NET_BYTES + recipe.batch * ch * cw * (PIXEL_BYTES + recipe.updates * UPDATE_BYTES))


def memory_to_test(size: tuple[int, int]) -> int:
    """Memory of testing one net on one pair of ``size`` = (H, W) [bytes], padded as ``training.predict`` pads."""
    h, w = (max(-(-x // 8) * 8, 128) for x in size)
    return int(TEST_BASE_BYTES + TEST_PIXEL_BYTES * h * w + CORR_BYTES * (h * w / 64) ** 2)


def estimate(recipe, nets: int, sizes: dict[str, tuple[int, int]], *, sources: list[tuple[dict, dict]],
             workers: int = 0, device: str = "cpu", cached: int = 0) -> dict:
    """The tune's needs [bytes] (module docstring): ``nets`` nets in rung 0, validation pairs of ``sizes`` ({name:
    (H, W)}), rung 0's pools' ``sources``, ``workers`` rendering processes, ``cached`` of the pools already on disk.

    Returns:
        {"host": {part: bytes}, "device": {part: bytes} (empty on the CPU: training and testing are host parts
        there), "disk": {"pools": bytes}, "peak": the host's peak, "device_peak"}; rendering and training are not
        at once, so the peak is the common parts plus the larger of the two.
    """
    from flowsynth.memory import BASE_BYTES, sample_memory_bytes
    from flowsynth.tune.pools import CHUNK, POOL_BYTES, pool_bytes

    w, h = recipe.res
    cfgs = [c for configs, _ in sources for c in configs.values()]
    sample = max(sample_memory_bytes(c) for c in cfgs)
    render = (workers * sample if workers else sample - BASE_BYTES) + max(2 * workers, 1) * CHUNK * w * h * POOL_BYTES
    pairs = sum(hh * ww * POOL_BYTES for hh, ww in sizes.values())
    largest = max(sizes.values(), key=lambda s: s[0] * s[1])
    work = {"training": memory_to_train(recipe, nets), "testing": memory_to_test(largest)}
    host = {"process": BASE_BYTES, "validation pairs": pairs, "rendering": render}
    on_device = device != "cpu"
    if not on_device:
        host.update(work)
    dev = work if on_device else {}
    peak = BASE_BYTES + pairs + max(render, 0 if on_device else sum(work.values()))
    pools = pool_bytes(recipe.pool, recipe.res) * max(len(sources) - cached, 0)
    return {"host": host, "device": dev, "disk": {"pools": pools}, "peak": peak, "device_peak": sum(dev.values())}


def _parts(parts: dict) -> str:
    return ", ".join(f"{k} {v / GIB:.2f}" for k, v in parts.items() if v)


def check(need: dict, device: str, folder: str | Path, hint: str) -> None:
    """Raise ConfigError when ``estimate``'s ``need`` is more memory than this process may use (``flowsynth.memory.
    available_memory_bytes``), more than the CUDA device has free, or more disk than ``folder``'s file system has
    free; the message gives the parts in GiB, what lowers each, and ``hint`` (the flag that goes on anyway)."""
    import torch

    from flowsynth.memory import available_memory_bytes

    problems = []
    avail = available_memory_bytes()
    if avail is not None and need["peak"] > avail:
        problems.append(f"about {need['peak'] / GIB:.1f} GiB of memory at its peak ({_parts(need['host'])} GiB; "
                        f"rendering comes before training, not beside it), but {avail / GIB:.1f} GiB are available")
    dev = torch.device(device)
    if dev.type == "cuda" and need["device_peak"]:
        free = torch.cuda.mem_get_info(dev)[0]
        if need["device_peak"] > free:
            problems.append(f"about {need['device_peak'] / GIB:.1f} GiB on {device} ({_parts(need['device'])} GiB), "
                            f"but {free / GIB:.1f} GiB are free there")
    folder = Path(folder)
    probe = next(p for p in (folder, *folder.parents) if p.exists())
    free_disk = shutil.disk_usage(probe).free
    if need["disk"]["pools"] > free_disk:
        problems.append(f"{need['disk']['pools'] / GIB:.1f} GiB of disk for its pools in {folder}, but "
                        f"{free_disk / GIB:.1f} GiB are free there")
    if problems:
        raise ConfigError("this tune needs " + "; and ".join(problems) + ". Lower --candidates (nets trained at "
                          "once), --pool (pairs a pool), the validation pairs (--pairs) or --workers, train on a "
                          f"--device with more memory, or {hint}")
