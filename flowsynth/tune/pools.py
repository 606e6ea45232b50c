"""A tune's training pools: rendered into tensors allocated once (``PoolRenderer``, ``render_pool``), by worker
processes started once for every pool of a tune, and kept on disk (``PoolCache``), so a resumed tune renders none
again and the pools a rung trains on are memory-mapped files, not process memory.

A pool is pairs 0 .. n-1 of ``Mixture(*sources, seed=seed)`` (frames 0 and 1 of each sample, in index order at any
number of workers): img1, img2 uint8 (n, 3, H, W), flow float32 (n, 2, H, W) [px], valid bool (n, 1, H, W);
``POOL_BYTES`` a pixel a pair.

A cached pool is two files in the cache folder, named by a hash of the pool's identity (its sources, seed and size;
not the library's version: a tune resumed under another version trains on the pools it began with): ``KEY.npy``,
the four tensors' bytes one after another as one uint8 array (each at a multiple of ``ALIGN``), and ``KEY.json``,
the identity, the tune's identity and each tensor's dtype, shape and offset. Both are written atomically
(``flowsynth.io.atomic_path``), the ``.npy`` first: a pool without its ``.json`` was cut short and is rendered again.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections import deque
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import torch

from flowsynth.caches import register
from flowsynth.errors import ConfigError
from flowsynth.options import check_int

__all__ = ["OUTPUTS", "POOL_BYTES", "PoolCache", "PoolRenderer", "pool_bytes", "render_pool"]

OUTPUTS = ("rgb", "flow_fw", "valid_fw")  # what a pool is made of
POOL_BYTES = 2 * 3 + 2 * 4 + 1  # [bytes per pixel] of a pool's pair: two uint8 images, float32 flow, bool valid
CHUNK = 16  # [pairs] rendered per task of a worker process
ALIGN = 64  # [bytes] each tensor of a cached pool starts at a multiple of this in its file
_LAYOUT = (("img1", 3, torch.uint8), ("img2", 3, torch.uint8), ("flow", 2, torch.float32), ("valid", 1, torch.bool))
_STREAMS: dict = register("tune.pool_streams", {})  # (repr of sources, seed) -> the Mixture rendering them, per process


def pool_bytes(n: int, res: tuple[int, int]) -> int:
    """Bytes of a pool of ``n`` pairs at ``res`` = (width, height) [px]."""
    return n * res[0] * res[1] * POOL_BYTES


def _empty(n: int, res: tuple[int, int]) -> tuple[torch.Tensor, ...]:
    w, h = res
    return tuple(torch.empty(n, c, h, w, dtype=dt) for _, c, dt in _LAYOUT)


def _stream(sources: tuple[dict, dict], seed: int):
    key = (repr(sources), seed)
    if key not in _STREAMS:
        from flowsynth.datasets import Mixture

        _STREAMS.clear()  # one pool's stream at a time: a texture bank's frames are cached apart from it
        _STREAMS[key] = Mixture(*sources, outputs=list(OUTPUTS), seed=seed)
    return _STREAMS[key]


def _render_chunk(sources: tuple[dict, dict], seed: int, lo: int, hi: int) -> tuple[int, list[np.ndarray]]:
    """Pairs lo .. hi-1 of the pool as numpy arrays (the layout's order), and the rendering process's id."""
    ds = _stream(sources, seed)
    parts: list[list[np.ndarray]] = [[], [], [], []]
    for i in range(lo, hi):
        s = ds.sample(i)
        rgb = (s["rgb"][:2] * 255).round().clamp(0, 255).to(torch.uint8)
        for lst, x in zip(parts, (rgb[0], rgb[1], s["flow_fw"][0], s["valid_fw"][0] > 0.5)):
            lst.append(x.numpy())
    return os.getpid(), [np.stack(p) for p in parts]


def _init_worker() -> None:
    torch.set_num_threads(1)  # as a DataLoader worker: the processes share the cores


class PoolRenderer:
    """Renders pools (module docstring) in ``workers`` processes (0: this one), started on the first pool and reused
    for every later one until ``close()``, so what a process caches once (render kernels, a texture bank's frames) is
    made once per process, not once per pool. The processes start with forkserver (``flowsynth.processes.
    worker_context``), so a process that has initialised CUDA may render.

    ``pids``: the ids of the processes that have rendered pairs so far. A context manager: ``with PoolRenderer(2) as
    render: render(sources, seed, n)``."""

    def __init__(self, workers: int = 0) -> None:
        self.workers = check_int("workers", workers, 0)
        self.pids: set[int] = set()
        self._pool: ProcessPoolExecutor | None = None

    def __call__(self, sources: tuple[dict, dict], seed: int, n: int,
                 out: tuple[torch.Tensor, ...] | None = None) -> tuple[torch.Tensor, ...]:
        """Pairs 0 .. n-1 of ``Mixture(*sources, seed=seed)`` (``sources`` = (configs, weights), configs of 2 or more
        frames), written into ``out`` (four tensors of the pool's dtypes and shapes: a memory map, say) or, when it
        is None, into tensors allocated here; returns them. Nothing of pool size is allocated besides ``out``."""
        w, h = next(iter(sources[0].values())).width, next(iter(sources[0].values())).height
        if out is None:
            out = _empty(n, (w, h))
        size = min(CHUNK, -(-n // max(self.workers, 1)))  # every worker has a part of a small pool
        chunks = [(lo, min(lo + size, n)) for lo in range(0, n, size)]
        if self.workers == 0:
            results = (_render_chunk(sources, seed, lo, hi) for lo, hi in chunks)
        else:
            results = self._parallel(sources, seed, chunks)
        for (lo, hi), (pid, arrays) in zip(chunks, results):
            self.pids.add(pid)
            for dst, a in zip(out, arrays):
                dst[lo:hi] = torch.from_numpy(a)
        return out

    def _parallel(self, sources, seed, chunks):
        """Each chunk's result in order, at most two chunks a worker in flight (the results wait in memory)."""
        if self._pool is None:
            from flowsynth.processes import worker_context

            self._pool = ProcessPoolExecutor(self.workers, mp_context=worker_context(fork_ok=False),
                                             initializer=_init_worker)
        todo, ahead = iter(chunks), deque()
        for lo, hi in todo:
            ahead.append(self._pool.submit(_render_chunk, sources, seed, lo, hi))
            if len(ahead) >= 2 * self.workers:
                break
        while ahead:
            yield ahead.popleft().result()
            nxt = next(todo, None)
            if nxt is not None:
                ahead.append(self._pool.submit(_render_chunk, sources, seed, *nxt))

    def close(self) -> None:
        """Stop the worker processes (a later pool starts new ones)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def __enter__(self) -> PoolRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def render_pool(sources: tuple[dict, dict], seed: int, n: int, workers: int = 0,
                out: tuple[torch.Tensor, ...] | None = None) -> tuple[torch.Tensor, ...]:
    """One pool (module docstring) rendered by a ``PoolRenderer(workers)`` closed after it; ``out`` as its."""
    with PoolRenderer(workers) as render:
        return render(sources, seed, n, out)


def _pool_identity(sources: tuple[dict, dict], seed: int, n: int) -> dict:
    configs, weights = sources
    return {"configs": {k: c.to_dict() for k, c in configs.items()}, "weights": dict(weights), "seed": seed, "n": n,
            "outputs": list(OUTPUTS)}


def refuse_other_tune(what: str, saved: dict, ours: dict) -> None:
    """ConfigError, naming the fields that differ, when a folder's saved tune identity ``saved`` is not ``ours``
    (``what`` leads the message: "DIR holds" a tune, "DIR holds the pools of" one)."""
    if saved != ours:
        diff = sorted(k for k in saved.keys() | ours.keys() if saved.get(k) != ours.get(k))

        def field(k: str) -> str:  # a short value is named (a pool's configs are not: too long to read)
            old, new = json.dumps(saved.get(k)), json.dumps(ours.get(k))
            return k if max(len(old), len(new)) > 40 else f"{k}: {old} there, {new} here"

        raise ConfigError(f"{what} a tune of other settings (they differ in {diff}: {'; '.join(map(field, diff))}); "
                          "run it with its own settings to continue it, or remove the folder (or name another --out) "
                          "to start")


class PoolCache:
    """The pools of one tune on disk (module docstring), in ``folder``: ``get`` maps a cached pool, or renders it
    into a new file and maps that. ``tune``: the tune's identity (JSON values), recorded in every pool's ``.json``;
    ``check`` refuses a folder holding pools of another tune."""

    def __init__(self, folder: str | os.PathLike[str], tune: dict) -> None:
        self.folder, self.tune = Path(folder), tune

    def _key(self, identity: dict) -> str:
        return hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()[:16]

    def check(self) -> None:
        """Raise ConfigError when a pool in the folder was recorded by a tune of another identity (naming the
        fields that differ)."""
        for meta in sorted(self.folder.glob("*.json")):
            saved = json.loads(meta.read_text())["tune"]
            refuse_other_tune(f"{self.folder} holds the pools of", saved, self.tune)

    def paths(self, sources: tuple[dict, dict], seed: int, n: int) -> tuple[Path, Path]:
        """The (``.npy``, ``.json``) files of that pool."""
        key = self._key(_pool_identity(sources, seed, n))
        return self.folder / f"{key}.npy", self.folder / f"{key}.json"

    def get(self, sources: tuple[dict, dict], seed: int, n: int, render: Callable,
            log: Callable[[str], None] = lambda line: None) -> tuple[torch.Tensor, ...]:
        """That pool, memory-mapped (copy on write: the file never changes): read from the cache, or first rendered
        by ``render(sources, seed, n, out=...)`` into a new file. ``log`` is told which."""
        from flowsynth.io import atomic_path, write_json

        identity = _pool_identity(sources, seed, n)
        data, meta = self.paths(sources, seed, n)
        w, h = next(iter(sources[0].values())).width, next(iter(sources[0].values())).height
        if meta.is_file() and data.is_file():
            saved = json.loads(meta.read_text())
            if saved["pool"] != identity or saved["tune"] != self.tune:
                raise ConfigError(f"{meta} describes another pool or tune than its name says; remove it")
            log(f"tune: pool of {n} pairs for seed {seed} read from {data.name}")
            return self._map(data, saved["layout"])
        log(f"tune: rendering a pool of {n} pairs for seed {seed} into {data.name}")
        self.folder.mkdir(parents=True, exist_ok=True)
        layout, offset = [], 0
        for name, c, dt in _LAYOUT:
            size = n * c * h * w * torch.empty(0, dtype=dt).element_size()
            layout.append({"name": name, "dtype": str(dt).removeprefix("torch."), "shape": [n, c, h, w],
                           "offset": offset})
            offset += -(-size // ALIGN) * ALIGN
        with atomic_path(data) as tmp:
            whole = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.uint8, shape=(offset,))
            render(sources, seed, n, out=self._views(torch.from_numpy(whole), layout))
            whole.flush()
            del whole
        write_json(meta, {"pool": identity, "tune": self.tune, "layout": layout})
        return self._map(data, layout)

    @staticmethod
    def _views(whole: torch.Tensor, layout: list[dict]) -> tuple[torch.Tensor, ...]:
        out = []
        for part, (_, _, dt) in zip(layout, _LAYOUT):
            size = int(np.prod(part["shape"])) * torch.empty(0, dtype=dt).element_size()
            out.append(whole[part["offset"]:part["offset"] + size].view(dt).view(part["shape"]))
        return tuple(out)

    def _map(self, data: Path, layout: list[dict]) -> tuple[torch.Tensor, ...]:
        return self._views(torch.from_numpy(np.load(data, mmap_mode="c")), layout)

    def remove(self, sources: tuple[dict, dict], seed: int, n: int) -> None:
        """Delete that pool's files (a net that left the search never needs its pool again)."""
        for p in reversed(self.paths(sources, seed, n)):
            p.unlink(missing_ok=True)

    def clear(self) -> None:
        """Delete every pool of the folder, and the folder when nothing else is in it."""
        for p in [*self.folder.glob("*.json"), *self.folder.glob("*.npy")]:
            p.unlink(missing_ok=True)
        if self.folder.is_dir() and not any(self.folder.iterdir()):
            self.folder.rmdir()
