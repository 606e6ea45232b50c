"""All cores in one process: ray launches split into row bands, launched from a thread pool.

A Warp CPU launch runs on the calling thread, and releases the GIL while it runs. A launch over rows
(or rays) ``0 .. n-1`` is therefore cut into contiguous bands, and each band is launched from a worker
thread of a process-wide pool; the kernel takes the band's first index as an argument (``band0``) and
adds it to its thread id, so every pixel or ray is computed by the same code from the same inputs
whatever the banding: results are bit-identical for any thread count (tests/test_parallel.py).

Thread count (``threads``, a ``fs.render`` keyword, a ``Plan`` field and a ``BouncingThings`` argument):

- ``None`` (default): every core this process may run on, ``len(os.sched_getaffinity(0))``, except
  inside a DataLoader worker process or an export worker process, where it is 1: there the processes
  already share the cores, and processes x threads must not exceed them.
- an integer >= 1: exactly that many (1 = launch on the calling thread, no pool).

The cut: ``BANDS_PER_THREAD`` bands per thread, handed out in order, so a band full of expensive rays
(the objects of a scene are rarely spread evenly over the rows) does not leave the other threads idle.
On a CUDA device a launch is never cut.

Launch shape (``launch_image``): the image kernels (primary cast, pair kernel, world points, shading, tone mapping)
have two shapes of one body. On the CPU a thread does a row and loops over its pixels (a thread per pixel spends ~35
ns unravelling its 3-D index: docs/decisions/0004-pair-kernel-rows-and-culls.md); on a CUDA device a thread does one
pixel (the GPU's shape: no loop over a band of rows). Both compute every pixel from the same inputs in the same
steps, so the shape changes no bit (tests/test_batched.py runs the GPU's shape on the CPU).
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

from flowsynth.options import check_int
from flowsynth.processes import is_worker_process

__all__ = ["BAND0", "BANDS_PER_THREAD", "default_threads", "launch_bands", "launch_image", "pixel_threads",
           "resolve_threads"]

# Bands per thread of a cut launch (more bands balance uneven rows; each band costs one more launch).
BANDS_PER_THREAD = 4
# Fewest kernel threads (pixels, rays) in a band: smaller launches are not worth cutting.
MIN_BAND_ITEMS = 2048
# The image kernels' launch shape (``pixel_threads``): None = a thread per pixel on a CUDA device, a thread per row on
# the CPU; True or False force one shape on every device (the tests run the GPU's shape on the CPU).
PIXEL_THREADS: bool | None = None


class _Band0:
    """Placeholder in a kernel's ``inputs``: replaced by the first index of each band."""

    def __repr__(self) -> str:
        return "BAND0"


BAND0 = _Band0()

_pools: dict[int, ThreadPoolExecutor] = {}
_pool_lock = threading.Lock()
_loaded: set = set()


def default_threads() -> int:
    """Threads of a launch when none is asked for: 1 inside worker processes (``flowsynth.processes``' mark, or a
    DataLoader worker), else every core this process may run on."""
    if is_worker_process():
        return 1
    try:
        from torch.utils.data import get_worker_info

        if get_worker_info() is not None:
            return 1
    except ImportError:  # pragma: no cover - torch is a dependency
        pass
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def resolve_threads(threads: int | None) -> int:
    """``threads`` validated (an integer >= 1), or ``default_threads()`` for None."""
    if threads is None:
        return default_threads()
    return check_int("threads (None: all cores)", threads, 1)


def _get_pool(size: int) -> ThreadPoolExecutor:
    """The process's pool of exactly ``size`` threads (one pool per size asked for)."""
    with _pool_lock:
        if size not in _pools:
            _pools[size] = ThreadPoolExecutor(size, thread_name_prefix="flowsynth-band")
        return _pools[size]


def _forget_pool() -> None:
    """After fork the child has no pool threads: start new pools when needed."""
    global _pool_lock
    _pools.clear()
    _pool_lock = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def launch_bands(kernel, dim: tuple[int, ...], axis: int, inputs: list, outputs: list, device: str,
                 threads: int | None, row_loop: bool = False, cost: int = 1) -> None:
    """``wp.launch(kernel, dim, inputs, outputs, device)`` cut along ``axis`` into bands run in parallel.

    Args:
        kernel: a Warp kernel whose thread index along ``axis`` is offset by an int32 argument.
        dim: full launch dims.
        axis: the axis of ``dim`` to cut (rows of an image launch, rays of a 1-D launch).
        inputs: kernel inputs; the ``BAND0`` placeholder marks the offset argument.
        outputs: kernel outputs (whole arrays: each band writes its own rows).
        device: Warp device; a CUDA launch is never cut.
        threads: threads to use (None: ``default_threads()``).
        row_loop: the kernel loops over the last axis of ``dim`` itself: it is launched without it (``dim``
            still counts the work items, and ``axis`` must be another axis).
        cost: work of one item in units of a cheap one (a pixel's ray): items x cost, not items, is held
            against ``MIN_BAND_ITEMS`` (a kernel whose item loops over a mesh's vertices is cut sooner).
    """
    import warp as wp

    n = int(dim[axis])
    if n == 0 or any(int(x) == 0 for x in dim):
        return
    threads = resolve_threads(threads)
    items = 1
    for x in dim:
        items *= int(x)
    items *= max(int(cost), 1)
    bands = min(threads * BANDS_PER_THREAD, n, max(items // MIN_BAND_ITEMS, 1)) if threads > 1 else 1
    if row_loop:
        dim = tuple(dim)[:-1]
    if bands <= 1 or wp.get_device(device).is_cuda:
        wp.launch(kernel, dim=tuple(dim), inputs=[0 if a is BAND0 else a for a in inputs], outputs=outputs,
                  device=device)
        return
    key = (id(kernel.module), str(device))
    if key not in _loaded:  # compile or load once, before several threads launch it
        wp.load_module(kernel.module, device=device)
        _loaded.add(key)
    edges = [n * b // bands for b in range(bands + 1)]

    def run(b: int) -> None:
        d = list(dim)
        d[axis] = edges[b + 1] - edges[b]
        wp.launch(kernel, dim=tuple(d), inputs=[edges[b] if a is BAND0 else a for a in inputs], outputs=outputs,
                  device=device)

    pool = _get_pool(threads)
    for f in [pool.submit(run, b) for b in range(bands)]:
        f.result()


def pixel_threads(device) -> bool:
    """Whether image kernels launch a thread per pixel on ``device`` (a CUDA device) rather than one per row (the
    CPU), unless ``PIXEL_THREADS`` forces one shape."""
    import warp as wp

    if PIXEL_THREADS is not None:
        return bool(PIXEL_THREADS)
    return wp.get_device(device).is_cuda


def launch_image(build, dim: tuple[int, int, int], inputs: list, outputs: list, device: str,
                 threads: int | None) -> None:
    """Launch an image kernel over ``dim`` (frames or pairs, rows, columns) in the device's shape: ``build(per_pixel)``
    returns the kernel (a ``specialised_builder`` with a ``per_pixel`` flag), launched with a thread per pixel
    (``pixel_threads``) or per row (``row_loop``), in row bands on the CPU (``launch_bands``)."""
    per_pixel = pixel_threads(device)
    launch_bands(build(per_pixel), dim, 1, inputs, outputs, device, threads, row_loop=not per_pixel)
