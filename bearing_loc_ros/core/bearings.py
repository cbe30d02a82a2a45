"""Bearing measurements: one stamped bearing, and batches of N bearings for M problems.

Conventions (DESIGN.md): ENU world frame, metres, radians; azimuth θ CCW from East,
elevation ψ above the horizontal plane; an azimuth-only (1D) bearing has elevation NaN and
σ_el NaN. Wang, Zhang & Wu (2006) eq. (1) and Wang, Su, Bai & Zhong (2009) (mixed 1D/2D
sensors) define the measurement model

    θ_i = atan2(y − y_i, x − x_i) + n_i,   ψ_i = atan2(z − z_i, ρ_i) + m_i,

with n_i ~ N(0, σ_θi²), m_i ~ N(0, σ_ψi²) independent, ρ_i the horizontal range.
"""

from dataclasses import dataclass, field
import math

import numpy as np

HALF_PI = np.pi / 2.0
#: Largest |elevation| a simulated bearing carries, rad (a Bearing requires |ψ| < π/2): the
#: clip of :func:`simulate_bearings`, of the simulator and of core.evaluation.
MAX_ELEVATION = HALF_PI - 1e-9
#: Accepted range of an angle σ, rad. Below 1e-12 rad (a picoradian, far below any sensor)
#: the weights 1/σ² and their products overflow float64 in the estimators' sums (σ = 1e-300
#: made TMA's eigen-solver fail); the upper bound only keeps σ² r² finite (a σ above π
#: already carries no information, and range-grown σ of Zong & Cui (2015) eqs. (9)-(10) may
#: exceed it).
SIGMA_MIN = 1e-12
SIGMA_MAX = 1e3
#: Largest |azimuth|, rad (about 1592 turns). Wrapping a larger angle into (−π, π] keeps
#: fewer digits: the spacing of doubles near 1e4 is 1.8e-12 rad, near 1e9 it is 1.2e-7 rad
#: and near 1e16 it is 2 rad, so such a value says nothing about the direction.
MAX_ABS_ANGLE = 1.0e4
#: Largest |station coordinate|, m (a thousand times the Earth-Moon distance); beyond it the
#: estimators' squared ranges overflow float64 in intermediate sums.
MAX_ABS_POSITION = 1.0e12


@dataclass
class Bearing:
    """One stamped bearing from one station (the core twin of the ROS bearing message).

    Attributes:
        station: station id (the topic namespace, for example ``station_1``).
        stamp_ns: observation time, integer nanoseconds on the node (ROS) clock.
        position: station phase-centre position (3,), m, world frame.
        azimuth: θ, rad, ENU (CCW from East).
        elevation: ψ, rad, or NaN for an azimuth-only (1D) station.
        sigma_azimuth: σ_θ, rad (> 0).
        sigma_elevation: σ_ψ, rad (> 0), or NaN for a 1D station.
        frame_id: world frame the ray is expressed in.
        position_covariance: (3, 3) station position covariance, m².
    """

    station: str
    stamp_ns: int
    position: np.ndarray
    azimuth: float
    elevation: float = float('nan')
    sigma_azimuth: float = 0.01
    sigma_elevation: float = float('nan')
    frame_id: str = 'map'
    position_covariance: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))

    @property
    def has_elevation(self):
        """True for a 2D (azimuth + elevation) bearing."""
        return bool(np.isfinite(self.elevation))

    def validate(self):
        """Raise ``ValueError`` naming the first bad field; return self when valid."""
        if _scalar_fields_valid(self):
            return self
        pos = _as_float_array(self.position, 'position')
        if pos.ndim == 0:
            raise ValueError('position: expected 3 coordinates, got a scalar')
        _check_bearing_fields(
            pos[None, None, :],
            *(_as_float_array(getattr(self, name), name).reshape(1, 1)
              for name in ('azimuth', 'elevation', 'sigma_azimuth', 'sigma_elevation')))
        return self


def _as_float_array(value, name):
    """``value`` as a float array; ValueError naming ``name`` when it is not numeric."""
    try:
        out = np.asarray(value, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f'{name}: not a number ({type(value).__name__})') from None
    if name != 'position' and out.size != 1:
        raise ValueError(f'{name}: expected one number, got shape {out.shape}')
    return out


