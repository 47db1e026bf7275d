r"""High-precision reference for the white-surface energy deficit of single + double.

    python scripts/deficit_reference.py              # writes tests/data/deficit_reference.npz
    python scripts/deficit_reference.py --check      # and the convergence check (doubled rules)

The multiple-scattering remainder (docs/physics/multiple_scattering.md) is built from the
deficit ``D(m, mu) = 1 - E_single - E_double`` of the ideal white surface (``F = 1``). This
script computes it independently of ppr's BRDF code, tables and quadratures, as a *positive*
integral (no ``1 - E`` cancellation), which keeps its relative precision in the tails where
``D`` is 1e-12 or 1e-100:

    D(mu)  = int d omega_h1  rho1(h1) b1(d1) U(d1.n),
    D_s(mu) = int d omega_h1  rho1(h1) b1(d1)            (single term alone),

with, for incidence ``k`` (``k.n = c = mu``), ``d1 = 2 (k.h1) h1 - k``:

* ``rho1 = p(h1) (h1.k)+ / <h.k>+``: the lit facet normals (integrates to 1);
* ``b1(d1)``: the probability that the ray leaving facet 1 is blocked, given that facet 1 is lit:
  1 if ``d1`` heads down, else ``1 - P(k|d1) / P(k)`` with Ashikhmin's joint visibility, i.e.
  ``(1 - f) Q(d1)`` if ``d1.n >= c`` and ``(1 - f) Q(d1) + f (Q(d1) - Q(k)) / P(k)`` below,
  ``Q = 1 - P`` and ``f = cos(phi/2)`` of the azimuth between ``k`` and ``d1``;
* ``U(z)``: the probability that the ray that left facet 1 along ``d1`` (``z = d1.n``) does not
  leave after its second facet,

    U(z) = int d omega_h2 q(h2|w) L(k', w),   q = p(h2) (h2.w)+ / <h.w>+,   w = -d1,
    k' = 2 (h2.w) h2 - w,

  ``L = 1`` for ``k'`` heading down; for ``z > 0`` (the ray went up and was blocked)
  ``L = Q(k')``; for ``z < 0`` ``L = 1 - P(k') rho(k', w)`` with ppr's exit correlation, which
  is ``Q(k') + f P(k')`` if ``k'.n <= |z|`` and ``Q(k') (1 - f + f / Q(w))`` above
  (``f`` between ``k'`` and ``w``). ``U`` is a function of ``z`` alone (rotation about ``n``).

These are the model of docs/physics/double_bounce.md ("Two-facet visibility"), rewritten:
``E_single = int rho1 P(k|d1) / P(k)`` and ``E_double = int rho1 b1 (1 - U)`` because the
double term's weight is ``P(k) B(d1) rho(k, d1) = P(k) b1`` times the second bounce's escape
probability (the coherent backscatter cone is outside, as in the albedo tables).

Numerics (float64 NumPy except the lobe integral):

* ``<h.(-u)>+`` (facets facing away from ``u``, ``u.n = c``) from its definition,
  ``(m + 1)/pi int_e^{pi/2} cos^m t sin t [sqrt(sin^2 t - c^2) - c cos t acos(x)] dt`` with
  ``x = c cot t / sqrt(1 - c^2)`` (``e = asin c``), by mpmath tanh-sinh at 30 digits on
  subintervals that follow the lobe, tabulated per ``m`` on nodes log-spaced in ``c`` and
  interpolated by a cubic spline of ``log <h.(-u)>+ - (m+2)/2 log(1 - c^2)`` (a smooth
  function); ``Q(c)`` and ``P(c)`` follow
  without cancellation. The spline error is measured against direct mpmath values at the
  cell midpoints and reported.
* Facet normals in ``(y, phi)`` with ``cos^(m+1) t = exp(-y^2)`` (``p d omega = 2 y e^{-y^2} dy
  dphi / 2 pi``): every structure of the integrand (lobe, masking ``Q`` of a direction near the
  horizon) has width O(1) in ``y`` at every ``m``. Per azimuth the kinks are panel ends in closed
  form (``d1.n = R cos(2t - alpha)``, ``k'.n = R sin(2t - beta)``): the lit boundary, the
  horizons, ``d1.n = c`` and ``k'.n = |z|``. Composite Gauss-Legendre (8 nodes) on ``y``
  panels of at most ``DY`` up to ``y = Y_MAX`` (``e^{-y^2}`` = 1e-317) and on azimuth panels of
  at most ``DPHI``, refined geometrically toward ``phi = pi/2`` where the lit boundary moves
  fast at grazing incidence.
* ``U(z)`` on ``NZ`` nodes per sign of ``z``, log-spaced in the elevation ``asin|z|``, interpolated
  by a cubic spline of ``log U`` (interpolation error at the midpoints reported).

``--check`` repeats the computation with every rule doubled (``DY``, ``DPHI`` halved, twice the
lobe and ``U`` nodes) and reports the relative change of ``D``.

``D_avg = 2 int_0^1 D mu dmu`` per ``m``: Gauss-Legendre (8 nodes) on 24 panels log-spaced in
``mu`` from ``1e-3 / sqrt(m + 2)`` to 1.

The output ``tests/data/deficit_reference.npz`` holds ``m``, ``theta_deg``, ``D`` (single +
double), ``D_single``, ``D_avg`` and ``rel_change``, ``rel_change_avg`` (the doubled-rule
changes, when ``--check``).
"""

