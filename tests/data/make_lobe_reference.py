"""Regenerate tests/data/lobe_reference.npz: mpmath reference values of <h.k>+.

Independent of ppr's quadrature: the facet azimuth is integrated in closed form (checked
against mp.quad over the azimuth in tests/test_microfacet.py) and the remaining integral over
t = h.n is done by mpmath's tanh-sinh quadrature in the variable t = s exp(-w / (m + 1))
(uniform lobe weight e^-w), split at the kink (w = 0), at the grazing layer
w = (m + 1) c^2 / 2 and at fixed w, at 40 significant digits.

    <h.k>+ = c (m+1)/(m+2) + s^(m+1) int_0^inf e^-w G(s e^(-w/(m+1))) dw,
    pi G(t) = sqrt(s^2 - t^2) - c t atan2(sqrt(s^2 - t^2), c t),   s = sqrt(1 - c^2).

Run:  .venv/bin/python tests/data/make_lobe_reference.py     (about 2 minutes)
"""

from __future__ import annotations

import pathlib

import mpmath as mp
import numpy as np

DPS = 40
M_VALUES = [0.0, 1e-3, 0.5, 1.0, 10.0, 100.0, 1e3, 5e3, 1e4, 1e5, 1e6]
ANGLES_DEG = [
    0,
    15,
    30,
    45,
    60,
    70,
    75,
    80,
    84,
    86,
    88,
    89,
    89.5,
    89.8,
    89.9,
    89.95,
    89.98,
    89.99,
    89.995,
    89.998,
    89.999,
]
# extra points inside the grazing band of each m: c = z sqrt(2 / (m + 2))
Z_BAND = [0.1, 0.3, 1.0, 2.0, 3.0, 5.0]


def azimuth_closed_form(c, t):
    """Facet-azimuth average of max(h.k, 0) minus c t, for h.n = t (mpmath numbers)."""
    s = mp.sqrt(1 - c * c)
    if t >= s:
        return mp.mpf(0)
    r = mp.sqrt((s - t) * (s + t))
    return (r - c * t * mp.atan2(r, c * t)) / mp.pi


def mean_cosine_plus_ref(m, c, dps: int = DPS):
    """<h.k>+ at Blinn-Phong exponent m and cos_theta c (floats), as an mpmath number."""
    with mp.workdps(dps):
        m = mp.mpf(m)
        c = mp.mpf(c)
        s = mp.sqrt((1 - c) * (1 + c))
        base = c * (m + 1) / (m + 2)
        if s == 0:
            return base

        def integrand(w):
            t = s * mp.exp(-w / (m + 1))
            r = s * mp.sqrt(-mp.expm1(-2 * w / (m + 1)))
            return mp.exp(-w) * (r - c * t * mp.atan2(r, c * t)) / mp.pi

        w_layer = (m + 1) * c * c / 2
        pts = {mp.mpf(0), mp.mpf(1), mp.mpf(5), mp.mpf(20), mp.mpf(60)}
        for f in (mp.mpf("0.1"), mp.mpf("0.5"), mp.mpf(1), mp.mpf(2)):
            if 0 < w_layer * f < 60:
                pts.add(w_layer * f)
        pts = sorted(pts) + [mp.inf]
        corr = s ** (m + 1) * mp.quad(integrand, pts)
        return base + corr


def grid() -> tuple[np.ndarray, np.ndarray]:
    ms, cs = [], []
    for m in M_VALUES:
        cvals = [float(mp.cos(mp.radians(mp.mpf(a)))) for a in ANGLES_DEG]
        cvals += [z * (2.0 / (m + 2.0)) ** 0.5 for z in Z_BAND]
        for c in sorted(set(cvals)):
            if 0.0 <= c <= 1.0:
                ms.append(m)
                cs.append(c)
    return np.array(ms), np.array(cs)


def main() -> None:
    ms, cs = grid()
    vals = np.array([float(mean_cosine_plus_ref(m, c)) for m, c in zip(ms, cs, strict=True)])
    out = pathlib.Path(__file__).with_name("lobe_reference.npz")
    np.savez(out, m=ms, cos_theta=cs, mean_cosine_plus=vals, dps=DPS)
    print(f"wrote {out} ({len(ms)} points)")


if __name__ == "__main__":
    main()