@dataclass
class BearingSet:
    """N bearings for each of M independent problems (batch-first, DESIGN.md).

    Attributes (arrays):
        positions: (M, N, 3) station positions, m.
        azimuth: (M, N) θ, rad.
        elevation: (M, N) ψ, rad; NaN marks an azimuth-only (1D) bearing.
        sigma_az: (M, N) σ_θ, rad.
        sigma_el: (M, N) σ_ψ, rad; NaN where elevation is NaN.
        stations: optional list of N station ids (shared by all M problems).

    Use :meth:`from_arrays` to build one from (N, ...) or (M, N, ...) arrays; it validates.
    """

    # Fields and size properties: alike other batch containers (planning layouts,
    # horizontal problems) in shape only, each holds its own arrays.
    positions: np.ndarray
    azimuth: np.ndarray
    elevation: np.ndarray
    sigma_az: np.ndarray
    sigma_el: np.ndarray
    stations: list = None

    @property
    def M(self):
        """Number of problems in the batch."""
        return self.azimuth.shape[0]

    @property
    def N(self):
        """Number of bearings per problem."""
        return self.azimuth.shape[1]

    @property
    def has_elevation(self):
        """(M, N) bool: True where the bearing carries an elevation (2D station)."""
        return np.isfinite(self.elevation)

    @classmethod
    def from_arrays(cls, positions, azimuth, elevation=None, sigma_az=None, sigma_el=None,
                    stations=None, validate=True, require_elevation=True):
        """Build a batch from arrays shaped (N, ...) (one problem) or (M, N, ...).

        ``elevation`` None means every bearing is azimuth-only. ``sigma_az``/``sigma_el`` may be
        scalars or broadcastable arrays (rad); ``sigma_el`` is forced to NaN where elevation is
        NaN. With ``validate`` (default) the batch is checked by :meth:`validate`
        (``require_elevation`` passed on; False for azimuth-only sets of a horizontal solve).
        """
        pos = np.asarray(positions, dtype=float)
        az = np.asarray(azimuth, dtype=float)
        if pos.ndim == 2:
            pos = pos[None]
        if az.ndim == 1:
            az = az[None]
        if pos.ndim != 3 or pos.shape[-1] != 3:
            raise ValueError(f'positions: expected shape (N, 3) or (M, N, 3), got {pos.shape}')
        if az.ndim != 2:
            raise ValueError(f'azimuth: expected shape (N,) or (M, N), got {az.shape}')
        M = max(pos.shape[0], az.shape[0])
        N = pos.shape[1]
        try:
            pos = np.broadcast_to(pos, (M, N, 3)).copy()
            az = np.broadcast_to(az, (M, N)).copy()
            el = np.broadcast_to(np.asarray(np.nan if elevation is None else elevation,
                                            dtype=float), (M, N)).copy()
            saz = np.broadcast_to(np.asarray(0.01 if sigma_az is None else sigma_az,
                                             dtype=float), (M, N)).copy()
            sel = np.broadcast_to(np.asarray(np.nan if sigma_el is None else sigma_el,
                                             dtype=float), (M, N)).copy()
        except ValueError as exc:
            raise ValueError(f'bearings: inconsistent array shapes ({exc})') from None
        sel = np.where(np.isfinite(el), sel, np.nan)
        out = cls(pos, az, el, saz, sel, list(stations) if stations is not None else None)
        if validate:
            out.validate(require_elevation)
        return out

    @classmethod
    def from_bearings(cls, bearings, validate=True):
        """Build a one-problem batch (M = 1) from a sequence of :class:`Bearing`."""
        bearings = list(bearings)
        if not bearings:
            raise ValueError('bearings: empty set (need at least two stations)')
        return cls.from_arrays(
            np.array([b.position for b in bearings], dtype=float),
            np.array([b.azimuth for b in bearings], dtype=float),
            np.array([b.elevation for b in bearings], dtype=float),
            np.array([b.sigma_azimuth for b in bearings], dtype=float),
            np.array([b.sigma_elevation for b in bearings], dtype=float),
            stations=[b.station for b in bearings], validate=validate)

    def subset(self, mask):
        """Return the bearings selected by the (N,) boolean or index array ``mask``."""
        idx = np.arange(self.N)[mask]
        st = None if self.stations is None else [self.stations[i] for i in idx]
        return BearingSet(self.positions[:, idx], self.azimuth[:, idx], self.elevation[:, idx],
                          self.sigma_az[:, idx], self.sigma_el[:, idx], st)

    def problem(self, m):
        """Return problem ``m`` of the batch as a one-problem BearingSet (M = 1)."""
        sl = slice(m, m + 1)
        return BearingSet(self.positions[sl], self.azimuth[sl], self.elevation[sl],
                          self.sigma_az[sl], self.sigma_el[sl], self.stations)

    def validate(self, require_elevation=True):
        """Check every field; raise ``ValueError`` naming the bad field. Returns self.

        Field rules: finite positions (|coordinate| ≤ 1e12 m) and azimuths (|θ| ≤ 1e4 rad,
        :data:`MAX_ABS_ANGLE`); elevation finite or NaN (1D) with
        |ψ| < π/2; σ_θ in [SIGMA_MIN, SIGMA_MAX] = [1e-12, 1e3] rad; σ_ψ in that range wherever
        elevation is given; at least two bearings. With ``require_elevation`` (the 3D solve,
        default) also at least three independent scalar constraints with at least one
        elevation (azimuths alone never fix the height: Wang, Su, Bai & Zhong 2009 need one 2D
        sensor); False (the horizontal solve, core.horizontal) checks the fields only.
        """
        if require_elevation and _one_problem_valid(self):
            return self
        _check_bearing_fields(self.positions, self.azimuth, self.elevation, self.sigma_az,
                              self.sigma_el)
        if self.N < 2:
            what = 'a 3D fix' if require_elevation else 'a fix'
            raise ValueError(f'bearings: {self.N} station(s); {what} needs at least two')
        if not require_elevation:
            return self
        n_el = np.sum(self.has_elevation, axis=1)
        if np.any(n_el == 0):
            raise ValueError('elevation: no bearing measures elevation; azimuths alone cannot '
                             'fix the height (need at least one 2D station)')
        if np.any(self.N + n_el < 3):
            raise ValueError('bearings: fewer than three independent angle measurements')
        return self