from __future__ import annotations

import argparse
import os
import time

import mpmath as mp
import numpy as np
from scipy.interpolate import CubicSpline
from scipy.special import expit

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OUT = os.path.join(ROOT, "tests", "data", "deficit_reference.npz")

Y_MAX = 27.0  # e^{-y^2} = 1e-317
DY = 0.2
DPHI = 0.05
N_GL = 8
N_LOBE = 160  # lobe-integral nodes in c
NZ = 120  # uniform U nodes per sign of z and half of the elevation range

# (m, incidence in degrees) of the stored reference
M_GRID = (0.0, 1.0, 10.0, 100.0, 1000.0, 1e4)
THETA_GRID = (
    0.0,
    30.0,
    45.0,
    60.0,
    62.0,
    65.0,
    70.0,
    72.5,
    75.0,
    77.5,
    80.0,
    82.0,
    84.0,
    85.0,
    86.0,
    87.0,
    88.0,
    88.5,
    89.0,
    89.5,
    89.8,
    89.9,
    89.95,
    89.98,
)


# ---------------------------------------------------------------------------------------------
# lobe integrals


def nm_direct(m: float, c: float, dps: int = 30) -> mp.mpf:
    """``<h.(-u)>+`` for ``u.n = c`` (facets facing away from ``u``), from the definition."""
    with mp.workdps(dps):
        m = mp.mpf(m)
        c = mp.mpf(c)
        if c >= 1:
            return mp.mpf(0)
        su = mp.sqrt(1 - c * c)
        e = mp.asin(c)

        def f(t):
            st, ct = mp.sin(t), mp.cos(t)
            x = c * ct / (su * st)
            r2 = st * st - c * c
            if x >= 1 or r2 <= 0:  # tanh-sinh nodes rounded onto t <= e
                return mp.mpf(0)
            return ct**m * st * (mp.sqrt(r2) - c * ct * mp.acos(x))

        # subintervals on the lobe's scale beyond t = e (cos^m t ~ exp(-m tan(e) (t - e)) there)
        tau = 1 / (m * mp.tan(e) + mp.sqrt(m + 1)) if c > 0 else 1 / mp.sqrt(m + 1)
        pts = [e]
        k = 1
        while e + k * tau < mp.pi / 2 and k < 2**14:
            pts.append(e + k * tau)
            k *= 2
        pts.append(mp.pi / 2)
        return (m + 1) / mp.pi * mp.quad(f, pts)


