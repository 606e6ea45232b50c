"""``loader``: a ``torch.utils.data.DataLoader`` over a flowsynth stream whose worker processes survive CUDA.

DataLoader forks its workers by default on Linux, and CUDA does not survive ``fork()``: a flowsynth stream in a worker
forked after this process initialised CUDA raises ``ForkError`` (``flowsynth.processes``). ``loader``'s workers start
with ``forkserver`` (``spawn`` where the platform has none): a fresh interpreter that never saw CUDA forks them, and
each yields exactly the samples it would under fork (sample i is a pure function of (config, seed, i), and the
shards depend only on the worker's id). Each worker imports torch and flowsynth once and is sent the dataset
pickled, so the script's own work must sit under ``if __name__ == "__main__":``. Why and what it costs:
docs/decisions/0027-workers-and-cuda.md.
"""

from __future__ import annotations

from torch.utils.data import DataLoader, Dataset

from flowsynth.options import check_int
from flowsynth.processes import worker_context

__all__ = ["loader"]


def loader(dataset: Dataset, batch_size: int | None = 1, num_workers: int = 0, **kwargs) -> DataLoader:
    """A DataLoader over ``dataset`` (``BouncingThings``, ``Mixture``, ``FlowPairs``, ...) whose ``num_workers``
    worker processes start with forkserver (or spawn), so they render in a process that has initialised CUDA.

    Args:
        dataset: any dataset; flowsynth's streams split their indices over the workers themselves.
        batch_size: as DataLoader's (None: unbatched samples).
        num_workers: worker processes (0: samples are made in this process, where CUDA does no harm).
        kwargs: DataLoader's other arguments (torchdata's ``StatefulDataLoader`` takes the same start method).
            ``multiprocessing_context`` (a name or a context) overrides the start method; ``persistent_workers``
            defaults to True with workers, so an epoch after the first starts none (an epoch broken off skips the
            batches the workers had prefetched, up to ``prefetch_factor`` a worker, and repeats none).

    Returns:
        the DataLoader.

    Raises:
        ConfigError: ``num_workers`` is not an integer >= 0.
    """
    num_workers = check_int("num_workers", num_workers, 0)
    if num_workers > 0:
        kwargs.setdefault("multiprocessing_context", worker_context(fork_ok=False))
        kwargs.setdefault("persistent_workers", True)
    return DataLoader(dataset, batch_size=batch_size, num_workers=num_workers, **kwargs)