def _scalar_fields_valid(b):
    """Fast path of :meth:`Bearing.validate` (~1 µs instead of ~40 µs, per-message use).

    True only when the bearing certainly passes :func:`_check_bearing_fields` (same rules on
    Python floats: finite position of 3 coordinates and azimuth, σ_θ finite > 0, elevation NaN
    or finite with |ψ| < π/2 and then σ_ψ finite > 0); anything else (a bad field, another
    shape, another number type) returns False and goes through the full check, which names
    the field.
    """
    p = b.position
    if type(p) is np.ndarray:
        if p.shape != (3,):
            return False
        p = p.tolist()
    elif not isinstance(p, (list, tuple)) or len(p) != 3:
        return False
    values = (*p, b.azimuth, b.elevation, b.sigma_azimuth, b.sigma_elevation)
    if not all(isinstance(v, (float, int)) and not isinstance(v, bool) for v in values):
        return False
    try:
        x, y, z, az, el, saz, sel = (float(v) for v in values)
    except OverflowError:
        return False
    # Each value compared on its own: NaN fails every comparison (max() would skip it).
    if not (abs(x) <= MAX_ABS_POSITION and abs(y) <= MAX_ABS_POSITION
            and abs(z) <= MAX_ABS_POSITION and abs(az) <= MAX_ABS_ANGLE
            and SIGMA_MIN <= saz <= SIGMA_MAX):
        return False
    if math.isnan(el):
        return True
    return math.isfinite(el) and abs(el) < HALF_PI and SIGMA_MIN <= sel <= SIGMA_MAX


def _one_problem_valid(bs):
    """Fast path of :meth:`BearingSet.validate` for one problem of float arrays (M = 1).

    The same rules on Python floats (~3 µs at N = 10 instead of ~40 µs: one fix at a time is
    the fusion node's and ``bearing_loc locate``'s case, bench/bench_estimators.py). True only
    when the set certainly passes; anything else returns False and goes through the full
    check, which names the bad field.
    """
    arrays = (bs.positions, bs.azimuth, bs.elevation, bs.sigma_az, bs.sigma_el)
    if not all(type(a) is np.ndarray and a.dtype == np.float64 for a in arrays):
        return False
    N = bs.azimuth.shape[-1]
    if bs.positions.shape != (1, N, 3) or any(a.shape != (1, N) for a in arrays[1:]) or N < 2:
        return False
    # Bounded positions and azimuths (NaN fails every comparison and takes the full check).
    if not (all(abs(v) <= MAX_ABS_POSITION for v in bs.positions.ravel().tolist())
            and all(abs(v) <= MAX_ABS_ANGLE for v in bs.azimuth[0].tolist())):
        return False
    n_el = 0
    for el, saz, sel in zip(bs.elevation[0].tolist(), bs.sigma_az[0].tolist(),
                            bs.sigma_el[0].tolist()):
        if not SIGMA_MIN <= saz <= SIGMA_MAX:
            return False
        if el == el:                                    # not NaN: a 2D bearing
            if not (abs(el) < HALF_PI and SIGMA_MIN <= sel <= SIGMA_MAX):
                return False
            n_el += 1
    return n_el > 0 and N + n_el >= 3


