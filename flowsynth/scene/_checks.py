"""Input validation shared by the public API. Errors say what was expected and how to fix it."""

from __future__ import annotations

import numpy as np
import torch

from flowsynth.errors import ConfigError, ShapeError

__all__ = ["RIGID_TOL", "as_float64_array", "check_rigid"]

# Tolerance on R^T R = I and det R = 1 for a pose to count as rigid (float32 poses carry ~1e-7 error).
RIGID_TOL = 1e-4


def as_float64_array(x, name: str, shape: tuple) -> np.ndarray:
    """Convert a numpy array or torch tensor to float64 numpy and check its shape.

    ``shape`` entries may be ``None`` (any size). Raises ShapeError on mismatch, ConfigError on NaN/Inf.
    """
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().double().numpy()
    try:
        a = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ShapeError(f"{name} must be a numeric array of shape {_fmt(shape)}, got {type(x).__name__}") from e
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
        raise ShapeError(f"{name} must have shape {_fmt(shape)}, got {tuple(a.shape)}")
    if not np.isfinite(a).all():
        raise ConfigError(f"{name} contains NaN or Inf; pass finite values")
    return a


def check_rigid(T: np.ndarray, name: str) -> None:
    """Check that every (4,4) matrix in ``T`` (..., 4, 4) is a rigid transform [R t; 0 1], det R = +1."""
    R = T[..., :3, :3]
    bottom = T[..., 3, :]
    if not np.allclose(bottom, [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise ConfigError(f"{name}: last row of every pose must be [0, 0, 0, 1]")
    err = np.abs(np.einsum("...ji,...jk->...ik", R, R) - np.eye(3)).max(initial=0.0)
    if err > RIGID_TOL:
        raise ConfigError(
            f"{name}: rotation part is not orthonormal (max |R^T R - I| = {err:.2e} > {RIGID_TOL}); "
            "poses must be rigid — no scale or shear. Bake scale into the mesh vertices instead."
        )
    det = np.linalg.det(R) if R.size else np.ones(0)
    if (det < 0).any():
        raise ConfigError(f"{name}: rotation has determinant -1 (a reflection); use a proper rotation")


def _fmt(shape: tuple) -> str:
    return "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
