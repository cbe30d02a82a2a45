"""Float arithmetic shared by the one-problem paths of core/ml_single.py and core/ctls_single.py.

Each function performs the floating point operations of its vectorised counterpart in the
same order, so the one-problem paths reproduce the batch paths to rounding.
"""

import math

from .solvers import INVERSE3_MAX_CONDITION


def solve3(a00, a01, a02, a11, a12, a22, b0, b1, b2):
    """solvers.solve3_packed on floats: A x = b for symmetric A by cofactors; NaN where det ≤ 0.

    A = [[a00, a01, a02], [a01, a11, a12], [a02, a12, a22]], b = (b0, b1, b2); any units.
    """
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    det = a00 * c00 + a01 * c01 + a02 * c02
    inv_det = 1.0 / det if det > 0 else math.nan
    return ((c00 * b0 + c01 * b1 + c02 * b2) * inv_det,
            (c01 * b0 + (a00 * a22 - a02 * a02) * b1 + (a01 * a02 - a00 * a12) * b2) * inv_det,
            (c02 * b0 + (a01 * a02 - a00 * a12) * b1 + (a00 * a11 - a01 * a01) * b2) * inv_det)


def pseudo_linear_rows(th, ps, has_el):
    """Rows h_θ, h_ψ of the pseudo-linear system of one station (Wang, Zhang & Wu eq. (4);
    pseudo_linear.pseudo_linear_system): h_θ = (sin θ, −cos θ, 0), h_ψ = (cos θ sin ψ,
    sin θ sin ψ, −cos ψ), zero for an azimuth-only station. θ ENU azimuth, ψ elevation, rad."""
    st, ct = math.sin(th), math.cos(th)
    if not has_el:
        return (st, -ct, 0.0), (0.0, 0.0, 0.0)
    sp, cp = math.sin(ps), math.cos(ps)
    return (st, -ct, 0.0), (ct * sp, st * sp, -cp)


def normal_equations(rows):
    """(HᵀH packed (a00, a01, a02, a11, a12, a22), HᵀY (b0, b1, b2)) of the pseudo-linear LS.

    ``rows``: per station (h00, h01, h10, h11, h12, y0, y1), the rows h_θ = (h00, h01, 0) and
    h_ψ = (h10, h11, h12) of :func:`pseudo_linear_rows` and their right-hand sides y = h·p
    (p the station position, m), summed in station order (Wang, Zhang & Wu eq. (4)).
    """
    a00 = a01 = a02 = a11 = a12 = a22 = b0 = b1 = b2 = 0.0
    for h00, h01, h10, h11, h12, y0, y1 in rows:
        a00 += h00 * h00 + h10 * h10
        a01 += h00 * h01 + h10 * h11
        a02 += h10 * h12
        a11 += h01 * h01 + h11 * h11
        a12 += h11 * h12
        a22 += h12 * h12
        b0 += h00 * y0 + h10 * y1
        b1 += h01 * y0 + h11 * y1
        b2 += h12 * y1
    return (a00, a01, a02, a11, a12, a22), (b0, b1, b2)


def inverse3(a00, a01, a02, a11, a12, a22):
    """solvers.spd_inverse3 on floats: A⁻¹ by cofactors (nested lists), or None.

    A = [[a00, a01, a02], [a01, a11, a12], [a02, a12, a22]] with finite entries, any units;
    A⁻¹ = adj(A) / det(A). None unless the leading principal minors are positive (A positive
    definite, Sylvester's criterion) and tr(A) tr(A⁻¹) ≤ solvers.INVERSE3_MAX_CONDITION:
    that product bounds κ = λ_max/λ_min, so the result agrees with LAPACK's inverse
    (crlb.safe_inverse, which such a matrix always passes) to about κ² machine epsilons
    (≤ 1e-11 relative to its largest entry); otherwise the caller takes the LAPACK path.
    """
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    if not (a00 > 0.0 and c22 > 0.0 and 0.0 < det < math.inf):
        return None
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    if not (a00 + a11 + a22) * (c00 + c11 + c22) <= INVERSE3_MAX_CONDITION * det:
        return None
    i = 1.0 / det
    return [[c00 * i, c01 * i, c02 * i], [c01 * i, c11 * i, c12 * i],
            [c02 * i, c12 * i, c22 * i]]