def _check_bearing_fields(pos, az, el, saz, sel):
    """Shared field checks for :class:`Bearing` and :class:`BearingSet` (ValueError)."""
    if not np.all(np.isfinite(pos)):
        raise ValueError('position: non-finite station coordinate')
    if not np.all(np.abs(pos) <= MAX_ABS_POSITION):
        raise ValueError(f'position: |coordinate| must be <= {MAX_ABS_POSITION:g} m')
    if not np.all(np.isfinite(az)):
        raise ValueError('azimuth: non-finite value')
    if not np.all(np.abs(az) <= MAX_ABS_ANGLE):
        raise ValueError(f'azimuth: |azimuth| must be <= {MAX_ABS_ANGLE:g} rad')
    if np.any(np.isinf(el)):
        raise ValueError('elevation: infinite value (use NaN/null for azimuth-only bearings)')
    has_el = np.isfinite(el)
    if np.any(np.abs(el[has_el]) >= HALF_PI):
        raise ValueError('elevation: |elevation| must be < pi/2')
    if not np.all((saz >= SIGMA_MIN) & (saz <= SIGMA_MAX)):
        raise ValueError(f'sigma_azimuth: must be finite and in [{SIGMA_MIN:g}, {SIGMA_MAX:g}] '
                         'rad')
    sel_given = sel[has_el]
    if not np.all((sel_given >= SIGMA_MIN) & (sel_given <= SIGMA_MAX)):
        raise ValueError(f'sigma_elevation: must be finite and in [{SIGMA_MIN:g}, '
                         f'{SIGMA_MAX:g}] rad where elevation is measured')


def simulate_bearings(target, positions, sigma_az, sigma_el=None, has_elevation=True, rng=None,
                      require_elevation=True):
    """Noisy bearings from stations ``positions`` (N, 3) to target(s) ``target`` (M, 3) or (3,).

    Model of Wang, Zhang & Wu eq. (1) with additive Gaussian noise eq. (6): θ_i = θ_i* + n_i,
    ψ_i = clip(ψ_i* + m_i, ±:data:`MAX_ELEVATION`), MAX_ELEVATION = π/2 − 1e-9 rad (the rule
    of the simulator and of core.evaluation): near the zenith a Gaussian draw can cross
    ±π/2, and a bearing needs |ψ| < π/2; the clipped ψ is a valid bearing, its distribution
    the Gaussian with the tails beyond ±90° moved onto ±90° (a target exactly overhead,
    noise-free, gets ψ = MAX_ELEVATION). The draws do not change: a set that needed no
    clipping is the same as before. ``sigma_az``/``sigma_el`` are
    scalars or (N,)/(M, N) arrays (rad); ``has_elevation`` a bool or (N,) bool mask
    (False = 1D station). ``rng`` a numpy Generator (None: noise-free). Returns a validated
    :class:`BearingSet` with M problems (``require_elevation=False``: field checks only,
    azimuth-only sets allowed).
    """
    from .conventions import azimuth_elevation, wrap_angle
    tgt = np.atleast_2d(np.asarray(target, dtype=float))
    pos = np.asarray(positions, dtype=float)
    if pos.ndim == 2:
        pos = pos[None]
    M = tgt.shape[0]
    pos = np.broadcast_to(pos, (M,) + pos.shape[1:])
    N = pos.shape[1]
    az, el = azimuth_elevation(tgt[:, None, :] - pos)
    saz = np.broadcast_to(np.asarray(sigma_az, dtype=float), (M, N))
    sel = np.broadcast_to(np.asarray(saz if sigma_el is None else sigma_el, dtype=float), (M, N))
    if rng is not None:
        az = az + saz * rng.standard_normal((M, N))
        el = el + sel * rng.standard_normal((M, N))
    el = np.clip(el, -MAX_ELEVATION, MAX_ELEVATION)
    mask = np.broadcast_to(np.asarray(has_elevation, dtype=bool), (N,))
    el = np.where(mask[None, :], el, np.nan)
    return BearingSet.from_arrays(pos, wrap_angle(az), el, saz, sel,
                                  require_elevation=require_elevation)