class Lobe:
    """``P(c)``, ``Q(c) = 1 - P(c)`` and ``log Q`` of Ashikhmin's visibility for one ``m``, from
    a spline of the smooth part of ``log <h.(-u)>+`` (module docstring)."""

    def __init__(self, m: float, n_nodes: int = N_LOBE, check: bool = True):
        self.m = float(m)
        self.M = self.m + 2.0
        self.hn = (self.m + 1.0) / (self.m + 2.0)
        self.c0 = 0.02 / np.sqrt(self.M)
        xi = np.linspace(0.0, 1.0, n_nodes)
        c = self._c_of(xi)
        h = np.array([self._h_direct(ci) for ci in c])
        self.spline = CubicSpline(xi, h)
        self.spline_err = float("nan")
        if not check:
            return
        # interpolation error at the cell midpoints (every 4th cell)
        xm = 0.5 * (xi[:-1] + xi[1:])[::4]
        hm = np.array([self._h_direct(ci) for ci in self._c_of(xm)])
        self.spline_err = float(np.max(np.abs(self.spline(xm) - hm)))

    def _c_of(self, xi):
        return self.c0 * np.expm1(xi * np.log1p(1.0 / self.c0))

    def _xi_of(self, c):
        return np.log1p(np.asarray(c) / self.c0) / np.log1p(1.0 / self.c0)

    def _h_direct(self, c: float) -> float:
        cc = min(float(c), 1.0 - 1e-12)
        with mp.workdps(30):
            v = nm_direct(self.m, cc)
            return float(mp.log(v) - self.M / 2 * mp.log1p(-(mp.mpf(cc) ** 2)))

    def log_nm(self, c):
        c = np.clip(np.asarray(c, float), 0.0, 1.0)
        with np.errstate(divide="ignore"):
            return self.spline(self._xi_of(c)) + 0.5 * self.M * np.log1p(-c * c)

    def log_q_p(self, c):
        """``(log Q, Q, P)`` at ``u.n = c`` (``c`` in [0, 1])."""
        c = np.clip(np.asarray(c, float), 0.0, 1.0)
        ln = self.log_nm(c)
        with np.errstate(divide="ignore"):
            lc = np.log(c * self.hn)
        a = ln - lc  # log(Nm / (c <h.n>))
        q = expit(a)
        p = expit(-a)
        # log Q = -log(1 + exp(-a))
        log_q = -np.logaddexp(0.0, -a)
        return log_q, q, p


# ---------------------------------------------------------------------------------------------
# rules


def _gl():
    x, w = np.polynomial.legendre.leggauss(N_GL)
    return 0.5 * (x + 1.0), 0.5 * w


def phi_rule(lo: float, hi: float, lam: float, dphi: float):
    """Azimuth nodes on ``[lo, hi]`` (one end is pi/2), panels refined geometrically toward
    ``pi/2`` with first width ``lam`` and at most ``dphi`` wide."""
    span = hi - lo
    d = [0.0]
    step = max(min(lam, dphi), 1e-12)
    while d[-1] < span:
        d.append(min(d[-1] + step, span))
        step = min(2.0 * step, dphi)
    d = np.array(d)
    edges = (0.5 * np.pi + d) if lo >= 0.5 * np.pi - 1e-15 else (0.5 * np.pi - d)[::-1]
    x, w = _gl()
    a, b = edges[:-1, None], edges[1:, None]
    return (a + (b - a) * x).ravel(), ((b - a) * w).ravel()


