"""Hashes of every output of a fixed set of samples: the before/after check of a change that must keep the bytes.

    python benchmarks/speed/hashes.py --out /tmp/before.json            # at the old commit
    python benchmarks/speed/hashes.py --check /tmp/before.json          # at the new one: exit 1 on any difference

The set covers each stage: the default stream (every core output, scene flow, tracks, stereo) in flat and direct
render modes, a 3-frame clip with flow gaps, and a hand-built scene. Each output tensor is hashed (sha256 of its
dtype, shape and bytes); ``provenance`` (the config and scene description as JSON bytes) is reported apart,
since a new config field changes it and nothing else; ``--threads`` renders with that many threads (the bytes
do not depend on it).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # benchmarks/: _common


def _digest(value) -> str:
    import numpy as np
    import torch

    if isinstance(value, torch.Tensor):
        a = value.detach().cpu().contiguous().numpy()
    else:
        a = np.asarray(value)
    h = hashlib.sha256(f"{a.dtype}{a.shape}".encode())
    h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def workloads(threads: int | None):
    """(name, sample dict) pairs of the fixed set."""
    import numpy as np
    import trimesh

    import flowsynth as fs
    from flowsynth.plan import CORE_OUTPUTS, SCENE_FLOW_KEYS, STEREO_KEYS

    everything = list(CORE_OUTPUTS + SCENE_FLOW_KEYS + STEREO_KEYS) + ["tracks", "provenance"]
    base = fs.BouncingThingsConfig(width=96, height=72, num_frames=2, stereo_baseline=0.1, num_tracks=32)
    for mode in ("flat", "direct"):
        cfg = dataclasses.replace(base, render_mode=mode)
        ds = fs.datasets.BouncingThings(cfg, outputs=everything, seed=3)
        for i in (0, 1, 5):
            yield f"{mode}/{i}", ds.sample(i)
    cfg = dataclasses.replace(base, num_frames=3, flow_gaps=(1, 2), stereo_baseline=0.0)
    ds = fs.datasets.BouncingThings(cfg, outputs=["rgb", "flow_fw", "flow_bw_k2", "occ_fw_k2", "depth", "meta"],
                                    seed=7)
    yield "gaps/2", ds.sample(2)
    T = 3
    cam = fs.Camera.from_fov(width=80, height=60, fov_deg=60.0)
    scene = fs.Scene(camera=cam, num_frames=T)
    scene.set_camera_poses(np.tile(np.eye(4), (T, 1, 1)))
    poses = np.tile(np.eye(4), (T, 1, 1))
    poses[:, :3, 3] = [[0.1 * t, 0.0, 4.0] for t in range(T)]
    scene.add_object(trimesh.creation.icosphere(subdivisions=2, radius=0.8), poses=poses, category=3)
    # edge_spp=1: fs.render's default until issue 41 settled one default (4) for every route; the saved sets of
    # before that commit were made with 1
    yield "hand/sphere", fs.render(scene, outputs=["depth", "normals", "instance", "flow_fw", "occ_fw", "rgb"],
                                   threads=threads, edge_spp=1)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", help="write the hashes to this JSON file")
    p.add_argument("--check", help="compare with this JSON file (exit 1 on any difference)")
    p.add_argument("--threads", type=int, default=None)
    args = p.parse_args()
    got = {}
    for name, sample in workloads(args.threads):
        got[name] = {k: _digest(v) for k, v in sorted(sample.items()) if k not in ("index", "seed")}
    if args.out:
        Path(args.out).write_text(json.dumps(got, indent=1))
    n = sum(len(v) for v in got.values())
    print(f"{n} outputs of {len(got)} samples hashed")
    if args.check:
        want = json.loads(Path(args.check).read_text())
        bad = [f"{s}:{k}" for s in sorted(set(want) | set(got))
               for k in sorted(set(want.get(s, {})) | set(got.get(s, {})))
               if want.get(s, {}).get(k) != got.get(s, {}).get(k)]
        meta = [b for b in bad if b.endswith(":provenance")]
        bad = [b for b in bad if b not in meta]
        if meta:  # the sample's config and scene description: a new config field changes it, never the pixels
            print(f"provenance differs in {len(meta)} samples (expected when the config gains a field; the pixels "
                  "and ground truth are compared below)")
        if bad:
            print(f"DIFFERENT ({len(bad)}): " + ", ".join(bad))
            sys.exit(1)
        print(f"identical to {args.check}" + (" (but for provenance)" if meta else ""))


if __name__ == "__main__":
    main()
