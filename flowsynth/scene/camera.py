"""Camera with OpenCV intrinsics and an optional lens model (OpenCV's conventions; kornia's equations).

Conventions (see docs/conventions.md): camera frame x right, y down, z forward. The centre of pixel
(row i, col j) has image coordinates (u, v) = (j, i). A camera point X = (x, y, z), z > 0, with normalised
coordinates (a, b) = (x / z, y / z) projects to

- ``"pinhole"``: u = fx a + s b + cx, v = fy b + cy, with skew s = K[0, 1] (usually 0);
- ``"brown_conrady"`` (cv2.projectPoints), dist = (k1, k2, p1, p2[, k3[, k4, k5, k6]]), r2 = a^2 + b^2:
  q = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3),
  a' = a q + 2 p1 a b + p2 (r2 + 2 a^2), b' = b q + p1 (r2 + 2 b^2) + 2 p2 a b, u = fx a' + cx, v = fy b' + cy;
- ``"kannala_brandt"`` (cv2.fisheye.projectPoints), dist = (k1, k2, k3, k4), r = |(a, b)|, theta = atan(r):
  theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8), (a', b') = theta_d / r (a, b)
  ((a, b) itself when r < 1e-8), u = fx a' + cx, v = fy b' + cy.

A lens model is used on its *domain*, where the map is one-to-one: z > 0 and, for Brown-Conrady, r2 below the
first radius where r q(r) stops growing (``lens_limit``, inf when it never does); for Kannala-Brandt theta
below the first angle where theta_d stops growing (at most pi / 2). Points outside it project nowhere
(``project``'s ``ok`` False; flow's ``valid`` False). A pixel whose centre has no preimage in the domain
(beyond the image of the domain: strong barrel distortion's corners, a fisheye's circle) is *uncovered*: its
ray is 0 and the renderer reports no hit there (``covered``).
"""

from __future__ import annotations

import functools
import math

import numpy as np
import torch

from flowsynth.caches import register
from flowsynth.errors import ConfigError
from flowsynth.options import check_int
from flowsynth.scene._checks import as_float64_array

__all__ = ["LENS_MODELS", "LENS_UNSUPPORTED", "NEWTON_TOL", "Camera", "check_lens_outputs"]

# Lens models and the numbers of coefficients each accepts (OpenCV's order).
LENS_MODELS = {"pinhole": (0,), "brown_conrady": (4, 5, 8), "kannala_brandt": (4,)}
# An unprojected pixel centre counts as solved when the model maps it back within this [normalised units]
# (1e-10 x a focal length of 1e4 px = 1e-6 px).
NEWTON_TOL = 1e-10
_NEWTON_STEPS = 60
# A point stops iterating once the model maps it back within this [normalised units] (NEWTON_TOL / 1000).
_DONE_TOL = 1e-13
# Fixed-point steps of kornia's undistort_points giving Newton's start (Brown-Conrady; kornia's default). Newton
# finishes the job; more steps of kornia's cost most of an unprojection (cProfile) and change no ray beyond 1e-13.
_KORNIA_ITERS = 5
# Points per kornia call: elementwise torch ops on more than 32768 elements go to torch's intra-op thread pool,
# which cost up to 100x the CPU time of the same work in chunks on a loaded machine (same values either way).
_KORNIA_CHUNK = 8192
# Kannala-Brandt's theta depends on the distorted radius alone: kornia's start on this many radii, interpolated.
_KB_START_RADII = 257
# Brown-Conrady's domain is searched for a fold up to this normalised radius (an 89.4 deg half-angle).
_R_SEARCH = 100.0
# lens_limit scans its grid of radii in chunks of this many points (the same grid, the same first fold).
_R_CHUNK = 20000


