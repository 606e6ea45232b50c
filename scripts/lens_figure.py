"""Draw docs/lens_distortion.png: where each lens model (flowsynth/scene/camera.py) takes a grid of pixel centres.

    python scripts/lens_figure.py

For a 64x48 camera (pinhole fov 100 deg) and each model of docs/conventions.md: every fourth pixel centre of the
distorted image (dots) and where its ray meets the undistorted pinhole image plane, K (a, b, 1) (crosses; the ray
from Camera.unproject), joined by a line, the view cut at 0.6 image sizes around the frame; pixels whose
centre has no ray (uncovered) in red.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import flowsynth as fs

W, H = 64, 48
LENSES = [("brown_conrady", (-0.3, 0.1, 0.001, -0.002, 0.0), "Brown-Conrady, barrel (-0.3, 0.1, 0.001, -0.002, 0)"),
          ("brown_conrady", (-0.45, 0.0, 0.0, 0.0), "Brown-Conrady, strong barrel (-0.45, 0, 0, 0): folds"),
          ("kannala_brandt", (-0.3, 0.05, 0.0, 0.0), "Kannala-Brandt (-0.3, 0.05, 0, 0): fisheye circle")]


def main() -> None:
    fig, axes = plt.subplots(1, len(LENSES), figsize=(5 * len(LENSES), 4.4))
    v, u = np.mgrid[0:H:4, 0:W:4]
    for ax, (model, dist, title) in zip(axes, LENSES):
        cam = fs.Camera.from_fov(W, H, 100.0, model=model, dist=dist)
        rays, ok = cam.unproject(np.stack([u.ravel(), v.ravel()], 1).astype(np.float64))
        und = np.zeros((len(rays), 2))
        und[ok] = rays[ok, :2] / rays[ok, 2:] @ cam.K[:2, :2].T + cam.K[:2, 2]
        for (x0, y0), (x1, y1) in zip(np.stack([u.ravel(), v.ravel()], 1)[ok], und[ok]):
            ax.plot([x0, x1], [y0, y1], color="0.7", lw=0.6)
        ax.scatter(u.ravel()[ok], v.ravel()[ok], s=6, color="tab:blue", label="pixel centre (distorted image)")
        ax.scatter(und[ok, 0], und[ok, 1], s=10, marker="x", color="tab:orange", label="its ray on the pinhole plane")
        ax.scatter(u.ravel()[~ok], v.ravel()[~ok], s=6, color="tab:red", label="uncovered (no ray)")
        ax.add_patch(plt.Rectangle((-0.5, -0.5), W, H, fill=False, color="k", lw=0.8))
        ax.set_title(title, fontsize=9)
        ax.set_aspect("equal")
        ax.set_xlim(-0.6 * W, 1.6 * W)  # rays near 90 deg meet the pinhole plane far out: cut at the frame
        ax.set_ylim(1.6 * H, -0.6 * H)
        ax.set_xlabel("u [px]")
    axes[0].set_ylabel("v [px]")
    axes[0].legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    out = Path(__file__).resolve().parent.parent / "docs" / "lens_distortion.png"
    fig.savefig(out, dpi=110)
    print(out)


if __name__ == "__main__":
    main()
