r"""Conventions of ppr, fixed once here (and pinned by ``tests/test_conventions.py``).

Directions
    All directions are unit 3-vectors pointing *away from the surface*: ``k_in`` points from
    the surface toward the source (laser), ``k_out`` from the surface toward the receiver.
    Exact monostatic backscatter is ``k_out == k_in``; the specular direction of ``k_in`` about
    a normal ``n`` is ``2 (k_in . n) n - k_in``. The half vector is
    ``h = (k_in + k_out) / |k_in + k_out|``. The light *propagates* along ``-k_in`` before the
    bounce and along ``+k_out`` after it.

Complex refractive index and time convention
    Fields vary as ``exp(i (k z - omega t))``; an absorbing medium has ``n = n' + i n''`` with
    ``n'' >= 0`` (metals have large ``n''``). Fresnel amplitude coefficients follow the
    Hecht/Born-Wolf form with the square root on the principal branch:

        r_s = (cos t - sqrt(n^2 - sin^2 t)) / (cos t + sqrt(n^2 - sin^2 t))
        r_p = (n^2 cos t - sqrt(n^2 - sin^2 t)) / (n^2 cos t + sqrt(n^2 - sin^2 t))

    so that at normal incidence ``r_s = -r_p = -(n-1)/(n+1)`` (the paper's eq. 10 has the
    opposite sign of ``r_s``; its eq. 10-11 give ``r_s = r_p`` at normal incidence).

Beam frames, Jones and Stokes
    Every beam carries a right-handed frame ``(x, y, d)`` with ``d`` its direction of
    *propagation* and ``x`` (the "frame vector") perpendicular to ``d``; ``y = d x x``.
    Jones vectors are the complex components ``(E_x, E_y)`` in that frame. For a reflection,
    the s axis is shared by incident and reflected beams (``s = normalize(k_in x k_out)`` for a
    facet, or ``normalize(n x k)`` for a plane of incidence; the two differ in sign, which
    changes nothing: flipping ``s`` flips both ``p`` axes) and ``p = d x s`` for each beam.
    In these s/p frames the Hecht coefficients above are the diagonal of the Jones matrix,
    a perfect conductor is ``J = diag(-1, +1)`` at every angle (tangential field reversed,
    normal field kept), so its ``M = diag(1, 1, -1, -1)``; at normal incidence every mirror
    (``r_s = -r_p``) gives ``M = R diag(1, 1, -1, -1)`` in any beam frames with
    ``x_out = x_in``: circular handedness is reversed.

    Stokes vectors:
        S0 = |E_x|^2 + |E_y|^2,  S1 = |E_x|^2 - |E_y|^2,
        S2 = 2 Re(E_x E_y^*),    S3 = -2 Im(E_x E_y^*)
    i.e. ``S = A (E (x) E^*)`` with ``A = [[1,0,0,1],[1,0,0,-1],[0,1,1,0],[0,1j,-1j,0]]``;
    Mueller matrices from Jones matrices are ``M = A (J (x) J^*) A^{-1}``. With fields
    ``exp(i(kz - wt))`` and S3 defined this way, S3 > 0 (e.g. Jones ``(1, i)/sqrt 2``) is a
    field that turns from ``x`` toward ``y``: right-handed about the propagation direction
    ``d`` (positive helicity), seen *counterclockwise* by a receiver looking back at the
    source. The state names ``"R"``/``"L"`` (``ppr.pulse._pulse.STOKES_STATES``, and the
    measurement states of ``inversion``) follow Chipman, Born & Wolf and Hecht ("clockwise
    looking at the source is right"): ``"R"`` is ``S3 = -1`` (Jones ``(1, -i)/sqrt 2``),
    ``"L"`` is ``S3 = +1`` (IEEE's right-hand circular). Those texts attach ``S3 > 0`` to their
    right-circular state, so their S3 is minus ppr's for the same field (pinned by 3D field
    computations in ``tests/test_conventions.py``; docs/physics/conventions.md). Mueller
    matrices multiply Stokes column vectors from the left: ``S_out = M @ S_in``; a chain of
    elements is ``M_N @ ... @ M_1``.

    Rotating a beam's frame vector by angle ``a`` about ``d`` (counter-clockwise looking
    against ``d``, i.e. right-handed about ``d``) changes Stokes components by
    ``S' = R(a) S`` with ``R(a) = [[1,0,0,0],[0,cos 2a, sin 2a,0],[0,-sin 2a,cos 2a,0],[0,0,0,1]]``
    and Jones components by ``E' = [[cos a, sin a], [-sin a, cos a]] E``. A facet's reflection
    in beam frames is ``R(b) F R(a)`` (``a``: ``x_in -> s`` about ``-k_in``; ``b``:
    ``s -> x_out`` about ``+k_out``), see :mod:`ppr.optics._frames`.

BRDF output
    ``mueller_brdf`` returns a 4x4 Mueller BRDF in 1/sr mapping the incident Stokes vector
    (frame of the beam travelling along ``-k_in``) to the outgoing radiance Stokes vector
    (frame of the beam travelling along ``+k_out``). Its M00 is the scalar BRDF ``f`` with
    ``integral f (k_out . n) d omega_out`` = directional albedo.

Units and time zero
    Lengths in metres, time in seconds, angles in radians in code (degrees only in configs
    and plots where the field name says ``_deg``). Range is one-way distance ``r = c t / 2``
    measured along the line of sight from a float64 reference range subtracted on the host;
    time zero of a profile is the return of a point at the reference range.
"""

C_LIGHT = 299_792_458.0
"""Speed of light in vacuum, m/s."""

DEFAULT_WAVELENGTH_M = 532e-9
"""Wavelength (m) every function and config uses when none is given: the frequency-doubled
Nd:YAG line of satellite laser ranging (the other PPR line is 1064 nm)."""