class Camera:
    """Camera: intrinsics ``K`` (3,3), image size and a lens model (module docstring).

    Args:
        K: (3, 3) intrinsics [[fx, s, cx], [0, fy, cy], [0, 0, 1]] in pixels, numpy or torch.
        width: image width W [px], >= 1.
        height: image height H [px], >= 1.
        model: "pinhole" (default), "brown_conrady" or "kannala_brandt"; a lens model needs skew s = 0 (as
            OpenCV's projectPoints, which ignores it).
        dist: the model's coefficients in OpenCV's order: (k1, k2, p1, p2[, k3[, k4, k5, k6]]) for
            Brown-Conrady, (k1, k2, k3, k4) for Kannala-Brandt; None or () for a pinhole.
    """

    def __init__(self, K, width: int, height: int, *, model: str = "pinhole", dist=None) -> None:
        K = as_float64_array(K, "K", (3, 3))
        width, height = check_int("width", width, 1), check_int("height", height, 1)
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ConfigError(f"focal lengths must be positive, got fx={K[0, 0]}, fy={K[1, 1]}")
        if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
            raise ConfigError("K must be upper triangular with K[2, 2] = 1 (OpenCV convention)")
        self._K = K
        self.width = int(width)
        self.height = int(height)
        self.model, self.dist = check_lens(model, dist)
        if self.model != "pinhole" and K[0, 1] != 0:
            raise ConfigError(f"a {self.model} camera needs zero skew K[0, 1] (OpenCV's projectPoints ignores "
                              f"it), got {K[0, 1]}")
        self.lens_limit = lens_limit(self.model, self.dist)

    @classmethod
    def from_fov(cls, width: int, height: int, fov_deg: float = 60.0, *, model: str = "pinhole",
                 dist=None) -> Camera:
        """Camera with horizontal field of view ``fov_deg`` [deg] (of the pinhole part: fx = W / (2 tan(fov / 2))),
        square pixels and the principal point at the image centre ((W-1)/2, (H-1)/2)."""
        if not (isinstance(fov_deg, (int, float)) and math.isfinite(fov_deg) and 0.0 < fov_deg < 180.0):
            raise ConfigError(f"fov_deg must be in (0, 180), got {fov_deg!r}")
        width, height = check_int("width", width, 1), check_int("height", height, 1)
        f = 0.5 * width / math.tan(math.radians(fov_deg) / 2.0)
        K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
        return cls(K, width, height, model=model, dist=dist)

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

    @property
    def is_pinhole(self) -> bool:
        return self.model == "pinhole"

    def pixel_rays(self, dtype=torch.float64) -> torch.Tensor:
        """Unit ray directions through every pixel centre, camera frame: (H, W, 3); 0 where uncovered."""
        return torch.from_numpy(self.pixel_rays_numpy().copy()).to(dtype)

    def pixel_rays_numpy(self) -> np.ndarray:
        """Read-only cached (H, W, 3) float64 unit ray directions through the pixel centres (through the lens
        model: ``unproject``), 0 where a pixel is uncovered."""
        if self.is_pinhole:
            return _pixel_rays(self._K.tobytes(), self.width, self.height)
        return _lens_rays(self._K.tobytes(), self.width, self.height, self.model, self.dist)

    def ray_grid(self, pad: int = 2) -> np.ndarray:
        """Read-only cached (H + 2 pad, W + 2 pad, 3) float64 unit rays through the pixel centres of rows -pad ..
        H - 1 + pad and columns -pad .. W - 1 + pad (``pixel_rays_numpy`` inside, bit for bit; the ring outside
        through ``unproject`` too), 0 where uncovered: the stencils of shading's sub-pixel rays and the lens tile
        bounds of ``flowsynth.raycast.accel`` (one ring each)."""
        if pad == 0:
            return self.pixel_rays_numpy()
        return _ray_grid(self._K.tobytes(), self.width, self.height, self.model, self.dist, int(pad))

    @property
    def covered(self) -> np.ndarray:
        """(H, W) bool: the pixel centre has a ray (always True for a pinhole)."""
        return self.pixel_rays_numpy()[..., 2] > 0

    def project(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame points X (P, 3) [m] -> image points uv (P, 2) [px] through the model, float64, and ``ok``
        (P,) bool: X lies in the model's domain (z > 0 and within ``lens_limit``); uv is 0 where not ok."""
        X = np.asarray(X, np.float64)
        ok = X[:, 2] > 0
        z = np.where(ok, X[:, 2], 1.0)
        ab = X[:, :2] / z[:, None]
        if self.is_pinhole:
            uv = ab @ self._K[:2, :2].T + self._K[:2, 2]
        else:
            ok &= in_domain(self.model, self.lens_limit, ab)
            uv = distort(self.model, self.dist, np.where(ok[:, None], ab, 0.0), self._K)
        return np.where(ok[:, None], uv, 0.0), ok

    def unproject(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Image points uv (P, 2) [px] -> unit camera-frame rays (P, 3) float64 through the model, and ``ok`` (P,):
        the point has a preimage in the domain (rays 0 where not). Brown-Conrady starts from kornia's
        ``undistort_points``, Kannala-Brandt from kornia's ``undistort_points_kannala_brandt``; both are then
        solved by Newton's method (safeguarded by bisection for Kannala-Brandt's monotone theta_d) to
        ``NEWTON_TOL``."""
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        if self.is_pinhole:
            d = np.concatenate([uv, np.ones((len(uv), 1))], 1) @ np.linalg.inv(self._K).T
            return d / np.linalg.norm(d, axis=1, keepdims=True), np.ones(len(uv), bool)
        return unproject_lens(self.model, self.dist, self.lens_limit, self._K, uv)

    def lens_meta(self) -> dict:
        """{"model", "dist"} for provenance and camera files ({} for a pinhole: unchanged pinhole files)."""
        return {} if self.is_pinhole else {"model": self.model, "dist": list(self.dist)}

    def __repr__(self) -> str:
        lens = "" if self.is_pinhole else f", model={self.model!r}, dist={self.dist}"
        return (f"Camera(width={self.width}, height={self.height}, fx={self.fx:.4g}, fy={self.fy:.4g}, "
                f"cx={self.cx:.4g}, cy={self.cy:.4g}{lens})")


# Outputs a lens camera does not give: stereo (a distorted pair is not rectified: "disparity" along rows has no
# meaning there). RGB (rgb, rgb_final) is shaded through the model (flowsynth/kernels/shade.py).
LENS_UNSUPPORTED = ("rgb_right", "depth_right", "disparity", "disparity_right", "disparity_change", "disparity_occ",
                    "disparity_occ_right")


def check_lens_outputs(camera: Camera, outputs) -> None:
    """ConfigError when a lens camera is asked for an output it does not give (``LENS_UNSUPPORTED``)."""
    bad = [k for k in outputs if k in LENS_UNSUPPORTED]
    if bad and not camera.is_pinhole:
        raise ConfigError(f"outputs {bad} are not available with a {camera.model} camera: stereo disparity is "
                          "defined for a rectified pinhole pair only (a distorted pair's epipolar lines are curves); "
                          "use model='pinhole' or drop them")


def check_lens(model, dist) -> tuple[str, tuple[float, ...]]:
    """Validated (model, dist tuple of floats); ConfigError says what each model accepts."""
    if model not in LENS_MODELS:
        raise ConfigError(f"camera model must be one of {list(LENS_MODELS)}, got {model!r}")
    if dist is None:
        dist = ()
    if isinstance(dist, torch.Tensor):
        dist = dist.detach().cpu().double().numpy()
    try:
        d = tuple(float(x) for x in np.asarray(dist, np.float64).reshape(-1))
    except (TypeError, ValueError) as e:
        raise ConfigError(f"dist must be a sequence of numbers, got {dist!r}") from e
    if not all(math.isfinite(x) for x in d):
        raise ConfigError(f"dist must be finite, got {d}")
    counts = LENS_MODELS[model]
    if len(d) not in counts:
        want = {"pinhole": "none (a pinhole has no distortion; use model='brown_conrady' or 'kannala_brandt')",
                "brown_conrady": "4, 5 or 8: (k1, k2, p1, p2[, k3[, k4, k5, k6]])",
                "kannala_brandt": "4: (k1, k2, k3, k4)"}[model]
        raise ConfigError(f"a {model} camera takes {want} distortion coefficients, got {len(d)}: {d}")
    return model, d


def _bc(dist: tuple) -> np.ndarray:
    """Brown-Conrady coefficients padded to OpenCV's 8: (k1, k2, p1, p2, k3, k4, k5, k6)."""
    return np.pad(np.asarray(dist, np.float64), (0, 8 - len(dist)))


def _kb_poly(k: np.ndarray, th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """theta_d(theta) and its derivative."""
    t2 = th * th
    f = th * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))
    df = 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * 9 * k[3])))
    return f, df


