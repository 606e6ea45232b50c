"""The per-asset 4-wide BVH (flowsynth.raycast.blas, flowsynth.kernels.blas) against a float64 brute-force oracle."""

import numpy as np
import pytest
import trimesh

import oracle
from flowsynth.raycast import blas
from flowsynth.kernels import wp_runtime

wp = wp_runtime()

from flowsynth.kernels.blas import blas_any, blas_closest  # noqa: E402  (after Warp's quiet init)


@wp.kernel(enable_backward=False)
def _cast(bounds: wp.array[wp.vec4], kids: wp.array[wp.vec4i], tris: wp.array[wp.vec3], face: wp.array[wp.int32],
          root: wp.array[wp.int32], o: wp.array[wp.vec3], d: wp.array[wp.vec3], max_t: wp.array[wp.float32],
          f_out: wp.array[wp.int32], t_out: wp.array[wp.float32], uv_out: wp.array[wp.vec2],
          any_out: wp.array[wp.int32]):
    i = wp.tid()
    f, t, u, v = blas_closest(bounds, kids, tris, face, root[i], o[i], d[i], max_t[i])
    f_out[i] = f
    t_out[i] = t
    uv_out[i] = wp.vec2(u, v)
    any_out[i] = wp.where(blas_any(bounds, kids, tris, root[i], o[i], d[i], max_t[i]), 1, 0)


def cast(A: dict, mesh_of_ray: np.ndarray, o: np.ndarray, d: np.ndarray, max_t) -> dict:
    """blas_closest and blas_any of every ray (o, d) up to ``max_t`` (scalar or per ray) in mesh ``mesh_of_ray``
    of atlas ``A``."""
    R = len(o)
    outs = [wp.zeros(R, dtype=t) for t in (wp.int32, wp.float32, wp.vec2, wp.int32)]
    wp.launch(_cast, R, inputs=[A["bounds"], A["kids"], A["tris"], A["face"],
                                wp.array(A["roots"][mesh_of_ray], dtype=wp.int32),
                                wp.array(o.astype(np.float32), dtype=wp.vec3),
                                wp.array(d.astype(np.float32), dtype=wp.vec3),
                                wp.array(np.broadcast_to(np.float32(max_t), (R,)).astype(np.float32),
                                         dtype=wp.float32)],
              outputs=outs)
    f, t, uv, a = (x.numpy() for x in outs)
    return {"face": f, "t": t, "uv": uv, "any": a.astype(bool)}


def soup(n: int, seed: int) -> trimesh.Trimesh:
    """n random, intersecting triangles in the unit cube (a tree with overlapping boxes)."""
    rng = np.random.default_rng(seed)
    c = rng.uniform(-1, 1, (n, 1, 3))
    return trimesh.Trimesh((c + rng.normal(0, 0.15, (n, 3, 3))).reshape(-1, 3), np.arange(3 * n).reshape(n, 3),
                           process=False)


MESHES = {
    "icosphere": lambda: trimesh.creation.icosphere(subdivisions=3, radius=0.8),
    "torus": lambda: trimesh.creation.torus(0.9, 0.3),
    "soup": lambda: soup(400, 0),
    "box": lambda: trimesh.creation.box((1.0, 0.6, 0.3)),  # 12 faces: one node of leaves
    # two faces: the tree is a single leaf
    "quad": lambda: trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.0]], [[0, 1, 2], [0, 2, 3]]),
}


