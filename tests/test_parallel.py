"""Ray launches cut into row bands over a thread pool (flowsynth.parallel), issue 13.

Every ray launch (primary, visibility, shadow, path) must give bit-identical results for any thread count,
on image sizes that no band count divides evenly; the cut must cover every index exactly once; and the
default thread count must be 1 inside DataLoader workers and export worker processes.
"""

import os

import numpy as np
import pytest
import torch
import trimesh
from oracle import pose

import flowsynth as fs
from flowsynth import parallel
from flowsynth.errors import ConfigError

W, H, T = 61, 45, 3
KEYS = ["depth", "normals", "instance", "position", "flow_fw", "flow_bw", "occ_fw", "occ_bw", "valid_fw",
        "oof_bw", "motion"]


def busy_scene() -> fs.Scene:
    """Overlapping moving objects in front of a wall, a moving camera: every stage has work."""
    rng = np.random.default_rng(7)
    scene = fs.Scene(fs.Camera.from_fov(W, H, 65.0), T)
    scene.set_camera_poses(np.stack([pose((0.0, 0.02 * t, 0.0), (0.05 * t, 0.0, 0.0)) for t in range(T)]))
    wall = pose(t=(0.0, 0.0, 9.0))
    scene.add_object(trimesh.creation.box((20.0, 20.0, 0.2)), np.stack([wall] * T))
    for k in range(8):
        mesh = trimesh.creation.icosphere(2, radius=0.5) if k % 2 else trimesh.creation.box((0.8, 0.6, 0.9))
        p0, v = rng.uniform([-2, -1.5, 3], [2, 1.5, 7]), rng.uniform(-0.3, 0.3, 3)
        scene.add_object(mesh, np.stack([pose((0.2 * t, 0.1 * k, 0.3 * t), p0 + t * v) for t in range(T)]))
    return scene


@pytest.fixture
def fine_bands(monkeypatch):
    """Cut even small launches into many bands (one band per BANDS_PER_THREAD rows and thread)."""
    monkeypatch.setattr(parallel, "MIN_BAND_ITEMS", 1)


@pytest.mark.parametrize("options", [
    dict(),
    dict(render_mode="direct"),
    dict(render_mode="path", bounces=2, spp=2, edge_spp=4),
    dict(render_mode="direct", spp=3, shutter=0.5, edge_spp=5),
], ids=["gbuffer+flow+occ", "direct", "path", "motion-blur"])
def test_results_bit_identical_for_any_thread_count(fine_bands, options):
    scene = busy_scene()
    keys = KEYS + (["rgb"] if options else [])
    ref = fs.render(scene, keys, threads=1, seed=5, **options)
    assert ref["instance"].unique().numel() > 5  # the scene is busy
    assert ref["occ_fw"].any() and not ref["occ_fw"].all()
    for threads in (2, 3):
        out = fs.render(scene, keys, threads=threads, seed=5, **options)
        for k in keys:
            assert torch.equal(out[k], ref[k]), (k, threads)


def test_default_cut_bit_identical():
    """The cut at its real granularity (no monkeypatch), on an odd size large enough to be cut."""
    scene = busy_scene()
    scene.camera = fs.Camera.from_fov(157, 93, 65.0)
    ref = fs.render(scene, ["depth", "occ_fw", "rgb"], threads=1, render_mode="direct")
    out = fs.render(scene, ["depth", "occ_fw", "rgb"], threads=2, render_mode="direct")
    for k in ref:
        assert torch.equal(out[k], ref[k]), k


def test_bands_cover_every_index_once(fine_bands):
    import warp as wp

    from flowsynth.kernels import wp_runtime

    wp_runtime()

    @wp.kernel(enable_backward=False)
    def count(band0: wp.int32, hits: wp.array3d[wp.int32]):
        f, i, j = wp.tid()
        wp.atomic_add(hits, f, i + band0, j, 1)

    for rows in (1, 2, 5, 37):
        hits = wp.zeros((2, rows, 13), dtype=wp.int32, device="cpu")
        parallel.launch_bands(count, (2, rows, 13), 1, [parallel.BAND0], [hits], "cpu", 3)
        np.testing.assert_array_equal(hits.numpy(), 1)


def test_thread_setting_is_validated():
    scene = busy_scene()
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ConfigError, match="threads"):
            fs.render(scene, ["depth"], threads=bad)


def test_default_threads_all_cores_in_main_process():
    assert parallel.default_threads() == len(os.sched_getaffinity(0))
    assert parallel.resolve_threads(None) == parallel.default_threads()
    assert parallel.resolve_threads(3) == 3


class _DefaultThreads(torch.utils.data.IterableDataset):
    def __iter__(self):
        yield torch.tensor(parallel.default_threads())


def test_default_threads_is_one_in_dataloader_workers():
    loader = torch.utils.data.DataLoader(_DefaultThreads(), num_workers=1, batch_size=None, timeout=600)
    assert [int(x) for x in loader] == [1]


def _worker_default(_):
    return parallel.default_threads()


def test_default_threads_is_one_in_export_workers(tmp_path):
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from flowsynth.io import layouts
    from flowsynth.export.writer import ExportWriter

    cfg = fs.BouncingThingsConfig(width=16, height=12, num_frames=1, num_objects=(1, 1), motion="static")
    writer = ExportWriter(cfg, ("depth",), 0, "exact", layouts.get("native"))
    with ProcessPoolExecutor(1, mp_context=mp.get_context("fork"), initializer=writer.start_worker) as pool:
        assert list(pool.map(_worker_default, [0])) == [1]


def test_face_planes_bit_identical_for_any_thread_count(fine_bands):
    """The visibility rays' face planes (a kernel whose item loops over the mesh's vertices) cut into bands."""
    from flowsynth.raycast.culling import _face_planes_of

    mesh = trimesh.creation.icosphere(3, radius=0.7)
    ref = _face_planes_of(mesh, threads=1)
    assert (ref["planes"][:, 3] < 1e29).all()
    for threads in (2, 3):
        got = _face_planes_of(mesh, threads=threads)
        assert np.array_equal(got["planes"], ref["planes"]), threads
        assert got["inner"] == ref["inner"] and np.array_equal(got["sphere"], ref["sphere"])
