"""Target motion analysis (TMA) from one moving station with a speed prior (Lin et al.).

One station (the observer) measures azimuth and elevation of a target over time. The target
moves at constant velocity; the prior speed v_c fixes the scale that bearings alone leave
free. Equation numbers (T1)...(T23) refer to docs/tma.md, which derives
them from the text of Lin et al. (its formulas did not survive in our copy).

Conventions (docs/conventions.md). ENU world frame, metres, seconds, radians. Azimuth θ is ENU
(counter-clockwise from East), elevation ψ above the horizontal plane. Lin et al. measure their
azimuth θ' clockwise from North (the y axis): θ' = π/2 − θ, converted at the boundary
(``conventions.compass_to_enu``; the CLI flag ``--compass``). Only one sign changes: the
paper's azimuth row p_x cos θ' − p_y sin θ' = 0 is −h_θ·p = 0 below, the elevation row and the
line-of-sight vector e = (cos φ sin θ', cos φ cos θ', sin φ) = u(θ, ψ) are the same.

Model (Lin et al. sec. 2, eq. (1)-(3)). Bearing k is taken at time t_k from observer position
o_k; τ_k = t_k − t_0 counts from the first bearing of the window.

(T1)  target:            p_T(t) = o_0 + p0 + (v + v_o) (t − t_0)
(T2)  observer velocity: v_o = least-squares slope of o_k against τ_k;
      manoeuvre:         δ_k = o_k − o_0 − v_o τ_k   (≡ 0 for a constant-velocity observer)
(T3)  relative position: p_k = p_T(t_k) − o_k = p0 + v τ_k − δ_k
(T4)  θ_k = atan2(p_k,y, p_k,x) + n_k,  ψ_k = atan2(p_k,z, ρ_k) + m_k,  n ~ N(0, σ_θ²),
      m ~ N(0, σ_ψ²) independent.
(T5)  speed prior: |v| = v_c ('relative', Lin et al.: the prior relative speed) or
      |v + v_o| = v_c ('ground': the target's own speed, what type recognition gives).

So (p0, v) is the target state relative to the observer's fitted constant-velocity track,
exactly the relative motion p = p_t − p_o, v = v_t − v_o of Lin et al. when the observer does
not manoeuvre. ``ple`` and ``ctls`` use the paper's model (δ ≡ 0); ``mle`` and the CRLB use
the given observer positions exactly (any δ).

Modules: :mod:`.model` (options, input checks, observer track, simulation), :mod:`.sums`
(pseudo-linear moments (T6)-(T13)), :mod:`.closed_form` (ple, ctls, ctls6),
:mod:`.observability` (Fisher information, constrained CRLB, gates), :mod:`.confidence`
(the tests (T19)-(T22) that mark a fix whose covariance would be too small
``low_confidence``), :mod:`.mle` (tma_mle), :mod:`.roots` (the two ranges of a ground-speed
prior (T23)),
:mod:`.accumulator` (the recursive window of the fusion node) and :mod:`.methods` (by name).
Every public name is importable from ``bearing_loc_ros.core.tma``.
"""

from ..fix import STATUS_LOW_CONFIDENCE, STATUS_OK, STATUS_UNOBSERVABLE, TMA_STATUSES
from .accumulator import TmaAccumulator
from .closed_form import estimate_from_sums, tma_ctls, tma_ctls6, tma_ple
from .methods import TMA_FUNCTIONS, tma, tma_function
from .mle import tma_mle
from .model import DEFAULTS, observer_track, simulate_tma, SPEED_REFERENCES, TMA_OPTIONS
from .observability import (constrained_crlb, constraint_gradient, fisher_terms,
                            state_transform, tma_crlb)
from .sums import batch_sums, bearing_terms, prefix_sums, TmaSums

__all__ = ['DEFAULTS', 'SPEED_REFERENCES', 'STATUS_LOW_CONFIDENCE', 'STATUS_OK',
           'STATUS_UNOBSERVABLE', 'TMA_FUNCTIONS', 'TMA_OPTIONS',
           'TMA_STATUSES', 'TmaAccumulator', 'TmaSums', 'batch_sums', 'bearing_terms',
           'constrained_crlb', 'constraint_gradient', 'estimate_from_sums', 'fisher_terms',
           'observer_track', 'prefix_sums', 'simulate_tma', 'state_transform', 'tma',
           'tma_crlb', 'tma_ctls', 'tma_ctls6', 'tma_function', 'tma_mle', 'tma_ple']
