"""Worker processes that survive CUDA: ``loader``, a ``torch.utils.data.DataLoader`` over a flowsynth stream.

CUDA does not survive ``fork()``, and fork is DataLoader's default start method on Linux. A training script that
moves its net to the GPU (or renders a sample with Warp) before its loader starts the workers leaves them a CUDA
driver state they cannot use: Warp there prints "CUDA error 3" and renders about 10x slow (seen on an H200). A
flowsynth stream in such a forked worker raises ``ForkError`` at its first sample instead. ``loader`` starts the
workers with ``forkserver`` (``spawn`` where the platform has no forkserver): a fresh interpreter, which never saw
CUDA, forks them. Every worker yields exactly the samples it would under fork (sample i is a pure function of
(config, seed, i), and the shards depend only on the worker's id), at the CPU rate.

The price of a fresh interpreter: each worker imports torch and flowsynth and loads the compiled kernels from Warp's
cache once (a few seconds), the dataset is pickled to it, and the script's own work must sit under
``if __name__ == "__main__":``, as with any spawned worker. Workers are persistent by default, so a finite stream's
next epoch does not pay that again (a loop that breaks off an epoch and iterates again resumes after the batches the
workers had prefetched: up to 2 a worker are skipped, never repeated).

What is not caught: a parent that only called ``torch.cuda.is_available()`` has started the CUDA driver without
``torch.cuda.is_initialized()`` saying so (PyTorch's ``PYTORCH_NVML_BASED_CUDA_CHECK=1`` avoids that); its forked
children are not refused, and Warp there may print one CUDA error line and render on the CPU. torchdata's
``StatefulDataLoader`` takes ``multiprocessing_context="forkserver"`` the same way.
"""

from __future__ import annotations

from torch.utils.data import DataLoader, Dataset

from flowsynth.errors import ConfigError
from flowsynth.processes import worker_context

__all__ = ["loader"]


def loader(dataset: Dataset, batch_size: int | None = 1, num_workers: int = 0, **kwargs) -> DataLoader:
    """A DataLoader over ``dataset`` (``BouncingThings``, ``Mixture``, ``FlowPairs``, ...) whose ``num_workers``
    worker processes start with forkserver (or spawn), so they render at the CPU rate in a process that has
    initialised CUDA.

    Args:
        dataset: any dataset; flowsynth's streams split their indices over the workers themselves.
        batch_size: as DataLoader's (None: unbatched samples).
        num_workers: worker processes (0: samples are made in this process, where CUDA does no harm).
        kwargs: DataLoader's other arguments. ``multiprocessing_context`` (a name or a context) overrides the start
            method; ``persistent_workers`` defaults to True with workers.

    Returns:
        the DataLoader.
    """
    if isinstance(num_workers, bool) or not isinstance(num_workers, int) or num_workers < 0:
        raise ConfigError(f"num_workers must be an integer >= 0, got {num_workers!r}")
    if num_workers > 0:
        kwargs.setdefault("multiprocessing_context", worker_context(fork_ok=False))
        kwargs.setdefault("persistent_workers", True)
    return DataLoader(dataset, batch_size=batch_size, num_workers=num_workers, **kwargs)
