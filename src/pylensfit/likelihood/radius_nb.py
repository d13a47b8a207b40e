"""numba kernels of the sum over size: ``L(e) = sum_r w_r L(e, r)`` run by run (one run
of increasing sizes per bulge fraction), corrected for peaks narrower than the size
grid, and ``L(r)`` summed over the e cells (docs: method, eq-radius).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: below this many e-folds under a galaxy's peak, exp() underflows in double precision
UNDERFLOW = 700.0
#: exp(x) is exactly 0 in double precision below x = -745.14: the sum over models skips
#: the call there, bit-identical (a bright galaxy's models far from its shape are most of
#: them: the kernel 13% faster on a precision block)
EXP_ZERO = 746.0

#: a size prior whose ``ln`` weight bends by more than this between neighbouring nodes
#: has an edge there (a box, a steep population edge):
#: the narrow-peak factor then comes from ``ln L`` alone (where ``L`` peaks at that
#: node, else none), since the parabola through ``ln(w L)`` would read the cliff as a
#: peak narrower than the grid and inflate the edge node's weight (by ~30%)
PRIOR_KINK = 1.0


@njit(cache=True, fastmath={"contract", "arcp", "afn"}, inline="always")
def _narrow_peak_factor(lm, l0, lp):
    """Correction of the sum over the r grid for a peak narrower than the grid step.

    ``sum_j L(r_j) dr`` is the trapezoid rule, exact to ``exp(-2 pi^2 s^2)`` for a
    Gaussian of width ``s`` grid steps, but for ``s < 1`` its value oscillates with
    the sub-step position of the peak: a bright galaxy's ``L(e)`` then jumps from one
    e cell to the next as the best size moves across the r grid. With the parabola
    through ``ln L`` at the largest sample and its neighbours (width ``s``, offset
    ``d``), the factor is ``sqrt(2 pi) s / sum_j exp(-(j - d)^2 / (2 s^2))``: the ratio
    of that Gaussian's integral to its grid sum, which makes the r marginalisation
    exact for a Gaussian peak and tends to 1 (to 3e-9) for ``s >= 1``.
    """
    a = lm - 2.0 * l0 + lp
    if a >= -1.0:  # s >= 1 step, or no peak: the grid sum is accurate
        return 1.0
    s2 = -1.0 / a
    d = 0.5 * (lm - lp) / a
    gsum = 0.0
    for j in range(-7, 8):
        gsum += math.exp(-0.5 * (j - d) * (j - d) / s2)
    if not gsum > 1e-300:  # a cliff in ln(w L) (a prior's edge), not a peak
        return 1.0
    return math.sqrt(2.0 * math.pi * s2) / gsum


@njit(cache=True, fastmath={"contract", "arcp", "afn"}, inline="always")
def _run_peak_factor(lwm, lw0, lwp, lm, l0, lp, kink):
    """:func:`_narrow_peak_factor` at the largest ``ln(w_j L_j)`` of a run of sizes.

    ``lwm, lw0, lwp`` are ``ln(w L)`` at that node and its neighbours, ``lm, l0, lp``
    ``ln L`` there and ``kink`` the second difference of ``ln w``. Where the prior bends
    by more than :data:`PRIOR_KINK` (an edge) the factor comes from ``ln L`` alone, and
    only if ``L`` itself peaks at the node; else it is 1.
    """
    if abs(kink) <= PRIOR_KINK:
        return _narrow_peak_factor(lwm, lw0, lwp)
    if l0 >= lm and l0 >= lp:
        return _narrow_peak_factor(lm, l0, lp)
    return 1.0


@njit(cache=True, fastmath={"contract", "arcp", "afn"})
def collapse_models(g, buf, best, sums, out):
    """Galaxy ``g``'s second pass (:func:`~pylensfit.likelihood.grid_nb.laplace_grid`):
    from its ``ln L`` of every model ``buf`` (peak ``best``; cell ``ie``'s sizes at
    ``ie * n_r``, the point source last), ``ln L(e)`` summed over r, ``ln L_k(e)`` per
    run and ``ln L(r)`` per group of e cells, into ``out = (lnle, lnlb, lnlr)``.
    ``sums`` is ``(node_w, ln node_w, w_star, ln_pi, pi, e_w, e_grp, n_sub)``
    (:class:`~pylensfit.likelihood.grid_nb.Sums` with the logs and the exponentials).
    Where a whole e cell lies more than ``UNDERFLOW`` e-folds under the peak its sum
    underflows, and ``ln L(e)`` is its largest weighted term. (One loop: with the run's
    sum in a helper, inlined, the pass took 15% longer.)"""
    node_w, ln_w, w_star, ln_pi, pi, e_w, e_grp, n_sub = sums
    out_lnle, out_lnlb, out_lnlr = out
    n_r = node_w.size
    star = buf.size - 1
    n_blk = n_r // n_sub
    lw_star = buf[star] + math.log(w_star)
    ex_star = math.exp(lw_star - best)
    rsum = np.zeros((out_lnlr.shape[1], n_r))
    lwr = np.empty(n_sub)
    for ie in range(e_w.size):
        ge = e_grp[ie]
        ew = e_w[ie]
        acc = ex_star
        emax = lw_star
        for ib in range(n_blk):  # runs of increasing r, one per bulge fraction
            bacc = 0.0
            rmax = -np.inf
            km = 0
            for irr in range(n_sub):
                ir = ib * n_sub + irr
                if not node_w[ir] > 0.0:  # outside the size prior: not evaluated
                    lwr[irr] = -np.inf
                    continue
                l = buf[ie * n_r + ir]
                dlb = l - best
                ex = math.exp(dlb) if dlb > -EXP_ZERO else 0.0
                bacc += ex * node_w[ir]
                rsum[ge, ir] += ex * ew
                lw = l + ln_w[ir]
                lwr[irr] = lw
                if lw > rmax:
                    rmax = lw
                    km = irr
            ir = ib * n_sub + km
            if 0 < km < n_sub - 1 and node_w[ir - 1] > 0.0 and node_w[ir + 1] > 0.0:
                bacc *= _run_peak_factor(
                    lwr[km - 1], lwr[km], lwr[km + 1], buf[ie * n_r + ir - 1],
                    buf[ie * n_r + ir], buf[ie * n_r + ir + 1],
                    ln_w[ir - 1] - 2.0 * ln_w[ir] + ln_w[ir + 1],
                )  # fmt: skip
            if rmax > best - UNDERFLOW and bacc > 0.0:
                out_lnlb[g, ie, ib] = best + math.log(bacc)
            else:
                out_lnlb[g, ie, ib] = rmax
            acc += bacc * pi[ib]
            if rmax + ln_pi[ib] > emax:
                emax = rmax + ln_pi[ib]
        if emax > best - UNDERFLOW:
            out_lnle[g, ie] = best + math.log(acc)
        else:
            out_lnle[g, ie] = emax
    _lnl_r(g, best, rsum, buf[star], out_lnlr)


@njit(cache=True, fastmath={"contract", "arcp", "afn"})
def _lnl_r(g, best, rsum, l_star, out_lnlr):
    """Galaxy ``g``'s ``ln L(r)`` per group of e cells from the sums ``rsum`` (``exp(ln
    L - best)``, weighted over the e cells), the point source's ``l_star`` last."""
    n_r = rsum.shape[1]
    for a in range(rsum.shape[0]):
        for ir in range(n_r):
            if rsum[a, ir] > 0.0:
                out_lnlr[g, a, ir] = best + math.log(rsum[a, ir])
            else:
                out_lnlr[g, a, ir] = -np.inf
        out_lnlr[g, a, n_r] = l_star
