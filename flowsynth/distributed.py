"""Scale-out on Ray (the optional ``flowsynth[ray]`` extra): a Ray Data dataset of samples, and export.

Both run flowsynth in a fixed pool of Ray actors, one CPU each. An actor pays the setup once in
``__init__`` (imports, dataset, mesh caches; Warp kernels load from the node's cache, or compile, at its
first sample) and renders with one thread (``flowsynth.processes.set_worker_process``), like a
DataLoader or export worker process: actors x threads never exceed the CPUs Ray was given.

``ray_dataset`` is a Ray Data pipeline (``ray.data.ActorPoolStrategy``). It starts from
``ray.data.from_items`` (the sample indices, held in the driver), not from ``ray.data.range``: a
``range`` read task needs a CPU of its own, and on a cluster whose every CPU is held by an actor it
never runs (measured with Ray 2.60 on ``ray.init(num_cpus=2)``: an actor pool of 2 behind
``range(8)`` never finishes; behind ``from_items`` it returns all rows;
docs/decisions/0018-ray-export.md). Its actors are Ray Data's,
created with ``max_restarts=-1`` and ``max_task_retries=-1``
(``ray/data/_internal/execution/operators/actor_pool_map_operator.py``), so an actor that dies is
restarted and its batch runs again.

Export needs no dataset, only "run this job somewhere and give me its record": ``export_results``
drives plain actors with the same restart options itself, each holding the exporter's own
:class:`flowsynth.export.writer.ExportWriter` (the object the local engine calls). Samples are pure functions
of (config, seed, index), so a retry writes the same bytes.

Nothing outside this module imports Ray, and this module imports it only inside its functions.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

from flowsynth.errors import ConfigError
from flowsynth.options import check_int

__all__ = ["INSTALL_HINT", "connect", "export_results", "ray_dataset", "require_ray"]

INSTALL_HINT = "pip install 'flowsynth[ray]'  (in a checkout: bash scripts/setup.sh --ray)"


def require_ray():
    """The ``ray`` module, or a ConfigError naming the install command when the extra is missing."""
    try:
        import ray
        import ray.data
    except ImportError as e:
        raise ConfigError(f"the Ray engine needs Ray, which is not installed: {INSTALL_HINT}") from e
    return ray


def connect(address: str | None = None):
    """Join the Ray cluster at ``address`` (``"auto"``, ``"ray://host:10001"``, ``"host:6379"``) or, with
    None, the one this process already joined, else start a local one on this machine's CPUs.
    Returns the ``ray`` module."""
    ray = require_ray()
    if not ray.is_initialized():  # a cluster we start here needs no dashboard; one we join keeps its own
        ray.init(address=address, log_to_driver=False, **({} if address else {"include_dashboard": False}))
    return ray


def _cluster_cpus(ray) -> int:
    return max(int(ray.cluster_resources().get("CPU", 1)), 1)


def _pool_size(ray, actors: int | None, items: int) -> int:
    """Actors in a pool: ``actors`` (default: every CPU of the cluster), at most one per item."""
    if actors is not None:
        actors = check_int("actors (None: one per cluster CPU)", actors, 1)
    return min(actors or _cluster_cpus(ray), items)


def _pool(ray, actors: int | None, items: int):
    """A fixed Ray Data actor pool of :func:`_pool_size` actors."""
    return ray.data.ActorPoolStrategy(size=_pool_size(ray, actors, items))


class SampleRenderer:
    """Ray Data actor: ``{"item": (B,) int64 sample indices}`` -> one row per sample, every output key a
    column of ``BouncingThings(cfg, outputs, seed).sample(i)`` as numpy (shapes as in the stream,
    batch axis first)."""

    def __init__(self, cfg, outputs: Sequence[str], seed: int, occlusion: str) -> None:
        import torch

        from flowsynth.datasets import BouncingThings
        from flowsynth.processes import set_worker_process

        set_worker_process()
        torch.set_num_threads(1)
        self.ds = BouncingThings(cfg, outputs=outputs, seed=seed, occlusion=occlusion, threads=1)

    def __call__(self, batch: dict) -> dict:
        import numpy as np

        samples = [self.ds.sample(int(i)) for i in batch["item"]]
        return {k: np.array([s[k] for s in samples]) if isinstance(samples[0][k], str)  # provenance: JSON text
                else np.stack([s[k].numpy() for s in samples]) for k in samples[0]}


def ray_dataset(config, num_samples: int, seed: int = 0, outputs: Sequence[str] = ("rgb", "flow_fw"), *,
                start: int = 0, occlusion: str = "exact", actors: int | None = None, address: str | None = None):
    """Samples ``start .. start + num_samples - 1`` of ``BouncingThings(config, outputs, seed)`` as a
    ``ray.data.Dataset``, rendered lazily by a pool of actors.

    Args:
        config: BouncingThingsConfig (defaults when None).
        num_samples: number of rows, >= 1.
        seed, outputs, occlusion: as for ``flowsynth.datasets.BouncingThings``.
        start: first sample index.
        actors: actors in the pool, one CPU each (None: one per CPU of the cluster).
        address: Ray cluster to join when this process has not joined one (see :func:`connect`).

    Returns:
        A Dataset with one row per sample: every key of ``ds.sample(i)`` (``index``, ``seed`` and the outputs,
        ``K``, ``cam_T_world`` and ``provenance`` among them when asked for: ``"meta"``) as a numpy column with
        the stream's dtype and per-sample shape, equal to ``ds.sample(i)`` whatever the cluster size. Row order is
        not guaranteed; read ``index``. ``iter_torch_batches`` gives the tensors the DataLoader would.
    """
    from flowsynth.scene import BouncingThingsConfig
    from flowsynth.datasets import BouncingThings

    config = BouncingThingsConfig() if config is None else config
    num_samples = check_int("num_samples", num_samples, 1)
    outputs = BouncingThings(config, outputs=outputs, seed=seed, start=start, occlusion=occlusion).outputs
    ray = connect(address)
    items = list(range(start, start + num_samples))
    return ray.data.from_items(items, override_num_blocks=num_samples).map_batches(
        SampleRenderer, fn_constructor_args=(config, outputs, seed, occlusion), batch_size=1, num_cpus=1,
        compute=_pool(ray, actors, num_samples), batch_format="numpy")


class WriterActor:
    """Ray actor around a :class:`flowsynth.export.writer.ExportWriter`: opens it once as a worker process
    (one thread), then ``write(job)`` is ``writer(job)`` (the files are on disk, the record comes back)."""

    def __init__(self, writer) -> None:
        self.writer = writer.open(worker_process=True)

    def write(self, job: tuple) -> tuple:
        return self.writer(job)


_IN_FLIGHT = 2  # jobs queued per actor: the next one waits in the actor while the driver handles a result


def export_results(jobs: list, writer, *, actors: int | None = None, address: str | None = None) -> Iterator:
    """Run ``writer(job)`` (a :class:`flowsynth.export.writer.ExportWriter`) for every job in a pool of Ray actors;
    yields its return values in completion order. Each actor opens its copy of the writer once.

    Plain actors, not Ray Data (whose map operator would add a stats actor, a Ray Data import in every
    actor and a polling executor in the driver: start-up measured in benchmarks/speed/ray_export.py). They are
    created with ``max_restarts=-1, max_task_retries=-1``, so an actor that dies is restarted and its
    queued and running jobs run again on it; jobs are pure functions of (config, seed, index), so a
    retry writes the same bytes. An attempt cut short by a dying actor leaves a staging folder
    ``.tmp-*`` that no result names; the exporter removes those when the run ends. When the caller
    stops early (an error, an interrupt), the actors are killed and waited for before this returns, so
    none writes a staging folder after the exporter has cleaned up.
    """
    from collections import deque

    ray = connect(address)
    size = _pool_size(ray, actors, len(jobs))
    actor = ray.remote(num_cpus=1, max_restarts=-1, max_task_retries=-1)(WriterActor)
    pool = [actor.remote(writer) for _ in range(size)]  # every actor starts at once
    queue = deque(jobs)
    running: dict = {}  # ObjectRef -> the actor it runs on

    def submit(actor) -> None:
        if queue:
            running[actor.write.remote(queue.popleft())] = actor

    try:
        for _ in range(_IN_FLIGHT):
            for actor in pool:
                submit(actor)
        while running:
            [done], _ = ray.wait(list(running), num_returns=1)
            submit(running.pop(done))
            try:
                result = ray.get(done)
            except ray.exceptions.RayTaskError as e:  # the job's own exception, as the local pool raises it
                raise (e.cause if isinstance(e.cause, Exception) else e) from e
            yield result
    finally:
        for actor in pool:
            ray.kill(actor, no_restart=True)
        if running:  # they fail once their actor is dead: then no attempt writes any more
            ray.wait(list(running), num_returns=len(running), timeout=60)