def _bc_radial(k: np.ndarray, r2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, D, d(r q)/dr) of the radial factor q = N / D at r2 = r^2."""
    N = 1 + r2 * (k[0] + r2 * (k[1] + r2 * k[4]))
    D = 1 + r2 * (k[5] + r2 * (k[6] + r2 * k[7]))
    dN = k[0] + r2 * (2 * k[1] + 3 * r2 * k[4])
    dD = k[5] + r2 * (2 * k[6] + 3 * r2 * k[7])
    with np.errstate(divide="ignore", invalid="ignore"):
        g = N / D + 2 * r2 * (dN * D - N * dD) / (D * D)
    return N, D, g


@register("camera.lens_limit")
@functools.lru_cache(maxsize=64)
def lens_limit(model: str, dist: tuple) -> float:
    """The domain's bound: Brown-Conrady the largest r2 = a^2 + b^2 (the first fold of r q(r) or zero of its
    denominator, inf when none up to r = 100), Kannala-Brandt the largest theta (the first fold of theta_d,
    at most pi / 2) [rad]; inf for a pinhole."""
    if model == "pinhole":
        return math.inf
    if model == "kannala_brandt":
        k = np.asarray(dist, np.float64)
        th = np.linspace(0.0, math.pi / 2, 100001)
        bad = np.nonzero(_kb_poly(k, th)[1] <= 0)[0]
        if len(bad) == 0:
            return math.pi / 2
        lo, hi = th[bad[0] - 1], th[bad[0]]
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if _kb_poly(k, np.array(mid))[1] > 0 else (lo, mid)
        return float(lo)
    k = _bc(dist)
    r = _r_grid()
    first = None
    for c0 in range(0, len(r), _R_CHUNK):  # outwards chunk by chunk: a fold near the axis ends the scan early
        rc = r[c0:c0 + _R_CHUNK]
        _, D, g = _bc_radial(k, rc * rc)
        bad = np.nonzero(~((D > 0) & (g > 0)))[0]
        if len(bad):
            first = c0 + int(bad[0])
            break
    if first is None:
        return math.inf
    lo, hi = r[first - 1], r[first]
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        _, Dm, gm = _bc_radial(k, np.array(mid * mid))
        lo, hi = (mid, hi) if (Dm > 0 and gm > 0) else (lo, mid)
    return float(lo * lo)


@register("camera.radius_grid")
@functools.cache
def _r_grid() -> np.ndarray:
    """lens_limit's grid of radii: 1,000,001 points on [0, _R_SEARCH] (read-only)."""
    r = np.linspace(0.0, _R_SEARCH, 1000001)
    r.setflags(write=False)
    return r


