"""Recursive TMA sums over a sliding window for the fusion node (Lin et al. Table 1, (T13)).

Conventions as :mod:`bearing_loc_ros.core.tma`.
"""

from collections import deque

import numpy as np

from ..bearings import _check_bearing_fields, BearingSet
from ..conventions import los_vector
from ..fix import STATUS_OK
from .closed_form import estimate_from_sums
from .methods import _CLOSED_FORMS, tma_function
from .mle import _mle_start, _options, tma_mle
from .model import prepare, SPEED_REFERENCES
from .observability import finish
from .roots import resolve
from .sums import bearing_terms, TmaSums


class TmaAccumulator:
    """Recursive P, Ω (Lin et al. sec. 3.2.1, Table 1; (T13)) over a sliding time window.

    ``add`` costs O(1): it adds the bearing's terms (:func:`bearing_terms`) to the moments of
    :class:`TmaSums` and, when ``window`` (s) is set, subtracts the terms of bearings older
    than t − window. The moments are re-summed from the stored bearings whenever as many
    bearings have been evicted as remain (amortised O(1)), which bounds rounding drift and
    re-references τ to the window start. ``estimate`` solves ple/ctls from the sums in O(1)
    (plus an O(K) vectorised CRLB for the covariance) and runs mle on the stored window.

    Args:
        speed: prior speed v_c, m/s (T5). window: None (grow forever) or seconds (> 0).
        speed_reference: 'relative' (Lin et al.) or 'ground'. Further keyword options are
        passed to the estimators (see :func:`tma_ple`).
    """

    def __init__(self, speed, window=None, speed_reference='relative', **options):
        if not (np.isfinite(speed) and speed > 0):
            raise ValueError('speed: must be finite and > 0 (m/s)')
        if window is not None and not (np.isfinite(window) and window > 0):
            raise ValueError('window: must be None or finite and > 0 (s)')
        if speed_reference not in SPEED_REFERENCES:
            raise ValueError(f'speed_reference: expected one of {SPEED_REFERENCES}')
        _options(options)
        self.speed = float(speed)
        self.window = None if window is None else float(window)
        self.speed_reference = speed_reference
        self.options = options
        self.reset()

    def reset(self):
        """Forget every bearing."""
        self._entries = deque()
        self._evicted = 0
        self._sums = None

    def __len__(self):
        return len(self._entries)

    @property
    def t_last(self):
        """Time of the newest bearing (s) or None."""
        return self._entries[-1][0] if self._entries else None

    def add(self, t, observer, azimuth, elevation, sigma_azimuth, sigma_elevation):
        """Add one bearing (t s, observer (3,) m, ENU angles rad, σ rad); O(1).

        Raises ValueError naming the field for invalid values or a time older than the
        newest bearing (out of order: the caller decides whether to reset).
        """
        t = float(t)
        o = np.asarray(observer, dtype=float).reshape(-1)
        if not np.isfinite(t):
            raise ValueError('t: non-finite observation time')
        if o.shape != (3,):
            raise ValueError('observer: expected 3 coordinates')
        if elevation is None or not np.isfinite(elevation):
            raise ValueError('elevation: 3-D TMA needs azimuth and elevation on every bearing')
        _check_bearing_fields(o[None, None], np.array([[azimuth]], float),
                              np.array([[elevation]], float),
                              np.array([[sigma_azimuth]], float),
                              np.array([[sigma_elevation]], float))
        if self._entries and t < self._entries[-1][0]:
            raise ValueError(f't: bearing at {t!r} s is older than the newest one '
                             f'({self._entries[-1][0]!r} s)')
        Ph, Oh, Qh = bearing_terms(azimuth, elevation, sigma_azimuth, sigma_elevation)
        entry = (t, o, float(azimuth), float(elevation), float(sigma_azimuth),
                 float(sigma_elevation), Ph, Oh, Qh)
        self._entries.append(entry)
        if self._sums is None:
            self._rebuild()
        else:
            self._apply(entry, +1.0)
            self._sums.t_last = np.array(t)
            self._sums.o_last = o
        if self.window is not None:
            while self._entries[0][0] < t - self.window:
                self._apply(self._entries.popleft(), -1.0)
                self._evicted += 1
            if self._evicted:
                self._set_first()
            if self._evicted >= len(self._entries):
                self._rebuild()

    def _apply(self, entry, sign):
        s = self._sums
        t, o, Ph, Oh, Qh = entry[0], entry[1], entry[6], entry[7], entry[8]
        tau = t - float(s.t_ref)
        do = o - s.o_ref
        s.n = s.n + sign
        s.A0 = s.A0 + sign * Ph
        s.A1 = s.A1 + sign * tau * Ph
        s.A2 = s.A2 + sign * tau * tau * Ph
        s.B0 = s.B0 + sign * Oh
        s.B1 = s.B1 + sign * tau * Oh
        s.B2 = s.B2 + sign * tau * tau * Oh
        s.Q = s.Q + sign * Qh
        s.T1 = s.T1 + sign * tau
        s.T2 = s.T2 + sign * tau * tau
        s.O1 = s.O1 + sign * do
        s.TO = s.TO + sign * tau * do

    def _set_first(self):
        f = self._entries[0]
        s = self._sums
        s.t0 = np.array(f[0])
        s.e0 = los_vector(f[2], f[3])
        s.o0 = f[1]
        s.B_first = f[7]

    def _rebuild(self):
        f = self._entries[0]
        z3 = np.zeros((3, 3))
        self._sums = TmaSums(
            n=np.array(0.0), t_ref=np.array(f[0]), o_ref=f[1].copy(), t0=np.array(f[0]),
            e0=los_vector(f[2], f[3]), o0=f[1], B_first=f[7],
            t_last=np.array(self._entries[-1][0]), o_last=self._entries[-1][1],
            A0=z3, A1=z3, A2=z3, B0=z3, B1=z3, B2=z3, Q=z3, T1=np.array(0.0),
            T2=np.array(0.0), O1=np.zeros(3), TO=np.zeros(3))
        for entry in self._entries:
            self._apply(entry, +1.0)
        self._evicted = 0

    def sums(self):
        """The current :class:`TmaSums` with leading shape (1,) (a copy)."""
        s = self._sums
        return TmaSums(**{k: np.asarray(getattr(s, k))[None].copy()
                          for k in TmaSums.__dataclass_fields__})

    def paper_matrices(self):
        """The paper's P(k), Ω(k) (4, 4) for the current window (Lin et al. sec. 3.2.1)."""
        P, Om = self.sums().paper_matrices()
        return P[0], Om[0]

    def bearings(self):
        """The stored window as (BearingSet with M = 1, times (1, K))."""
        e = self._entries
        bs = BearingSet.from_arrays(np.array([x[1] for x in e]), np.array([x[2] for x in e]),
                                    np.array([x[3] for x in e]), np.array([x[4] for x in e]),
                                    np.array([x[5] for x in e]), validate=False)
        return bs, np.array([[x[0] for x in e]])

    def estimate(self, method='tma_ctls', speed=None, **options):
        """Estimate for the current window with TMA estimator ``method`` -> FixResult (M = 1).

        ``method``: ``tma_ple``, ``tma_ctls``, ``tma_ctls6`` or ``tma_mle``.

        ple/ctls come from the recursive sums in O(1) (the covariance, if requested, is an
        O(K) vectorised CRLB); mle starts from the recursive ctls (or ple) solution and
        iterates over the stored bearings. Raises ValueError when no bearing was added.
        """
        if not self._entries:
            raise ValueError('observations: no bearing added yet')
        opts = dict(self.options)
        opts.update(options)
        opts['speed_reference'] = self.speed_reference
        vc = self.speed if speed is None else float(speed)
        bs, times = self.bearings()
        fn = tma_function(method)
        fo = _options(opts, fn)
        data = prepare(bs, times, vc, self.speed_reference)
        sums = self.sums()
        if fn is tma_mle:
            p0, v, status, reason = _mle_start(data, sums, fo)
            if status[0] != STATUS_OK:
                return finish('mle', data, p0, v, status, reason, np.zeros(1, int),
                              np.zeros(1, bool), fo)
            return tma_mle(bs, times, vc, start=(p0, v), **opts)
        method = _CLOSED_FORMS[fn]
        p0, v, status, reason = estimate_from_sums(sums, method, np.array([vc]),
                                                   self.speed_reference, fo['min_bearings'],
                                                   fo['alpha'])
        p0, v, status, reason, _ = resolve(data, p0, v, status, reason, status == STATUS_OK,
                                           self.speed_reference)
        return finish(method, data, p0, v, status, reason, np.zeros(1, int),
                      status == STATUS_OK, fo)
