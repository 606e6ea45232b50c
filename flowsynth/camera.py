"""Pinhole camera with OpenCV intrinsics.

Conventions (see docs/conventions.md): camera frame x right, y down, z forward. The centre of pixel
(row i, col j) has image coordinates (u, v) = (j, i). A camera point X = (x, y, z) projects to
u = (fx x + s y) / z + cx, v = fy y / z + cy, with skew s = K[0, 1] (usually 0).
"""

from __future__ import annotations

import functools
import math

import numpy as np
import torch

from flowsynth._checks import as_float64_array
from flowsynth.errors import ConfigError

__all__ = ["Camera"]


class Camera:
    """Pinhole camera: intrinsics ``K`` (3,3) and image size.

    Args:
        K: (3, 3) intrinsics [[fx, s, cx], [0, fy, cy], [0, 0, 1]] in pixels, numpy or torch.
        width: image width W [px], >= 1.
        height: image height H [px], >= 1.
    """

    def __init__(self, K, width: int, height: int) -> None:
        K = as_float64_array(K, "K", (3, 3))
        if not (isinstance(width, (int, np.integer)) and isinstance(height, (int, np.integer))):
            raise ConfigError(f"width and height must be integers, got {width!r} x {height!r}")
        if width < 1 or height < 1:
            raise ConfigError(f"image size must be at least 1x1 px, got width={width}, height={height}")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ConfigError(f"focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
        if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
            raise ConfigError("K must be upper triangular with K[2, 2] = 1 (OpenCV convention)")
        self._K = K
        self.width = int(width)
        self.height = int(height)

    @classmethod
    def from_fov(cls, width: int, height: int, fov_deg: float = 60.0) -> Camera:
        """Camera with horizontal field of view ``fov_deg`` [deg], square pixels and the principal point
        at the image centre ((W-1)/2, (H-1)/2)."""
        if not (isinstance(fov_deg, (int, float)) and math.isfinite(fov_deg) and 0.0 < fov_deg < 180.0):
            raise ConfigError(f"fov_deg must be in (0, 180), got {fov_deg!r}")
        if not (isinstance(width, (int, np.integer)) and width >= 1):
            raise ConfigError(f"width must be an integer >= 1, got {width!r}")
        f = 0.5 * width / math.tan(math.radians(fov_deg) / 2.0)
        K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
        return cls(K, width, height)

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 intrinsics (a copy)."""
        return self._K.copy()

    @property
    def fx(self) -> float:
        return float(self._K[0, 0])

    @property
    def fy(self) -> float:
        return float(self._K[1, 1])

    @property
    def cx(self) -> float:
        return float(self._K[0, 2])

    @property
    def cy(self) -> float:
        return float(self._K[1, 2])

    def pixel_rays(self, dtype=torch.float64) -> torch.Tensor:
        """Unit ray directions through every pixel centre, camera frame: (H, W, 3)."""
        return torch.from_numpy(self.pixel_rays_numpy().copy()).to(dtype)

    def pixel_rays_numpy(self) -> np.ndarray:
        """Read-only cached (H, W, 3) float64 unit ray directions through the pixel centres."""
        return _pixel_rays(self._K.tobytes(), self.width, self.height)

    def __repr__(self) -> str:
        return (f"Camera(width={self.width}, height={self.height}, fx={self.fx:.4g}, fy={self.fy:.4g}, "
                f"cx={self.cx:.4g}, cy={self.cy:.4g})")


@functools.lru_cache(maxsize=16)
def _pixel_rays(K_bytes: bytes, width: int, height: int) -> np.ndarray:
    """(H, W, 3) float64 unit directions K^-1 (u, v, 1) / |.|, cached per intrinsics and size (read-only)."""
    K = np.frombuffer(K_bytes, dtype=np.float64).reshape(3, 3)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    d = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    d.setflags(write=False)
    return d