def in_domain(model: str, limit: float, ab: np.ndarray) -> np.ndarray:
    """(P,) bool: normalised points ab (P, 2) (of points with z > 0) lie in the model's domain."""
    r2 = (ab * ab).sum(1)
    if model == "kannala_brandt":
        return np.arctan(np.sqrt(r2)) < limit
    return r2 < limit


def distort(model: str, dist: tuple, ab: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Normalised points ab (P, 2) -> pixels (P, 2) through the lens model (module docstring), numpy float64:
    the equations of kornia's ``distort_points`` (Brown-Conrady) and ``distort_points_kannala_brandt``, which
    tests/test_lens.py checks this against (and against OpenCV). Not kornia's calls themselves: they were ~87% of
    a lens sample's profile (the amodal boxes project every mesh edge's sample points; benchmarks/speed/throughput.py
    --lens), and this form computes the same values."""
    ab = np.asarray(ab, np.float64)
    a, b = ab[:, 0], ab[:, 1]
    if model == "brown_conrady":
        k = _bc(dist)
        r2 = a * a + b * b
        q = (1 + r2 * (k[0] + r2 * (k[1] + r2 * k[4]))) / (1 + r2 * (k[5] + r2 * (k[6] + r2 * k[7])))
        ad = a * q + 2 * k[2] * a * b + k[3] * (r2 + 2 * a * a)
        bd = b * q + k[2] * (r2 + 2 * b * b) + 2 * k[3] * a * b
    else:
        r = np.hypot(a, b)
        small = r < 1e-8
        rr = np.where(small, 1.0, r)
        th = np.arctan(rr)
        s = np.where(small, 1.0, _kb_poly(np.asarray(dist, np.float64), th)[0] / rr)
        ad, bd = s * a, s * b
    return np.stack([K[0, 0] * ad + K[0, 2], K[1, 1] * bd + K[1, 2]], 1)


def _bc_forward(k: np.ndarray, a: np.ndarray, b: np.ndarray):
    """Brown-Conrady in numpy: distorted (a', b') and the 2x2 Jacobian entries (for Newton's method)."""
    r2 = a * a + b * b
    N, D, _ = _bc_radial(k, r2)
    q = N / D
    dN = k[0] + r2 * (2 * k[1] + 3 * r2 * k[4])
    dD = k[5] + r2 * (2 * k[6] + 3 * r2 * k[7])
    dq = (dN * D - N * dD) / (D * D)  # dq / d(r2)
    p1, p2 = k[2], k[3]
    ad = a * q + 2 * p1 * a * b + p2 * (r2 + 2 * a * a)
    bd = b * q + p1 * (r2 + 2 * b * b) + 2 * p2 * a * b
    j00 = q + 2 * a * a * dq + 2 * p1 * b + 6 * p2 * a
    j01 = 2 * a * b * dq + 2 * p1 * a + 2 * p2 * b
    j10 = 2 * a * b * dq + 2 * p1 * a + 2 * p2 * b
    j11 = q + 2 * b * b * dq + 6 * p1 * b + 2 * p2 * a
    return ad, bd, j00, j01, j10, j11


def unproject_lens(model: str, dist: tuple, limit: float, K: np.ndarray,
                   uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Camera.unproject`` of a lens model (see there)."""
    from kornia.geometry.calibration import undistort_points

    P = len(uv)
    ad = (uv[:, 0] - K[0, 2]) / K[0, 0]  # distorted normalised coordinates
    bd = (uv[:, 1] - K[1, 2]) / K[1, 1]
    rays = np.zeros((P, 3))
    if model == "kannala_brandt":
        k = np.asarray(dist, np.float64)
        rd = np.hypot(ad, bd)
        top = _kb_poly(k, np.array(limit))[0]
        ok = rd < top
        th = _kb_theta(k, rd, limit)
        ok &= np.abs(_kb_poly(k, th)[0] - rd) <= NEWTON_TOL
        s = np.where(rd > 0, np.sin(th) / np.where(rd > 0, rd, 1.0), 0.0)
        rays = np.stack([s * ad, s * bd, np.cos(th)], 1)
        return np.where(ok[:, None], rays, 0.0), ok
    k = _bc(dist)
    pts, Kt, kt = torch.from_numpy(np.ascontiguousarray(uv, np.float64))[None], torch.from_numpy(K.copy())[None], \
        torch.from_numpy(k)[None]
    with torch.no_grad():  # in chunks below torch's parallel grain: its intra-op threads spun on a loaded machine
        guess = np.concatenate([np.zeros((0, 2))] + [
            undistort_points(pts[:, c:c + _KORNIA_CHUNK], Kt, kt, num_iters=_KORNIA_ITERS)[0].numpy()
            for c in range(0, P, _KORNIA_CHUNK)])
    a = (guess[:, 0] - K[0, 2]) / K[0, 0]
    b = (guess[:, 1] - K[1, 2]) / K[1, 1]
    bad = ~(np.isfinite(a) & np.isfinite(b)) | ~in_domain(model, limit, np.stack([a, b], 1))
    a = np.where(bad, ad, a)  # kornia's fixed point left the domain: start from the distorted point itself
    b = np.where(bad, bd, b)
    with np.errstate(all="ignore"):
        act = np.arange(P)  # points still iterating: a point leaves once solved to _DONE_TOL
        for _ in range(_NEWTON_STEPS):
            fa, fb, j00, j01, j10, j11 = _bc_forward(k, a[act], b[act])
            ea, eb = fa - ad[act], fb - bd[act]
            more = ~(np.hypot(ea, eb) <= _DONE_TOL)
            if not more.any():
                break
            act, ea, eb, j00, j01, j10, j11 = (x[more] for x in (act, ea, eb, j00, j01, j10, j11))
            aa, bb = a[act], b[act]
            det = j00 * j11 - j01 * j10
            da = np.where(det != 0, (j11 * ea - j01 * eb) / det, 0.0)
            db = np.where(det != 0, (j00 * eb - j10 * ea) / det, 0.0)
            # damped: a step never more than doubles or halves the radius (keeps Newton on the domain's branch)
            r = np.hypot(aa, bb) + 1e-12
            step = np.hypot(da, db)
            sc = np.minimum(1.0, 0.5 * r / np.maximum(step, 1e-300))
            sc = np.where(r < 1e-6, 1.0, sc)
            a[act], b[act] = aa - sc * da, bb - sc * db
        fa, fb = _bc_forward(k, a, b)[:2]
        ok = np.isfinite(a) & np.isfinite(b) & (np.hypot(fa - ad, fb - bd) <= NEWTON_TOL)
    ok &= in_domain(model, limit, np.stack([np.where(ok, a, 0.0), np.where(ok, b, 0.0)], 1))
    d = np.stack([np.where(ok, a, 0.0), np.where(ok, b, 0.0), np.ones(P)], 1)
    rays = d / np.linalg.norm(d, axis=1, keepdims=True)
    return np.where(ok[:, None], rays, 0.0), ok


def _kb_theta(k: np.ndarray, rd: np.ndarray, limit: float) -> np.ndarray:
    """theta in [0, limit] with theta_d(theta) = rd (clamped at the ends): kornia's Gauss-Newton start
    (its undistort_points_kannala_brandt), then Newton steps kept inside a bisection bracket (theta_d grows
    on [0, limit])."""
    from kornia.geometry.camera import undistort_points_kannala_brandt

    params = torch.tensor([1.0, 1.0, 0.0, 0.0, *k], dtype=torch.float64)
    # theta depends on rd alone: kornia's start on _KB_START_RADII radii up to the largest, interpolated
    radii = np.linspace(0.0, float(rd.max(initial=0.0)), _KB_START_RADII)
    pts = torch.from_numpy(np.stack([radii, np.zeros_like(radii)], 1))
    with torch.no_grad():
        a = undistort_points_kannala_brandt(pts, params)[:, 0].numpy()
    th = np.interp(rd, radii, np.arctan(np.where(np.isfinite(a), np.abs(a), 0.0)))
    lo, hi = np.zeros_like(rd), np.full_like(rd, limit)
    th = np.clip(th, lo, hi)
    act = np.arange(len(rd))  # radii still iterating: one leaves once solved to _DONE_TOL
    for _ in range(_NEWTON_STEPS):
        t, lo_a, hi_a = th[act], lo[act], hi[act]
        f, df = _kb_poly(k, t)
        e = f - rd[act]
        more = ~(np.abs(e) <= _DONE_TOL)
        if not more.any():
            break
        act, t, lo_a, hi_a, e, df = (x[more] for x in (act, t, lo_a, hi_a, e, df))
        lo_a = np.where(e < 0, t, lo_a)
        hi_a = np.where(e > 0, t, hi_a)
        nxt = t - e / np.where(df > 0, df, 1.0)
        th[act] = np.where((nxt > lo_a) & (nxt < hi_a) & (df > 0), nxt, 0.5 * (lo_a + hi_a))
        lo[act], hi[act] = lo_a, hi_a
    return th


@register("camera.pixel_rays")
@functools.lru_cache(maxsize=16)
def _pixel_rays(K_bytes: bytes, width: int, height: int) -> np.ndarray:
    """(H, W, 3) float64 unit directions K^-1 (u, v, 1) / |.|, cached per intrinsics and size (read-only)."""
    K = np.frombuffer(K_bytes, dtype=np.float64).reshape(3, 3)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    d = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    d.setflags(write=False)
    return d


@register("camera.lens_rays")
@functools.lru_cache(maxsize=16)
def _lens_rays(K_bytes: bytes, width: int, height: int, model: str, dist: tuple) -> np.ndarray:
    """(H, W, 3) float64 unit rays through the pixel centres of a lens model, 0 where uncovered (read-only)."""
    K = np.frombuffer(K_bytes, dtype=np.float64).reshape(3, 3)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    rays, _ = unproject_lens(model, dist, lens_limit(model, dist), K, np.stack([u.ravel(), v.ravel()], 1))
    d = np.ascontiguousarray(rays.reshape(height, width, 3))
    d.setflags(write=False)
    return d


@register("camera.ray_grid")
@functools.lru_cache(maxsize=16)
def _ray_grid(K_bytes: bytes, width: int, height: int, model: str, dist: tuple, pad: int) -> np.ndarray:
    """``Camera.ray_grid``: the pixel rays (cached) framed by a ring of ``pad`` unprojected pixel centres."""
    K = np.frombuffer(K_bytes, dtype=np.float64).reshape(3, 3)
    inner = (_pixel_rays(K_bytes, width, height) if model == "pinhole"
             else _lens_rays(K_bytes, width, height, model, dist))
    v, u = np.mgrid[-pad:height + pad, -pad:width + pad].astype(np.float64)
    ring = np.ones(v.shape, bool)
    ring[pad:-pad, pad:-pad] = False
    uv = np.stack([u[ring], v[ring]], 1)
    if model == "pinhole":
        d = np.concatenate([uv, np.ones((len(uv), 1))], 1) @ np.linalg.inv(K).T
        rays = d / np.linalg.norm(d, axis=1, keepdims=True)
    else:
        rays, _ = unproject_lens(model, dist, lens_limit(model, dist), K, uv)
    out = np.zeros(v.shape + (3,))
    out[ring] = rays
    out[pad:-pad, pad:-pad] = inner
    out.setflags(write=False)
    return out
