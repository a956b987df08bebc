"""Lens, blur and aperture descriptions, and the thin-lens mapping between them.

Conventions (docs/conventions.md):

* Disparity ``d`` is in [0, 1], 1 = nearest, 0 = farthest (or infinitely far).
* The circle-of-confusion (CoC) radius in pixels is ``r = K * |d - d_f|``
  (paper eq. 3, BokehMe convention); the signed defocus ``K * (d - d_f)`` is
  positive in front of the focal plane.
* A metric depth map ``z`` (metres) maps to disparity by the explicit
  normalisation ``d = (1/z - 1/z_far) / (1/z_near - 1/z_far)``
  (:class:`DepthNormalization`). ``z_far = inf`` is allowed (sky).
* A physical thin lens (focal length, f-number, focus distance, sensor width)
  maps to ``(K, d_f)`` through the textbook thin-lens CoC
  ``c = A * f / (z_f - f) * z_f * |1/z - 1/z_f|`` (diameter on the sensor,
  ``A = f / N``), divided by two and by the pixel pitch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .formats import first_index
from .validate import fits_in_memory, number_text, real, shown

MAX_K_PX = 1.0e5
"""Largest K accepted: a CoC of 100 000 px is beyond any image; larger values only exhaust memory."""

DEPTH_BYTES_PER_PX = 56
"""Peak bytes per pixel of :func:`disparity_from_depth` beyond its input (47 measured with tracemalloc on a float64
map: the float64 copy, the masks, the normalisation's temporaries), with a margin."""

__all__ = ["MAX_K_PX", "Aperture", "BlurParams", "DepthNormalization", "ThinLens", "aperture_area", "depth_from_disparity", "disparity_from_depth"]


def _finite(name: str, value: float, *, lo: float | None = None, lo_open: bool = False) -> float:
    # a real number only: True, "4" or None are mistakes, not 1.0, 4.0 or an error from float(); 10**400 too
    v = real(value, name)
    if lo is not None and (v < lo or (lo_open and v == lo)):
        raise InputError(f"{name}: expected a value {'>' if lo_open else '>='} {lo:g}, got {number_text(v)}")
    return v


@dataclass(frozen=True, slots=True)
class BlurParams:
    """Blur strength ``K`` (pixels per unit disparity) and focus disparity ``d_f``.

    The CoC radius of a pixel with disparity ``d`` is ``K * |d - d_f|`` pixels.
    """

    k_px: float
    focus_disparity: float

    def __post_init__(self) -> None:
        k = _finite("K (blur)", self.k_px, lo=0.0)
        if k > MAX_K_PX:
            raise InputError(f"K (blur): expected at most {MAX_K_PX:g} px per unit disparity, got {number_text(k)}")
        f = _finite("focus disparity", self.focus_disparity)
        if not 0.0 <= f <= 1.0:
            raise InputError(f"focus disparity: expected a value in [0, 1] (1 = nearest), got {number_text(f)}")
        # + 0.0: a negative zero (-0 given for either) is 0, not "-0.000" in every line, stats and JSON after it
        object.__setattr__(self, "k_px", k + 0.0)
        object.__setattr__(self, "focus_disparity", f + 0.0)

    def signed_coc(self, disparity: np.ndarray) -> np.ndarray:
        """Signed CoC radius ``K * (d - d_f)`` in pixels (> 0 in front of focus), float32."""
        return (np.float32(self.k_px) * (np.asarray(disparity, np.float32) - np.float32(self.focus_disparity))).astype(
            np.float32, copy=False  # float32 already: no second copy of the map
        )

    def coc_radius(self, disparity: np.ndarray) -> np.ndarray:
        """CoC radius ``K * |d - d_f|`` in pixels, float32."""
        return np.abs(self.signed_coc(disparity))


@dataclass(frozen=True, slots=True)
class Aperture:
    """Aperture shape: a disc, or a polygon with curved blades.

    Args:
        blades: number of diaphragm blades; 0 means a perfect disc, otherwise >= 3.
        rotation_deg: rotation of the polygon, degrees counter-clockwise (image y up).
        curvature: blade curvature in [0, 1]; 0 gives straight blades (a regular
            polygon inscribed in the CoC circle), 1 gives the circle itself. In
            between, each blade is a circular arc through two polygon vertices with
            radius ``R / curvature`` (R = CoC radius).

    Every shape is rescaled so that its kernel integrates to exactly 1 at every
    radius (see docs/renderer.md); the CoC radius is the circumradius.
    """

    blades: int = 0
    rotation_deg: float = 0.0
    curvature: float = 0.0

    def __post_init__(self) -> None:
        if isinstance(self.blades, bool) or not isinstance(self.blades, (int, np.integer)):
            raise InputError(f"aperture blades: expected an integer, got {self.blades!r}")
        if self.blades != 0 and not 3 <= self.blades <= 32:
            raise InputError(f"aperture blades: expected 0 (disc) or 3..32, got {shown(self.blades)}")
        _finite("aperture rotation", self.rotation_deg)
        c = _finite("aperture curvature", self.curvature)
        if not 0.0 <= c <= 1.0:
            raise InputError(f"aperture curvature: expected a value in [0, 1], got {number_text(c)}")
        object.__setattr__(self, "blades", int(self.blades))

    @property
    def is_disc(self) -> bool:
        return self.blades == 0 or self.curvature >= 1.0

    def vertical_extent(self) -> tuple[float, float]:
        """``(y_top, y_bottom)`` of the shape for a unit circumradius (y down), to 1e-5.

        The scatter needs it so that a flat blade edge cuts its last pixel row at
        the right height.
        """
        if self.is_disc:
            return -1.0, 1.0
        y = np.linspace(-1.0, 1.0, 200_001)
        lo, hi = self.chords(y)
        inside = np.flatnonzero(hi > lo)
        return float(y[inside[0]]) - 1e-5, float(y[inside[-1]]) + 1e-5

    def chords(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The shape's chord ``[lo, hi]`` at heights ``y`` (unit circumradius; ``hi <= lo`` where the row misses
        it), in float64: the NumPy form of ``bokehray_kernels.aperture.chord``."""
        y = np.asarray(y, np.float64)
        lo = -np.sqrt(np.maximum(1.0 - y * y, 0.0))
        hi = -lo
        for nx, ny, h, big_r in self.blade_discs().astype(np.float64):
            if big_r == 0.0:
                rhs = h - ny * y
                if nx > 1e-7:
                    hi = np.minimum(hi, rhs / nx)
                elif nx < -1e-7:
                    lo = np.maximum(lo, rhs / nx)
                else:
                    hi = np.where(rhs < 0, lo, hi)
            else:
                q = big_r * big_r - (y - h * ny) ** 2
                sq = np.sqrt(np.maximum(q, 0.0))
                lo = np.where(q > 0, np.maximum(lo, h * nx - sq), hi)
                hi = np.where(q > 0, np.minimum(hi, h * nx + sq), lo)
        return lo, hi

    def blade_discs(self) -> np.ndarray:
        """The shape as an intersection of constraints, for a unit circumradius.

        Returns an ``(n, 4)`` float32 array, one row per blade, ``(nx, ny, h, R)``:
        with ``R == 0`` the half-plane ``nx*x + ny*y <= h``; with ``R > 0`` the
        disc of radius ``R`` centred at ``(h_c * nx, h_c * ny)`` where
        ``h_c = h`` (stored in the third column). A disc aperture has zero rows.
        Image coordinates: x right, y down; rotation is counter-clockwise on screen.
        """
        if self.is_disc:
            return np.zeros((0, 4), np.float32)
        n = self.blades
        rows = []
        apothem = math.cos(math.pi / n)
        for i in range(n):
            theta = math.radians(self.rotation_deg) + (i + 0.5) * 2.0 * math.pi / n
            nx, ny = math.cos(theta), -math.sin(theta)  # screen y points down
            if self.curvature < 1e-4:  # sagitta < 1e-4 of the radius: straight
                rows.append((nx, ny, apothem, 0.0))
            else:
                big_r = 1.0 / self.curvature
                # centre at -t * n so that the arc passes through both vertices (|v| = 1)
                t = -apothem + math.sqrt(apothem * apothem - 1.0 + big_r * big_r)
                rows.append((nx, ny, -t, big_r))
        return np.asarray(rows, np.float32)


@dataclass(frozen=True, slots=True)
class DepthNormalization:
    """Depth (metres, along the optical axis) to disparity in [0, 1].

    ``d = (1/z - 1/z_far) / (1/z_near - 1/z_far)``; ``z_far`` may be ``inf``.
    """

    z_near_m: float
    z_far_m: float = math.inf

    def __post_init__(self) -> None:
        zn = _finite("z_near", self.z_near_m, lo=0.0, lo_open=True)
        zf = real(self.z_far_m, "z_far", inf=True)
        if zf <= zn:
            raise InputError(f"z_far: expected a value > z_near = {zn:g} (inf allowed), got {number_text(zf)}")
        object.__setattr__(self, "z_near_m", zn)
        object.__setattr__(self, "z_far_m", zf)

    @property
    def inv_span(self) -> float:
        """``1/z_near - 1/z_far`` in 1/metres."""
        return 1.0 / self.z_near_m - 1.0 / self.z_far_m

    @classmethod
    def from_depth(cls, depth_m: np.ndarray) -> DepthNormalization:
        """Min-max normalisation over a depth map (what the path-traced dev set uses)."""
        z = np.asarray(depth_m, np.float64)
        zn, zf = float(z.min()), float(z.max())
        if zf <= zn:
            zf = math.inf
        return cls(zn, zf)

    def disparity(self, depth_m: np.ndarray | float) -> np.ndarray:
        z = np.asarray(depth_m, np.float64)
        d = (1.0 / z - 1.0 / self.z_far_m) / self.inv_span
        return np.clip(d, 0.0, 1.0).astype(np.float32)

    def depth(self, disparity: np.ndarray | float) -> np.ndarray:
        d = np.asarray(disparity, np.float64)
        inv = d * self.inv_span + 1.0 / self.z_far_m
        with np.errstate(divide="ignore"):
            return np.where(inv > 0, 1.0 / np.maximum(inv, 1e-300), np.inf)


DEPTH_RANGE_TOLERANCE = 1e-6
"""Relative slack of the check that a depth map lies within a given normalisation: a float32 map whose nearest
value is 1.4 holds 1.39999998, which ``--z-near 1.4`` must accept (the normalisation clips that rounding)."""


def check_depth_range(lo: float, hi: float, norm: DepthNormalization, source: str,
                      names: tuple[str, str] = ("z_near", "z_far")) -> None:
    """Refuse a normalisation narrower than the map's nearest and farthest finite depths ``lo``, ``hi`` (metres):
    clipping them would render the depths beyond it at the wrong blur, silently. ``names``: what to call the two
    ends (the CLI's flags)."""
    if lo < norm.z_near_m * (1.0 - DEPTH_RANGE_TOLERANCE):
        raise InputError(f"{source}: depth reaches {lo:.4g} m, nearer than {names[0]} {norm.z_near_m:g} m; lower "
                         f"{names[0]} or leave it out (default: the map's nearest depth)")
    if hi > norm.z_far_m * (1.0 + DEPTH_RANGE_TOLERANCE):
        raise InputError(f"{source}: depth reaches {hi:.4g} m, farther than {names[1]} {norm.z_far_m:g} m; raise "
                         f"{names[1]} (inf allowed) or leave it out (default: the map's farthest depth)")


def check_focus_in_range(focus_m: float, norm: DepthNormalization, what: str = "focus_distance_m",
                         names: tuple[str, str] = ("z_near", "z_far")) -> None:
    """Refuse a focus distance outside ``norm``'s depth range (disparity [0, 1] cannot place it), saying how to
    widen the range; ``what`` and ``names``: what to call the distance and the range's ends (the CLI's flags)."""
    raw = (1.0 / focus_m - 1.0 / norm.z_far_m) / norm.inv_span
    if 0.0 <= raw <= 1.0:
        return
    span = f"the depth range [{norm.z_near_m:g}, {norm.z_far_m:g}] m of the disparity normalisation"
    if raw < 0.0:
        raise InputError(f"{what}: {focus_m:g} m lies beyond {span}; widen it with {names[1]} inf (or a "
                         f"{names[1]} of at least {focus_m:g})")
    raise InputError(f"{what}: {focus_m:g} m lies nearer than {span}; widen it with a {names[0]} of at most "
                     f"{focus_m:g}")


def disparity_from_depth(depth_m: np.ndarray, norm: DepthNormalization | None = None, *,
                         source: str = "depth", names: tuple[str, str] = ("z_near", "z_far"),
                         ) -> tuple[np.ndarray, DepthNormalization]:
    """Convert a metric depth map to normalised disparity; returns ``(d, norm)``.

    The one converter of the API and the CLI. Missing depth, <= 0 (no measurement: depth cameras write 0) and
    +/-inf (sky), is infinitely far: disparity 0 (with a finite ``z_far``, the far end of ``norm``). NaN is refused,
    and so is a map with no depth at all; messages start with ``source``. Without ``norm`` the map's own nearest and
    farthest finite depths span [0, 1] (the far end at infinity when any pixel is missing); a ``norm`` narrower than
    the map's finite depths is refused, naming its ends as ``names`` (clipping would blur them wrongly).
    """
    if np.ndim(depth_m) == 2:  # from the shape, before the float64 copy and its temporaries are made
        fits_in_memory(np.shape(depth_m), DEPTH_BYTES_PER_PX, f"{source}: the conversion to disparity")
    z = np.asarray(depth_m, np.float64)
    if z.ndim != 2:
        raise InputError(f"{source}: expected an H x W map, got shape {z.shape}")
    nan = np.isnan(z)
    if nan.any():
        y, x = first_index(nan)
        raise InputError(f"{source}: expected depth in metres, got NaN at (y, x) = ({y}, {x})")
    missing = ~np.isfinite(z) | (z <= 0)
    if missing.all():
        raise InputError(f"{source}: no pixel has a depth (every value is 0, negative or infinite)")
    if norm is not None and not isinstance(norm, DepthNormalization):
        raise InputError(f"{source}: expected a bokehray.DepthNormalization, got {type(norm).__name__}")
    z = np.where(missing, np.inf, z)
    finite = z[~missing]
    lo, hi = float(finite.min()), float(finite.max())
    if norm is not None:
        check_depth_range(lo, hi, norm, source, names)
    else:
        zf = math.inf if missing.any() else hi
        norm = DepthNormalization(lo, zf if zf > lo else math.inf)
    return norm.disparity(z), norm


def depth_from_disparity(disparity: np.ndarray, norm: DepthNormalization) -> np.ndarray:
    """Inverse of :func:`disparity_from_depth` (metres; ``inf`` where ``d`` maps to infinity)."""
    return norm.depth(disparity)


@dataclass(frozen=True, slots=True)
class ThinLens:
    """A physical thin lens.

    Args:
        focal_length_mm: focal length f in millimetres.
        f_number: N, so the aperture diameter is ``f / N``.
        focus_distance_m: distance of the in-focus plane from the lens, metres (> f).
        sensor_width_mm: width of the sensor that the image spans (36 mm = full frame).
    """

    focal_length_mm: float
    f_number: float
    focus_distance_m: float
    sensor_width_mm: float = 36.0

    def __post_init__(self) -> None:
        for name in ("focal_length_mm", "f_number", "focus_distance_m", "sensor_width_mm"):
            _finite(name, getattr(self, name), lo=0.0, lo_open=True)
        if self.focus_distance_m * 1e3 <= self.focal_length_mm:
            raise InputError(
                f"focus_distance_m: a thin lens cannot focus closer than its focal length "
                f"({self.focal_length_mm:g} mm), got {self.focus_distance_m:g} m"
            )

    def k_abs(self, width_px: int) -> float:
        """CoC radius in pixels per unit of ``|1/z - 1/z_f|`` (1/metres)."""
        f = self.focal_length_mm * 1e-3
        z_f = self.focus_distance_m
        pitch = self.sensor_width_mm * 1e-3 / int(width_px)
        aperture = f / self.f_number
        return aperture * f * z_f / (2.0 * (z_f - f) * pitch)

    def coc_radius_px(self, depth_m: np.ndarray | float, width_px: int) -> np.ndarray:
        """Thin-lens CoC radius in pixels of points at ``depth_m`` metres."""
        z = np.asarray(depth_m, np.float64)
        return self.k_abs(width_px) * np.abs(1.0 / z - 1.0 / self.focus_distance_m)

    def blur_params(self, norm: DepthNormalization, width_px: int) -> BlurParams:
        """``(K, d_f)`` for disparities normalised by ``norm`` in an image ``width_px`` wide."""
        check_focus_in_range(self.focus_distance_m, norm)
        d_f = float(norm.disparity(self.focus_distance_m))
        return BlurParams(self.k_abs(width_px) * norm.inv_span, d_f)

    @classmethod
    def from_blur_params(
        cls,
        blur: BlurParams,
        norm: DepthNormalization,
        width_px: int,
        *,
        focal_length_mm: float,
        sensor_width_mm: float = 36.0,
    ) -> ThinLens:
        """The lens (f-number, focus distance) that gives ``blur``: the inverse of :meth:`blur_params`."""
        inv_zf = blur.focus_disparity * norm.inv_span + 1.0 / norm.z_far_m
        if inv_zf <= 0:
            raise InputError("focus disparity 0 with z_far = inf means focus at infinity, which a finite lens cannot map")
        z_f = 1.0 / inv_zf
        f = focal_length_mm * 1e-3
        if z_f <= f:
            raise InputError(f"focus distance {z_f:g} m is closer than the focal length {focal_length_mm:g} mm")
        if blur.k_px <= 0:
            raise InputError("K = 0 is a pinhole: no finite f-number gives it")
        pitch = sensor_width_mm * 1e-3 / int(width_px)
        k_abs = blur.k_px / norm.inv_span
        aperture = k_abs * 2.0 * (z_f - f) * pitch / (f * z_f)
        return cls(focal_length_mm, f / aperture, z_f, sensor_width_mm)


def aperture_area(aperture: Aperture) -> float:
    """Area of the aperture at unit circumradius (the scatter's normalisation, docs/renderer.md).

    A disc is pi; N straight blades the inscribed regular polygon; curved blades add on each
    side the circular segment of radius 1 / curvature through the two vertices (that arc lies
    inside the unit circle, so the CoC disc does not clip it).
    """
    if aperture.is_disc:
        return math.pi
    n = aperture.blades
    poly = 0.5 * n * math.sin(2.0 * math.pi / n)
    if aperture.curvature < 1e-4:  # as Aperture.blade_discs: straight
        return poly
    big_r = 1.0 / aperture.curvature
    theta = 2.0 * math.asin(math.sin(math.pi / n) / big_r)
    return poly + n * 0.5 * big_r * big_r * (theta - math.sin(theta))
