"""Platform poses of a moving station: validated samples and an interpolating buffer.

Positions ENU, m; orientations unit quaternions (x, y, z, w) body to world (REP-103);
stamps integer ns. Re-exported from :mod:`.station`.
"""

from dataclasses import dataclass, field
import math

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from .readings import QUATERNION_NORM_TOL, ReadingError


@dataclass
class PoseSample:
    """A platform pose at one instant (from nav_msgs/Odometry).

    Attributes:
        stamp_ns: integer ns.
        position: (3,) body origin in the world frame, m.
        quaternion: (4,) unit quaternion (x, y, z, w) rotating body vectors into the world.
        position_covariance: (3, 3) m².
    """

    stamp_ns: int
    position: np.ndarray
    quaternion: np.ndarray
    position_covariance: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))


def pose_sample(stamp_ns, position, quaternion, position_covariance=None):
    """Validated :class:`PoseSample` (quaternion normalised).

    Rejections (:class:`ReadingError`): ``odometry_bad_stamp``, ``odometry_bad_position``
    (non-finite), ``odometry_bad_quaternion`` (NaN or |q| not within 1e-3 of 1),
    ``odometry_bad_covariance`` (non-finite or negative variances).
    """
    stamp_ns = int(stamp_ns)
    if stamp_ns <= 0:
        raise ReadingError('odometry_bad_stamp', f'stamp {stamp_ns} ns')
    p = np.asarray(position, dtype=float).reshape(3)
    if not np.all(np.isfinite(p)):
        raise ReadingError('odometry_bad_position', 'non-finite position')
    q = np.asarray(quaternion, dtype=float).reshape(4)
    n = math.hypot(*q.tolist())  # no overflow warning for |q| near 1e308
    if not math.isfinite(n) or abs(n - 1.0) > QUATERNION_NORM_TOL:
        raise ReadingError('odometry_bad_quaternion', f'quaternion norm {n:.6g} is not 1')
    cov = np.zeros((3, 3)) if position_covariance is None else \
        np.asarray(position_covariance, dtype=float).reshape(3, 3)
    if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) < 0.0):
        raise ReadingError('odometry_bad_covariance', 'non-finite or negative variance')
    return PoseSample(stamp_ns, p, q / n, cov)


#: Default largest gap between the two poses a reading is interpolated between, ns (2 s: a
#: 1 Hz odometry source with a late message still passes).
MAX_GAP_NS = 2_000_000_000
#: Default clock jump, ns: an odometry stamp more than this before the newest pose means the
#: clock went back (a restarted bag) and clears the buffer; a less late one is dropped.
JUMP_NS = 1_000_000_000