def y_of_t(m: float, t):
    """``y = sqrt(-(m+1) log cos t)`` (inf at ``t >= pi/2``)."""
    t = np.asarray(t, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        ct = np.cos(np.clip(t, 0.0, 0.5 * np.pi))
        y = np.sqrt(-(m + 1.0) * np.log(np.where(ct > 0, ct, 1.0)))
    return np.where((t >= 0.5 * np.pi) | (ct <= 0), np.inf, np.where(t <= 0, 0.0, y))


def y_rule(m: float, y_lo, y_hi, kinks, dy: float):
    """Per-azimuth ``y`` nodes on ``[y_lo, y_hi]`` (``(P,)``, cut at ``Y_MAX``): panels between
    the grid ``y_lo, y_lo + dy, ...`` and the kinks (``(P, K)`` in ``y``). Returns ``(y, wy)`` of
    shape ``(P, N)`` (zero-width panels carry zero weight)."""
    P = y_lo.shape[0]
    lo = np.minimum(y_lo, Y_MAX)[:, None]
    hi = np.minimum(y_hi, Y_MAX)[:, None]
    hi = np.maximum(hi, lo)
    n = int(np.ceil(np.max(hi - lo) / dy)) + 1
    grid = lo + dy * np.arange(n)[None, :]
    e = np.concatenate([grid, kinks], axis=1)
    e = np.sort(np.clip(np.nan_to_num(e, nan=0.0, posinf=Y_MAX), lo, hi), axis=1)
    e = np.concatenate([lo, e, hi], axis=1)
    a, b = e[:, :-1, None], e[:, 1:, None]
    x, w = _gl()
    return (a + (b - a) * x).reshape(P, -1), ((b - a) * w).reshape(P, -1)


def facets(m: float, y):
    """``(cos t, sin t, density)`` at ``y``: ``p(h) d omega = density dy dphi``."""
    a = y * y / (m + 1.0)
    ct = np.exp(-a)
    om = -np.expm1(-a)
    st = np.sqrt(om * (1.0 + ct))
    dens = 2.0 * y * np.exp(-y * y) / (2.0 * np.pi)
    return ct, st, dens


def _azimuth_f(ax, ay, bx, by):
    """Ashikhmin's ``f = cos(phi/2)`` between surface projections ``(ax, ay)``, ``(bx, by)``
    (1 where one vanishes)."""
    na = np.hypot(ax, ay)
    nb = np.hypot(bx, by)
    ok = (na > 1e-300) & (nb > 1e-300)
    cosd = np.where(ok, (ax * bx + ay * by) / np.where(ok, na * nb, 1.0), 1.0)
    return np.sqrt(np.clip(0.5 * (1.0 + cosd), 0.0, 1.0))


# ---------------------------------------------------------------------------------------------
# second bounce


def u_value(lobe: Lobe, z: float, dy: float = DY, dphi: float = DPHI) -> float:
    """``U(z)``: probability that the ray leaving facet 1 with ``d1.n = z`` is still inside
    the surface after its second facet (module docstring)."""
    m = lobe.m
    sw = np.sqrt(max(1.0 - z * z, 0.0))
    lam = max(abs(z), 1e-12)
    if z > 0:
        phis = [phi_rule(0.0, 0.5 * np.pi, lam, dphi)]
    else:
        phis = [phi_rule(0.0, 0.5 * np.pi, lam, dphi), phi_rule(0.5 * np.pi, np.pi, lam, dphi)]
    num = den = 0.0
    log_qw, qw, _ = lobe.log_q_p(abs(z))
    for ph, wph in phis:
        A = sw * np.cos(ph)
        R = np.hypot(A, z)
        beta = np.arctan2(z, A)  # h2.w = R sin(t - beta), k'.n = R sin(2t - beta)
        t_lo = np.maximum(beta, 0.0)
        t_hi = np.minimum(0.5 * np.pi, beta + np.pi)
        ks = [0.5 * (beta + np.pi), 0.5 * beta]
        if z < 0:
            a = np.arcsin(np.clip(abs(z) / R, 0.0, 1.0))
            ks += [0.5 * (beta + a), 0.5 * (beta + np.pi - a)]
        kinks = np.stack([y_of_t(m, np.clip(k, 0.0, 0.5 * np.pi)) for k in ks], axis=1)
        y_lo = y_of_t(m, t_lo)
        # U is a ratio: e^{-y^2} beyond y_lo^2 + 100 is 1e-43 of the lit region's start
        y_hi = np.minimum(y_of_t(m, t_hi), np.sqrt(y_lo**2 + 100.0))
        y, wy = y_rule(m, y_lo, y_hi, kinks, dy)
        ct, st, dens = facets(m, y)
        cp, sp = np.cos(ph)[:, None], np.sin(ph)[:, None]
        hx, hy, hz = st * cp, st * sp, ct
        hw = hx * sw - hz * z
        lit = hw > 0
        kx, ky, kz = 2 * hw * hx - sw, 2 * hw * hy, 2 * hw * hz + z
        wt = np.where(lit, dens * hw * wy * wph[:, None], 0.0)
        up = kz > 0
        log_qa, qa, pa = lobe.log_q_p(np.clip(kz, 0.0, 1.0))
        if z > 0:
            L = np.where(up, qa, 1.0)
        else:
            f = _azimuth_f(kx, ky, sw, 0.0)
            low = kz <= abs(z)
            # Q(k') / Q(w) <= 1 here; both from logs (no underflow at steep w)
            ratio = np.exp(np.minimum(np.where(np.isfinite(log_qa), log_qa - log_qw, -np.inf), 0.0))
            hi_case = qa * (1.0 - f) + f * ratio
            L = np.where(up, np.where(low, qa + f * pa, hi_case), 1.0)
        num += float(np.sum(wt * L))
        den += float(np.sum(wt))
    if den <= 0.0 or not np.isfinite(den):
        return float("nan")
    return min(max(num / den, 0.0), 1.0)


class SecondBounce:
    """Cubic splines of ``log U(z)`` in the elevation ``e = asin |z|``: per sign of ``z``, one
    on ``[0, pi/4]`` in ``d = e`` and one on ``[pi/4, pi/2]`` in ``d = pi/2 - e`` (``U`` varies on
    the lobe's scale ``a = 1/sqrt(m + 2)`` near the horizon and near the vertical, where
    Ashikhmin's ``f`` follows the azimuth of a nearly vertical ``w``). Nodes in ``d``: ``n``
    uniform on ``[0, 30 a]`` (``log U`` is close to quadratic in ``e / a`` there), a third as
    many log-spaced beyond, and a few log-spaced below ``0.1 a``; the spline variable is
    ``log d`` near the vertical (``U ~ d^k`` for ``z > 0``), where ``d >= 1e-6 a`` (exactly
    vertical ``w`` is the ``f = 1`` convention, a jump of ``U``: the limit is used). Where no
    facet faces ``w`` within the rule (``U`` undefined: steep ``z > 0``, whose weight ``Q(z)``
    underflows) the nearest defined value is used. ``spline_err``: max error of ``log U`` (the
    relative error of ``U``) at interval midpoints where ``U > 1e-12`` and, for ``z > 0``, the
    weight ``Q(z)`` of a blocked ray exceeds 1e-9."""

    def __init__(
        self, lobe: Lobe, nz: int = NZ, dy: float = DY, dphi: float = DPHI, check: bool = True
    ):
        a = 1.0 / np.sqrt(lobe.m + 2.0)
        self.d_min = 1e-6 * a
        top = 0.25 * np.pi
        lin_end = min(30.0 * a, top)
        d = np.concatenate(
            [
                [0.0],
                np.geomspace(self.d_min, 0.1 * a, 8),
                np.linspace(0.0, lin_end, nz),
                np.geomspace(lin_end, top, max(nz // 3, 2)) if lin_end < top else [top],
            ]
        )
        d = np.unique(np.round(d, 15))
        self.splines = {}
        errs = []
        for sign in (1.0, -1.0):
            for half in (0, 1):
                dh = d if half == 0 else d[d >= self.d_min]
                x = self._x_of(dh, half)
                lu = self._log_u(lobe, sign * np.sin(self._e_of(dh, half)), dy, dphi)
                sp = CubicSpline(x, lu)
                self.splines[sign, half] = sp
                if not check:
                    continue
                xm = 0.5 * (x[:-1] + x[1:])[::5]
                zm = sign * np.sin(self._e_of(self._d_of(xm, half), half))
                lum = self._log_u(lobe, zm, dy, dphi)
                keep = lum > np.log(1e-12)
                if sign > 0:
                    keep &= lobe.log_q_p(np.abs(zm))[1] > 1e-9
                if keep.any():
                    errs.append(np.max(np.abs(sp(xm) - lum)[keep]))
        self.spline_err = float(max(errs)) if errs else float("nan")

    @staticmethod
    def _x_of(d, half):
        # near the vertical U ~ d^k for z > 0 (smooth in log d); constant for z < 0
        return d if half == 0 else np.log(d)

    @staticmethod
    def _d_of(x, half):
        return x if half == 0 else np.exp(x)

    @staticmethod
    def _log_u(lobe, z, dy, dphi):
        z = np.clip(np.where(z == 0, 1e-15, z), -1.0 + 1e-15, 1.0 - 1e-15)
        u = np.array([u_value(lobe, zi, dy, dphi) for zi in z])
        lu = np.log(np.maximum(u, 1e-300))
        bad = ~np.isfinite(u)
        if bad.all():
            return np.zeros_like(lu)
        good = np.nonzero(~bad)[0]
        # nearest defined value (U undefined only where its weight Q(z) underflows)
        idx = good[np.clip(np.searchsorted(good, np.arange(len(lu))), 0, len(good) - 1)]
        return np.where(bad, lu[idx], lu)

    def _e_of(self, d, half):
        return d if half == 0 else 0.5 * np.pi - np.maximum(d, self.d_min)

    def __call__(self, z):
        z = np.asarray(z, float)
        e = np.arcsin(np.clip(np.abs(z), 0.0, 1.0))
        out = np.empty_like(z)
        for sign in (1.0, -1.0):
            for half in (0, 1):
                sel = (z > 0) if sign > 0 else (z <= 0)
                sel = sel & ((e <= 0.25 * np.pi) if half == 0 else (e > 0.25 * np.pi))
                if sel.any():
                    d = e[sel] if half == 0 else np.maximum(0.5 * np.pi - e[sel], self.d_min)
                    out[sel] = self.splines[sign, half](self._x_of(d, half))
        return np.exp(out).clip(0.0, 1.0)


# ---------------------------------------------------------------------------------------------
# first bounce


def deficit(lobe: Lobe, second: SecondBounce | None, mu: float, dy=DY, dphi=DPHI):
    """``(D, D_single, norm)`` at ``k.n = mu``: ``norm`` is the rule's integral of ``rho1``
    (1 up to the quadrature error)."""
    m = lobe.m
    c = float(mu)
    s = np.sqrt(max(1.0 - c * c, 0.0))
    lam = c * (1.0 + np.sqrt(m + 1.0) / 4.0) / max(s, 1e-300)
    log_qk, qk, pk = lobe.log_q_p(c)
    mcp = c * lobe.hn + np.exp(lobe.log_nm(c))  # <h.k>+
    tot = tot_s = norm = 0.0
    for ph, wph in (phi_rule(0.0, 0.5 * np.pi, lam, dphi), phi_rule(0.5 * np.pi, np.pi, lam, dphi)):
        cp = np.cos(ph)
        R1 = np.hypot(c, s * cp)
        alpha = np.arctan2(s * cp, c)  # d1.n = R1 cos(2t - alpha)
        t_max = np.minimum(0.5 * np.pi, 0.5 * np.pi + alpha)
        ks = [0.5 * alpha + 0.25 * np.pi]
        g = np.arccos(np.clip(c / R1, -1.0, 1.0))
        ks += [0.5 * (alpha - g), 0.5 * (alpha + g)]
        kinks = np.stack([y_of_t(m, np.clip(k, 0.0, 0.5 * np.pi)) for k in ks], axis=1)
        y, wy = y_rule(m, np.zeros_like(ph), y_of_t(m, t_max), kinks, dy)
        ct, st, dens = facets(m, y)
        hx, hy, hz = st * cp[:, None], st * np.sin(ph)[:, None], ct
        hk = hx * s + hz * c
        lit = hk > 0
        wt = np.where(lit, dens * hk / mcp * wy * wph[:, None], 0.0) * 2.0  # phi in [-pi, 0]
        dx, dyy, dz = 2 * hk * hx - s, 2 * hk * hy, 2 * hk * hz - c
        up = dz > 0
        _, qd, _ = lobe.log_q_p(np.clip(dz, 0.0, 1.0))
        f = _azimuth_f(dx, dyy, s, 0.0)
        b_up = (1.0 - f) * qd + np.where(
            dz < c, f * np.maximum(qd - qk, 0.0) / max(pk, 1e-300), 0.0
        )
        b1 = np.where(up, b_up, 1.0)
        tot_s += float(np.sum(wt * b1))
        if second is not None:
            tot += float(np.sum(wt * b1 * second(dz)))
        norm += float(np.sum(wt))
    return tot, tot_s, norm


def deficit_avg(lobe: Lobe, second: SecondBounce, dy=DY, dphi=DPHI, n_panels=24, n_gl=8):
    """``D_avg = 2 int_0^1 D(mu) mu dmu``: Gauss-Legendre on panels log-spaced from
    ``1e-3 / sqrt(m + 2)`` to 1 (plus ``[0, 1e-3 / sqrt(m + 2)]``)."""
    a = 1e-3 / np.sqrt(lobe.m + 2.0)
    edges = np.concatenate([[0.0], np.geomspace(a, 1.0, n_panels)])
    x, w = np.polynomial.legendre.leggauss(n_gl)
    lo, hi = edges[:-1, None], edges[1:, None]
    mu = (lo + 0.5 * (hi - lo) * (x + 1.0)).ravel()
    wt = (0.5 * (hi - lo) * w).ravel()
    D = np.array([deficit(lobe, second, u, dy, dphi)[0] for u in mu])
    return 2.0 * float(np.sum(D * mu * wt))


def reference(m_list, theta_list, *, scale: int = 1, log=print, cache: str = ""):
    """``D``, ``D_single`` on the grid and ``D_avg`` per m; ``scale = 2`` doubles every rule.
    ``cache``: an ``.npz`` of finished rows (an interrupted run resumes)."""
    D = np.zeros((len(m_list), len(theta_list)))
    Ds = np.zeros_like(D)
    Davg = np.zeros(len(m_list))
    info = [""] * len(m_list)
    done = np.zeros(len(m_list), bool)
    if cache and os.path.exists(cache):
        with np.load(cache) as z:
            if np.array_equal(z["m"], m_list) and np.array_equal(z["theta"], theta_list):
                D, Ds, Davg, done = z["D"], z["Ds"], z["Davg"], z["done"]
                info = list(z["info"])
    for i, m in enumerate(m_list):
        if done[i]:
            continue
        t0 = time.perf_counter()
        lobe = Lobe(m, N_LOBE * scale)
        t1 = time.perf_counter()
        second = SecondBounce(lobe, NZ * scale, DY / scale, DPHI / scale)
        t2 = time.perf_counter()
        norms = []
        for j, th in enumerate(theta_list):
            mu = float(np.cos(np.deg2rad(th)))
            D[i, j], Ds[i, j], nrm = deficit(lobe, second, mu, DY / scale, DPHI / scale)
            norms.append(nrm)
        Davg[i] = deficit_avg(lobe, second, DY / scale, DPHI / scale, 24 * scale)
        t3 = time.perf_counter()
        msg = (
            f"m={m:g}: lobe spline err {lobe.spline_err:.1e} ({t1 - t0:.0f} s), U spline err "
            f"{second.spline_err:.1e} ({t2 - t1:.0f} s), max |norm - 1| "
            f"{np.max(np.abs(np.array(norms) - 1)):.1e} ({t3 - t2:.0f} s)"
        )
        log(msg + f", D_avg {Davg[i]:.6e}", flush=True)
        info[i] = msg
        done[i] = True
        if cache:
            np.savez(
                cache,
                m=m_list,
                theta=theta_list,
                D=D,
                Ds=Ds,
                Davg=Davg,
                done=done,
                info=np.array(info),
            )
    return D, Ds, Davg, info


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="repeat with doubled rules")
    ap.add_argument("--m", type=float, nargs="*", default=None)
    ap.add_argument("--theta", type=float, nargs="*", default=None)
    ap.add_argument("--out", default=OUT)
    ap.add_argument("--cache", default="", help="npz of finished rows (resume)")
    args = ap.parse_args(argv)
    m_list = tuple(args.m) if args.m else M_GRID
    th_list = tuple(args.theta) if args.theta else THETA_GRID
    D, Ds, Davg, info = reference(m_list, th_list, cache=args.cache)
    rel = np.full_like(D, np.nan)
    rel_avg = np.full_like(Davg, np.nan)
    if args.check:
        c2 = args.cache.replace(".npz", "_x2.npz") if args.cache else ""
        D2, _, Davg2, info2 = reference(m_list, th_list, scale=2, cache=c2)
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.abs(D2 - D) / np.maximum(np.abs(D2), 1e-300)
            rel_avg = np.abs(Davg2 - Davg) / Davg2
        info += ["doubled: " + s for s in info2]
    np.set_printoptions(linewidth=200, precision=3)
    for i, m in enumerate(m_list):
        print(f"m={m:g}")
        for j, th in enumerate(th_list):
            print(
                f"  {th:5.1f} deg  D={D[i, j]:.6e}  D_single={Ds[i, j]:.6e}  "
                f"rel_change={rel[i, j]:.1e}"
            )
    np.savez(
        args.out,
        m=np.array(m_list),
        theta_deg=np.array(th_list),
        D=D,
        D_single=Ds,
        D_avg=Davg,
        rel_change=rel,
        rel_change_avg=rel_avg,
        info=np.array("\n".join(info)),
    )
    print("wrote", args.out)


if __name__ == "__main__":
    main()