def rays(n: int, seed: int):
    """Rays from a shell around the meshes towards random points near them, the first 10 % along an axis."""
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3))
    o *= 2.5 / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.normal(0, 0.6, (n, 3)) - o
    k = n // 10
    d[:k] = np.eye(3)[rng.integers(0, 3, k)] * rng.choice([-1.0, 1.0], (k, 1))
    o[:k] = rng.uniform(-1.2, 1.2, (k, 3)) - 2.5 * d[:k]
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("name", sorted(MESHES))
def test_closest_and_any_hit_match_brute_force(name):
    mesh = MESHES[name]()
    A = blas.atlas([mesh])
    o, d = rays(20000, 1)
    o32, d32 = o.astype(np.float32).astype(np.float64), d.astype(np.float32).astype(np.float64)
    got = cast(A, np.zeros(len(o), int), o32, d32, 1e6)
    ref = oracle.ray_cast(o32, d32, [mesh], np.eye(4)[None])
    hit, ref_hit = got["face"] >= 0, np.isfinite(ref["t"])
    assert ref_hit.sum() > 2000 and (~ref_hit).sum() > 2000  # the test sees hits and misses
    # a ray may disagree only where the oracle's hit grazes an edge (both sides are right to float32 precision)
    ub = ref["bary"]
    edge = np.minimum(np.minimum(ub[:, 0], ub[:, 1]), 1 - ub.sum(1))
    disagree = hit != ref_hit
    assert (disagree & ~(ref_hit & (np.abs(edge) < 1e-5))).sum() <= 2, f"{disagree.sum()} rays disagree"
    both = hit & ref_hit
    t, rt = got["t"][both], ref["t"][both]
    assert np.all(np.abs(t - rt) <= 1e-5 * np.maximum(rt, 1.0))
    # the reported face and (u, v) give the hit point: u a + v b + (1 - u - v) c = o + t d
    tri = np.asarray(mesh.vertices)[np.asarray(mesh.faces)[got["face"][both]]]
    u, v = got["uv"][both, :1], got["uv"][both, 1:]
    p = u * tri[:, 0] + v * tri[:, 1] + (1 - u - v) * tri[:, 2]
    assert np.abs(p - (o32[both] + t[:, None] * d32[both])).max() < 1e-5
    # any hit: the same rays as the closest hit; nothing nearer than the closest hit, something just beyond it
    assert np.array_equal(got["any"], hit)
    idx = np.nonzero(hit)[0]
    for scale, expect in ((1 - 1e-4, False), (1 + 1e-4, True)):
        again = cast(A, np.zeros(len(idx), int), o32[idx], d32[idx], got["t"][idx] * scale)
        assert np.all(again["any"] == expect) and np.all((again["face"] >= 0) == expect)


def test_scaled_copies_share_one_tree_and_refit_holds_every_triangle():
    unit = trimesh.creation.icosphere(subdivisions=4)
    blas.topology(unit.vertices, unit.faces)
    before = len(blas._TOPOLOGY[next(reversed(blas._TOPOLOGY))])
    meshes = [trimesh.Trimesh(unit.vertices * s, unit.faces, process=False) for s in (0.31, 1.7, 2.9)]
    A = blas.atlas(meshes)
    assert len(blas._TOPOLOGY[next(reversed(blas._TOPOLOGY))]) == before  # no second build
    bounds = A["bounds"].numpy().reshape(-1, 6, 4)
    kids = A["kids"].numpy()
    tris = A["tris"].numpy().reshape(-1, 3, 3)
    leaves, inner = kids <= -2, kids >= 0
    n, j = np.nonzero(leaves)
    c = -2 - kids[n, j]
    for node, lane, first, cnt in zip(n, j, c >> 3, c & 7):
        t = tris[first:first + cnt].reshape(-1, 3)
        assert np.array_equal(bounds[node, :3, lane], t.min(0)) and np.array_equal(bounds[node, 3:, lane], t.max(0))
    # slot: face f of mesh m is the triangle slot[face0[m] + f] (its vertices, in the mesh's order)
    slot = A["slot"].numpy()
    for m, f0 in zip(meshes, A["face0"]):
        got = tris[slot[f0:f0 + len(m.faces)]]
        assert np.array_equal(got, np.asarray(m.vertices, np.float32)[np.asarray(m.faces)])
    n, j = np.nonzero(inner)
    child = bounds[kids[n, j]]
    assert np.array_equal(bounds[n, :3, j], child[:, :3].min(2))
    assert np.array_equal(bounds[n, 3:, j], child[:, 3:].max(2))
    # each copy is its own refit: the same rays scaled with the mesh hit the same faces at scaled distances
    o, d = rays(4000, 2)
    hits = [cast(A, np.full(len(o), k), o * s, d, 1e6) for k, s in enumerate((0.31, 1.7, 2.9))]
    both = (hits[0]["face"] >= 0) & (hits[1]["face"] >= 0)
    assert both.sum() > 1000 and np.mean(hits[0]["face"][both] == hits[1]["face"][both]) > 0.999
    np.testing.assert_allclose(hits[1]["t"][both] / 1.7, hits[0]["t"][both] / 0.31, rtol=1e-5)


def test_empty_mesh_is_refused():
    with pytest.raises(ValueError, match="at least one face"):
        blas.topology(np.zeros((3, 3)), np.zeros((0, 3), int))
