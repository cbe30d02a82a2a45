"""Chi-square quantiles without importing ``scipy.stats``.

``scipy.stats`` takes 0.7-1.5 s to import, which every ``bearing_loc`` command and node start
would pay for two functions. The χ²_k distribution is a gamma distribution with shape k/2
and scale 2, so its quantiles are 2·P⁻¹(k/2, p) and 2·Q⁻¹(k/2, q) with the regularized
incomplete gamma inverses of ``scipy.special`` (exactly what ``scipy.stats.chi2`` evaluates).
"""

from scipy.special import gammainccinv, gammaincinv


def ppf(p, dof):
    """The p quantile of χ² with ``dof`` degrees of freedom (scalars or arrays)."""
    return 2.0 * gammaincinv(0.5 * dof, p)


def isf(q, dof):
    """The upper-tail q quantile of χ² with ``dof`` degrees of freedom: ppf(1 − q, dof)."""
    return 2.0 * gammainccinv(0.5 * dof, q)
