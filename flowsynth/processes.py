"""Worker processes and CUDA: the fork guard, the workers' start method, the worker mark.

CUDA does not survive ``fork()``: a child forked from a process that had initialised CUDA (torch on a GPU, or Warp,
whose initialisation starts the CUDA driver on a machine with one) inherits a driver state it cannot use, and Warp
there fails at every call. An at-fork hook notes in the parent whether it had initialised CUDA; in such a child, at
any generation, ``check_not_forked_from_cuda`` raises ``ForkError``. flowsynth calls it where it reaches the Warp
runtime (``flowsynth.kernels.wp_runtime``) and where it enters Newton (``flowsynth.scene.physics.simulate_physics``).
``worker_context`` picks a start method that avoids the state; ``set_worker_process`` marks a worker, whose launches
then default to one thread (``flowsynth.parallel``). The story and the numbers: docs/decisions/0027-workers-and-cuda.md.

Imports nothing beyond the standard library and ``flowsynth.errors``; reads torch and Warp only if already imported.
"""

from __future__ import annotations

import os
import sys

from flowsynth.errors import ForkError

__all__ = ["check_not_forked_from_cuda", "cuda_initialised", "is_worker_process", "set_worker_process",
           "worker_context"]

_worker_process = False
_cuda_at_fork = False  # in the parent, just before a fork: whether it had initialised CUDA
_forked_from_cuda = False  # in a child: whether a process it was forked from had (inherited down the generations)


def set_worker_process() -> None:
    """Mark this process as one of several worker processes (export workers, Ray actors): from now on
    ``is_worker_process()`` is True, and launches default to one thread."""
    global _worker_process
    _worker_process = True


def is_worker_process() -> bool:
    """Whether ``set_worker_process`` marked this process (a DataLoader worker is recognised by torch instead)."""
    return _worker_process


def cuda_initialised() -> bool:
    """Whether this process has initialised CUDA: torch (``torch.cuda.is_initialized()``) or Warp (its runtime
    found CUDA devices, so the driver is initialised). Looks only at modules already imported; imports nothing.

    Not seen: a process that only called ``torch.cuda.is_available()`` has started the driver without
    ``torch.cuda.is_initialized()`` saying so (``PYTORCH_NVML_BASED_CUDA_CHECK=1`` avoids starting it)."""
    torch = sys.modules.get("torch")
    if torch is not None and torch.cuda.is_initialized():
        return True
    context = sys.modules.get("warp._src.context") or sys.modules.get("warp.context")
    runtime = getattr(context, "runtime", None)
    return bool(getattr(runtime, "cuda_devices", None))


def _before_fork() -> None:
    global _cuda_at_fork
    _cuda_at_fork = cuda_initialised()


def _after_fork_in_child() -> None:
    global _forked_from_cuda
    _forked_from_cuda = _forked_from_cuda or _cuda_at_fork


def check_not_forked_from_cuda() -> None:
    """Return in a process that may run Warp; raise ``ForkError`` in one forked (at any generation) from a process
    that had initialised CUDA, before a Warp call there fails. The message says how to start workers instead."""
    if _forked_from_cuda:
        raise ForkError(
            "this process was forked from one that had initialised CUDA (torch on a GPU, or Warp), and CUDA does not "
            "survive fork(): Warp would print 'CUDA error 3' at every call and run slowly here. Start the workers with "
            "forkserver or spawn: fs.datasets.loader(dataset, batch_size=..., num_workers=K) does, or pass "
            "multiprocessing_context='forkserver' to torch's DataLoader (with the script's work under "
            "if __name__ == '__main__':)")


def worker_context(fork_ok: bool | None = None):
    """The ``multiprocessing`` context for worker processes that render on the CPU.

    Args:
        fork_ok: False rules ``fork`` out (for workers that may start after this process initialises CUDA, as a
            DataLoader's persistent workers may); None allows it while this process has not initialised CUDA
            (``cuda_initialised()``) and was not forked from one that had.

    Returns:
        ``fork`` where allowed and the platform has it (workers inherit the loaded modules: fastest to start), else
        ``forkserver`` (a fresh interpreter that never saw CUDA forks the workers), else ``spawn``.
    """
    import multiprocessing as mp

    methods = mp.get_all_start_methods()
    if fork_ok is None:
        fork_ok = not cuda_initialised() and not _forked_from_cuda
    if fork_ok and "fork" in methods:
        return mp.get_context("fork")
    return mp.get_context("forkserver" if "forkserver" in methods else "spawn")


if hasattr(os, "register_at_fork"):
    os.register_at_fork(before=_before_fork, after_in_child=_after_fork_in_child)