class PoseBuffer:
    """A bounded, time-ordered buffer of platform poses, interpolated to bearing stamps.

    For t_i ≤ t ≤ t_{i+1}, with s = (t − t_i) / (t_{i+1} − t_i): position and position
    covariance are linear, p = (1 − s) p_i + s p_{i+1}; the orientation is the spherical
    linear interpolation (slerp, shortest arc) of q_i and q_{i+1}. Only across a gap
    t_{i+1} − t_i ≤ ``max_gap_ns``: over a longer outage the platform may have turned or
    stopped in ways no interpolation knows, and the reading is rejected (``odometry_gap``)
    unless it lies within ``tolerance_ns`` of one of the two poses (that pose is held).
    A stamp outside the buffered interval by at most ``tolerance_ns`` gets the nearest pose
    (held, never extrapolated); further out it is rejected (``before_odometry`` /
    ``after_odometry``; ``no_odometry`` when empty). At most ``maxlen`` poses are kept
    (oldest dropped).

    Time must increase: a duplicate stamp is ignored ('duplicate'); a stamp before the
    newest one by at most ``jump_ns`` is a late (reordered) message and is dropped ('late',
    the buffer is kept); one earlier by more means the clock jumped back (a bag replay
    restarted) and clears the buffer ('reset').
    """

    def __init__(self, maxlen=200, tolerance_ns=100_000_000, max_gap_ns=MAX_GAP_NS,
                 jump_ns=JUMP_NS):
        if int(maxlen) < 2:
            raise ValueError('maxlen: need at least 2 poses to interpolate')
        if int(tolerance_ns) < 0:
            raise ValueError('tolerance_ns: must be >= 0')
        if int(max_gap_ns) <= 0:
            raise ValueError('max_gap_ns: must be > 0')
        if int(jump_ns) < 0:
            raise ValueError('jump_ns: must be >= 0')
        self.maxlen = int(maxlen)
        self.tolerance_ns = int(tolerance_ns)
        self.max_gap_ns = int(max_gap_ns)
        self.jump_ns = int(jump_ns)
        self._samples = []

    def __len__(self):
        return len(self._samples)

    @property
    def interval(self):
        """(first, last) buffered stamps in ns, or None when empty."""
        if not self._samples:
            return None
        return self._samples[0].stamp_ns, self._samples[-1].stamp_ns

    def add(self, sample):
        """Append a :class:`PoseSample`; return 'ok', 'duplicate' (ignored), 'late'
        (ignored: at most ``jump_ns`` before the newest pose) or 'reset' (the clock jumped
        back by more: the buffer is cleared and holds this pose)."""
        status = 'ok'
        if self._samples:
            last = self._samples[-1].stamp_ns
            if sample.stamp_ns == last:
                return 'duplicate'
            if sample.stamp_ns < last:
                if last - sample.stamp_ns <= self.jump_ns:
                    return 'late'
                self._samples.clear()
                status = 'reset'
        self._samples.append(sample)
        if len(self._samples) > self.maxlen:
            del self._samples[0]
        return status

    def clear(self):
        """Drop every buffered pose."""
        self._samples.clear()

    def interpolate(self, stamp_ns):
        """Pose at ``stamp_ns`` (class docstring) or :class:`ReadingError`."""
        if not self._samples:
            raise ReadingError('no_odometry', 'no platform pose received yet')
        t = int(stamp_ns)
        first, last = self._samples[0], self._samples[-1]
        if t <= first.stamp_ns:
            if first.stamp_ns - t > self.tolerance_ns:
                raise ReadingError('before_odometry', f'{(first.stamp_ns - t) / 1e9:.3f} s '
                                                      'before the oldest buffered pose')
            return PoseSample(t, first.position.copy(), first.quaternion.copy(),
                              first.position_covariance.copy())
        if t >= last.stamp_ns:
            if t - last.stamp_ns > self.tolerance_ns:
                raise ReadingError('after_odometry', f'{(t - last.stamp_ns) / 1e9:.3f} s '
                                                     'after the newest buffered pose')
            return PoseSample(t, last.position.copy(), last.quaternion.copy(),
                              last.position_covariance.copy())
        stamps = np.array([s.stamp_ns for s in self._samples], dtype=np.int64)
        i = int(np.searchsorted(stamps, t, side='right')) - 1
        a, b = self._samples[i], self._samples[i + 1]
        gap = b.stamp_ns - a.stamp_ns
        if gap > self.max_gap_ns:
            # Within tolerance of one of the poses around the gap: that pose is held, as at
            # the ends of the buffer.
            near = a if t - a.stamp_ns <= b.stamp_ns - t else b
            if abs(t - near.stamp_ns) <= self.tolerance_ns:
                return PoseSample(t, near.position.copy(), near.quaternion.copy(),
                                  near.position_covariance.copy())
            raise ReadingError('odometry_gap', f'{gap / 1e9:.3f} s between the poses around '
                                               f'it (limit {self.max_gap_ns / 1e9:.3g} s)')
        s = (t - a.stamp_ns) / gap
        pos = (1.0 - s) * a.position + s * b.position
        cov = (1.0 - s) * a.position_covariance + s * b.position_covariance
        q = Slerp([0.0, 1.0], Rotation.from_quat([a.quaternion, b.quaternion]))(s).as_quat()
        return PoseSample(t, pos, q, cov)
