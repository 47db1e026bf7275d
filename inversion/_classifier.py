r"""Weighted-inner-product classifier with an FFT search over the unknown range shift.

Score of an observation ``x`` against a template ``y`` (both (C, B): channels x range bins)
with non-negative weights ``w`` (C, B) attached to the *template's* range bins:

    s(x, y; k) = <x_k, w y> / (|x_k|_w |y|_w),   x_k(c, b) = x(c, b + k) (zero outside),
    |v|_w^2 = sum_cb w v^2,

maximized over integer shifts ``|k| <= max_shift``. ``s`` is invariant to the gain (it is a
cosine) and to the range offset (the shift absorbs it); ``s = 1`` iff ``x_k`` is a positive
multiple of ``y`` on the support of ``w``. All lags come from one zero-padded FFT per
observation and template (``n_fft >= 2 B - 1``, so correlation is linear, never circular):
numerator ``irfft(conj(F[w y]) F[x])`` summed over channels, observation norm
``irfft(conj(F[w]) F[x^2])``. The returned shift ``k`` is the estimated range offset of the
observation in bins (``x(b) ~ y(b - k)``), refined to sub-bin precision by a parabola through
the scores at ``k - 1, k, k + 1``.

Template spectra are precomputed once per weight design (:func:`prepare`) and scored in
equal chunks by one jitted function (padding rows score ``-inf``; at most 4096 rows, sized
to the bank so that little is padding), so a bank compiles one chunk shape; the top-k over all
chunks are returned.

Weight designs (:func:`design_weights`) for a target attribute with class labels ``l``
(shape, material, finish, or attitude = (shape, attitude index)) use per-feature between-class
and within-class variances of the normalized database signatures:

- ``uniform``: ``w = 1``;
- ``channel``: ``w_c = sum_b between_cb / sum_b within_cb`` (one weight per channel);
- ``range``: ``w_b = sum_c between_cb / sum_c within_cb`` (one weight per range bin);
- ``fisher``: ``w_cb = between_cb / (within_cb + eps)`` (diagonal Fisher discriminant ratio).

Each is scaled to mean 1 and floored at ``floor`` (default 1e-3) so no feature is dropped
entirely (a template never has zero norm).
"""

from __future__ import annotations

import functools
import json
import time
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

import ppr
from ppr.config import first_nonfinite
from ppr.geometry import quat_angle_deg, quat_multiply_host, quat_to_matrix_host

from ._database import TemplateBank
from ._grid import as_symmetry, los_half_turn
from ._noise import Observation, canonical_sensor

WEIGHT_KINDS = ("uniform", "channel", "range", "fisher")
ATTRIBUTES = ("shape", "material", "finish", "attitude")


def design_weights(
    bank: TemplateBank,
    kind: str = "uniform",
    attribute: str = "shape",
    floor: float = 1e-3,
    eps_rel: float = 1e-3,
) -> np.ndarray:
    """Weights (C, B) of design ``kind`` for recovering ``attribute`` (see module docstring)."""
    if kind not in WEIGHT_KINDS:
        raise ValueError(f"unknown weight design {kind!r}; use one of {WEIGHT_KINDS}")
    c, b = bank.n_channels, bank.n_bins
    if kind == "uniform":
        return np.ones((c, b), np.float32)
    return _weights_from(kind, *_class_variances(bank, attribute), floor, eps_rel)


def _class_variances(bank: TemplateBank, attribute: str) -> tuple[np.ndarray, np.ndarray]:
    """Between-class and within-class variance (C, B) of the bank's signatures for the class
    labels of ``attribute`` (what every design but ``uniform`` is made of)."""
    if len(bank) == 0:
        raise ValueError("design_weights: empty template bank")
    c, b = bank.n_channels, bank.n_bins
    labels = bank.labels(attribute)
    x = bank.signatures.reshape(len(bank), -1).astype(np.float64)
    mean = x.mean(axis=0)
    classes, inv = np.unique(labels, return_inverse=True)
    if len(classes) < 2:
        raise ValueError(f"design_weights: attribute {attribute!r} has a single class in the bank")
    counts = np.bincount(inv).astype(np.float64)
    sums = np.zeros((len(classes), x.shape[1]))
    np.add.at(sums, inv, x)
    mu = sums / counts[:, None]
    between = (counts[:, None] * (mu - mean) ** 2).sum(0) / len(x)
    within = ((x - mu[inv]) ** 2).sum(0) / len(x)
    return between.reshape(c, b), within.reshape(c, b)


def _weights_from(
    kind: str, between: np.ndarray, within: np.ndarray, floor: float = 1e-3, eps_rel: float = 1e-3
) -> np.ndarray:
    """Design ``kind`` (not ``uniform``) from :func:`_class_variances`."""
    if kind not in ("channel", "range", "fisher"):
        raise ValueError(f"unknown weight design {kind!r}; use one of {WEIGHT_KINDS}")
    c, b = between.shape
    eps = eps_rel * within.mean() + 1e-300
    if kind == "channel":
        w = np.broadcast_to((between.sum(1) / (within.sum(1) + eps * b))[:, None], (c, b))
    elif kind == "range":
        w = np.broadcast_to((between.sum(0) / (within.sum(0) + eps * c))[None, :], (c, b))
    else:
        w = between / (within + eps)
    w = np.asarray(w, np.float64)
    w = w / w.mean()
    return np.maximum(w, floor).astype(np.float32)


@dataclass
class PreparedBank:
    """One weight design applied to a bank: what :func:`classify` needs (device arrays).

    Exact mode (``rank=None``): template spectra ``F[w y / |y|_w]`` for every template, laid
    out ``(n_chunks, F, chunk, 2C)`` (real and imaginary parts side by side, so the channel sum
    is one batched matmul per frequency). Low-rank mode (``rank=K``): an orthonormal basis
    ``V`` (K, C*B) of the weighted normalized templates ``z_t = sqrt(w) y_t / |y_t|_w`` (SVD of
    up to ``svd_rows`` of them), coefficients ``A = Z V^T`` (T, K) and residuals
    ``r_t = |z_t - A_t V|``; scores are approximated by ``A G`` (``G`` the basis correlated
    with the observation) and certified: ``s_t <= A_t G + r_t`` for every shift, so after the
    top-``M`` upper bounds are rescored exactly, every further template whose bound still
    reaches the k-th exact score is rescored too: the result equals the exhaustive search
    (which is run instead if more than 16384 templates would need rescoring).
    """

    weights: np.ndarray
    n_fft: int
    n_templates: int
    chunk: int
    bank: TemplateBank
    w_re: jax.Array  # (C, F) spectrum of the weights
    w_im: jax.Array
    # per-chunk device arrays kept in lists: slicing one big array per call copies it
    spec: list | None = None  # exact: n_chunks x (F, chunk, 2C)
    valid: list | None = None  # n_chunks x (chunk,) bool
    rank: int | None = None
    coef: list | None = None  # n_chunks x (chunk, K)
    resid: list | None = None  # n_chunks x (chunk,); padding rows -inf
    basis_spec: jax.Array | None = None  # (F, K, 2C)


def _n_fft(b: int) -> int:
    n = 1
    while n < 2 * b - 1:
        n *= 2
    return n


def prepare(
    bank: TemplateBank,
    weights: np.ndarray | None = None,
    chunk: int | None = None,
    rank: int | None = None,
    svd_rows: int = 16384,
) -> PreparedBank:
    """Precompute what :func:`classify` needs for one weight design (see :class:`PreparedBank`)."""
    if len(bank) == 0:
        raise ValueError("prepare: empty template bank (no rows)")
    c, b = bank.n_channels, bank.n_bins
    w = np.ones((c, b), np.float32) if weights is None else np.asarray(weights, np.float32)
    if w.shape != (c, b):
        raise ValueError(f"weights have shape {w.shape}, the bank needs ({c}, {b})")
    if np.any(w < 0) or not np.all(np.isfinite(w)) or not np.any(w > 0):
        raise ValueError("weights must be finite, non-negative and not all zero")
    n_fft = _n_fft(b)
    t = len(bank)
    if chunk is None:  # at most 4096 (32768) rows, as few chunks as that allows, little padding
        n_chunks = -(-t // (4096 if rank is None else 32768))
        chunk = t if n_chunks == 1 else -(-t // (64 * n_chunks)) * 64
    chunk = int(min(chunk, t))
    n_chunks = -(-t // chunk)
    wj = jnp.asarray(w)
    wf = jnp.fft.rfft(wj, n_fft, axis=-1)
    valid = (np.arange(n_chunks * chunk) < t).reshape(n_chunks, chunk)
    prep = PreparedBank(
        w,
        n_fft,
        t,
        chunk,
        bank,
        jnp.real(wf).astype(jnp.float32),
        jnp.imag(wf).astype(jnp.float32),
        valid=[jnp.asarray(v) for v in valid],
    )

    def padded(i):
        y = np.zeros((chunk, c, b), np.float32)
        part = bank.signatures[i * chunk : (i + 1) * chunk]
        y[: len(part)] = part
        return jnp.asarray(y)

    if rank is None:
        prep.spec = [_template_spectra(padded(i), wj, n_fft) for i in range(n_chunks)]
        return prep
    rank = int(rank)
    if not 1 <= rank <= c * b:
        raise ValueError(f"rank must lie in [1, {c * b}], got {rank}")
    sel = np.linspace(0, t - 1, min(t, svd_rows)).astype(np.int64)
    z = np.asarray(_weighted_unit(jnp.asarray(bank.signatures[sel]), wj)).reshape(len(sel), -1)
    _, _, vt = np.linalg.svd(z.astype(np.float64), full_matrices=False)
    basis = jnp.asarray(vt[:rank], jnp.float32)  # (K, D)
    coefs, resids = [], []
    for i in range(n_chunks):
        a, r = _project(padded(i), wj, basis)
        coefs.append(a)
        resids.append(r)
    prep.rank = rank
    prep.coef = coefs
    prep.resid = [jnp.where(v, r, -jnp.inf) for v, r in zip(prep.valid, resids, strict=True)]
    vk = basis.reshape(rank, c, b) * jnp.sqrt(wj)[None]
    vf = jnp.fft.rfft(vk, n_fft, axis=-1)  # (K, C, F)
    prep.basis_spec = (
        jnp.concatenate([jnp.real(vf), jnp.imag(vf)], axis=1).transpose(2, 0, 1).astype(jnp.float32)
    )
    return prep


@jax.jit
def _weighted_unit(y, w):
    z = jnp.sqrt(w) * y
    nrm = jnp.sqrt(jnp.sum(z * z, axis=(1, 2)))
    return z / jnp.where(nrm > 0, nrm, 1.0)[:, None, None]


@jax.jit
def _project(y, w, basis):
    z = _weighted_unit(y, w).reshape(y.shape[0], -1)
    a = z @ basis.T
    r = jnp.sqrt(jnp.maximum(jnp.sum(z * z, axis=1) - jnp.sum(a * a, axis=1), 0.0))
    return a, r


@functools.partial(jax.jit, static_argnums=2)
def _template_spectra(y, w, n_fft):
    wy = w * y
    nrm = jnp.sqrt(jnp.sum(wy * y, axis=(1, 2)))
    wy = wy / jnp.where(nrm > 0, nrm, 1.0)[:, None, None]
    f = jnp.fft.rfft(wy, n_fft, axis=-1)  # (T, C, F)
    out = jnp.concatenate([jnp.real(f), jnp.imag(f)], axis=1)  # (T, 2C, F)
    return out.transpose(2, 0, 1).astype(jnp.float32)  # (F, T, 2C)


@functools.partial(jax.jit, static_argnames=("n_fft", "b", "max_shift"))
def _obs_terms(x, w_re, w_im, *, n_fft, b, max_shift):
    """Observation spectra as (F, 2C, 2N) right-hand side, and its weighted norm per lag."""
    x = x.astype(jnp.float32)
    xf = jnp.fft.rfft(x, n_fft, axis=-1)  # (N, C, F)
    x2f = jnp.fft.rfft(x * x, n_fft, axis=-1)
    wf = w_re + 1j * w_im
    nrm2 = jnp.fft.irfft(jnp.sum(jnp.conj(wf) * x2f, axis=1), n_fft, axis=-1)  # (N, n_fft)
    lags = jnp.arange(-max_shift, max_shift + 1)
    xnorm = jnp.sqrt(jnp.maximum(nrm2[:, lags % n_fft], 0.0))
    xr, xi = jnp.real(xf), jnp.imag(xf)
    # sum_c conj(Y) X = sum_c (Yr Xr + Yi Xi) + i (Yr Xi - Yi Xr)
    top = jnp.concatenate([xr, xi], axis=1)  # multiplies [Yr, Yi] -> real part
    bot = jnp.concatenate([xi, -xr], axis=1)  # -> imaginary part
    rhs = jnp.concatenate([top, bot], axis=0).transpose(2, 1, 0).astype(jnp.float32)  # (F, 2C, 2N)
    return rhs, xnorm


def _pick_max(a, b):
    """Reducer of :func:`_lag_max`: the larger score, the lower lag on a tie (``argmax``'s
    choice), carrying the lag and the scores of its two neighbours along."""
    (sa, ia, la, ha), (sb, ib, lb, hb) = a, b
    take_a = (sa > sb) | ((sa == sb) & (ia < ib))
    return tuple(jnp.where(take_a, u, v) for u, v in ((sa, sb), (ia, ib), (la, lb), (ha, hb)))


def _lag_max(corr, xnorm, max_shift, n_fft):
    """corr (T, N, n_fft), xnorm (N, L) -> best score, lag, sub-bin correction (N, T) over
    ``|lag| <= max_shift``.

    One pass over the scores (a variadic reduce carrying the running maximum, its lag and
    the scores at lag -1 and +1), so the (T, N, L) scores are never stored; the lag is the
    first maximum (``argmax``) and the neighbours are clamped at the ends of the lag range,
    as a gather at ``clip(best -+ 1)`` would give."""
    if max_shift == 0:
        corr = corr[..., :1]
    else:  # lags -max_shift .. max_shift: the circular correlation's last and first entries
        corr = jnp.concatenate([corr[..., n_fft - max_shift :], corr[..., : max_shift + 1]], -1)
    tiny = 1e-30
    xn = xnorm[None]
    s = jnp.where(xn > tiny, corr / jnp.maximum(xn, tiny), 0.0)
    prev = jnp.concatenate([s[..., :1], s[..., :-1]], -1)
    nxt = jnp.concatenate([s[..., 1:], s[..., -1:]], -1)
    idx_t = jax.dtypes.canonicalize_dtype(jnp.int_)
    idx = jax.lax.broadcasted_iota(idx_t, s.shape, 2)
    init = (
        jnp.array(-jnp.inf, s.dtype),
        jnp.array(jnp.iinfo(idx_t).max, idx_t),
        jnp.array(0, s.dtype),
        jnp.array(0, s.dtype),
    )
    sc, best, lo, hi = jax.lax.reduce((s, idx, prev, nxt), init, _pick_max, (2,))
    den = lo - 2 * sc + hi
    inner = (best > 0) & (best < 2 * max_shift) & (den < 0)
    frac = jnp.where(inner, 0.5 * (lo - hi) / jnp.where(inner, den, -1.0), 0.0)
    return sc.T, (best - max_shift).T, frac.T


@functools.partial(jax.jit, static_argnames=("n_fft", "max_shift"))
def _score_chunk(spec, valid, rhs, xnorm, *, n_fft, max_shift):
    """Exact best score, lag and sub-bin correction per (observation, template) of a chunk."""
    n = rhs.shape[-1] // 2
    z = jnp.einsum("ftk,fkm->ftm", spec, rhs)  # (F, T, 2N)
    # (T, N, F): moving F innermost keeps T and N in order (cheaper than (N, T, F))
    zc = jax.lax.complex(z[..., :n], z[..., n:]).transpose(1, 2, 0)
    corr = jnp.fft.irfft(zc, n_fft, axis=-1)  # (T, N, n_fft)
    sc, lag, frac = _lag_max(corr, xnorm, max_shift, n_fft)
    return jnp.where(valid[None, :], sc, -jnp.inf), lag, frac


@functools.partial(jax.jit, static_argnames=("n_fft", "max_shift"))
def _basis_corr(basis_spec, rhs, xnorm, *, n_fft, max_shift):
    """G (N, K, L): basis vectors correlated with the normalized observation at every lag."""
    n = rhs.shape[-1] // 2
    z = jnp.einsum("fkc,fcm->fkm", basis_spec, rhs)  # (F, K, 2N)
    zc = (z[..., :n] + 1j * z[..., n:]).transpose(2, 1, 0)  # (N, K, F)
    corr = jnp.fft.irfft(zc, n_fft, axis=-1)
    lags = jnp.arange(-max_shift, max_shift + 1)
    corr = corr[..., lags % n_fft]
    tiny = 1e-30
    return jnp.where(xnorm[:, None, :] > tiny, corr / jnp.maximum(xnorm[:, None, :], tiny), 0.0)


@jax.jit
def _bound_chunk(coef, resid, g):
    """Upper bound max_lag (A G) + r per (observation, template) of a chunk."""
    approx = jnp.einsum("tk,nkl->ntl", coef, g)
    return jnp.max(approx, axis=-1) + resid[None, :]


@dataclass
class Classification:
    """Top-k candidates per observation: rows of the bank, scores, shifts (bins).

    With a noise model (``classify(..., noise=...)``) also, per observation, `fit`: the
    :class:`~inversion.GoodnessOfFit` of the best template (gain and sub-bin shift fitted,
    the bank's resolution allowed for; :mod:`inversion._template_fit`) and
    `no_template_fits`: its ``model_mismatch``, i.e. no template of the bank explains the
    observation within its noise (a shape, or a material or roughness, the bank lacks).

    `no_signal` flags the observations without a single positive value: every channel is a
    non-negative intensity, so such a frame holds no return (an empty or fully
    background-subtracted frame) and its candidates are arbitrary (scores 0); it is flagged,
    not dropped, so a batch keeps its order.
    """

    index: np.ndarray  # (N, k) int
    score: np.ndarray  # (N, k)
    shift: np.ndarray  # (N, k) integer lag of the best score
    shift_refined: np.ndarray  # (N, k) parabolic sub-bin estimate
    seconds: float
    certified: np.ndarray  # (N,) bool: result provably equals the exhaustive search
    n_rescored: np.ndarray | None = None  # (N,) templates scored exactly (low-rank mode)
    fit: tuple | None = None  # (N,) GoodnessOfFit of the best template (with a noise model)
    no_template_fits: np.ndarray | None = None  # (N,) bool (with a noise model)
    no_signal: np.ndarray | None = None  # (N,) bool: no positive value in the frame

    def best(self, bank: TemplateBank) -> dict:
        """Attributes of the top candidate of each observation."""
        i = self.index[:, 0]
        return {
            "row": i,
            "shape_id": bank.shape_id[i],
            "material_id": bank.material_id[i],
            "finish_id": bank.finish_id[i],
            "quat": bank.quat[i],
            "score": self.score[:, 0],
            "shift": self.shift[:, 0],
        }

    def candidates(
        self, bank: TemplateBank, k: int = 3, per_shape: int = 1, obs: int = 0
    ) -> np.ndarray:
        """Columns of ``index[obs]`` to refine: the top ``k``, plus the best ``per_shape``
        candidates of every shape of ``bank`` (in rank order, without repeats).

        The classifier's rank is not a likelihood: a shape whose signature changes fast with
        attitude (a cube) can rank below hundreds of templates of other shapes at the grid
        resolution and still fit far better once refined. Refining each shape's best
        candidates lets the likelihood choose the shape. Classify with ``k = len(bank)``
        (ranks every template; cheap) so that every shape has its candidates; a
        classification cut shorter that misses a shape raises ``ValueError``.
        """
        if k < 0 or per_shape < 0:
            raise ValueError(f"candidates: k={k} and per_shape={per_shape} must be >= 0")
        if not 0 <= obs < len(self.index):
            raise ValueError(f"candidates: obs={obs} outside [0, {len(self.index)})")
        sid = np.asarray(bank.shape_id)[self.index[obs]]
        cols = list(range(min(k, len(sid))))
        for s in np.unique(bank.shape_id):
            found = np.flatnonzero(sid == s)
            if len(found) < min(per_shape, int(np.sum(bank.shape_id == s))):
                name = bank.names.get("shapes", [])
                name = name[s] if s < len(name) else str(s)
                raise ValueError(
                    f"candidates: shape {name!r} has {len(found)} of per_shape={per_shape} "
                    f"candidates among the classification's {len(sid)} columns; classify "
                    f"with a larger k (k=len(bank) ranks every template)"
                )
            cols += [int(c) for c in found[:per_shape] if c not in cols]
        return np.asarray(sorted(cols), dtype=int)


def _sensor_diff(a: str, b: str) -> str:
    da, db = json.loads(a), json.loads(b)
    keys = sorted(set(da) | set(db))
    return "; ".join(
        f"{k}: observation {da.get(k)!r} != database {db.get(k)!r}"
        for k in keys
        if da.get(k) != db.get(k)
    )


def check_observations(prep: PreparedBank, obs, dtype=np.float32) -> np.ndarray:
    """Stack observations to (N, C, B) (float32: the scores') after checking them against
    the bank."""
    bank = prep.bank
    items = obs if isinstance(obs, list | tuple) else [obs]
    datas = []
    for o in items:
        if isinstance(o, Observation):
            if o.sensor and bank.sensor and canonical_sensor(o.sensor) != bank.sensor:
                raise ValueError(
                    "observation was taken with other sensor settings than the database was built "
                    "with: " + _sensor_diff(canonical_sensor(o.sensor), bank.sensor)
                )
            d = np.asarray(o.data)
        else:
            d = np.asarray(o)
        datas.append(d)
    x = np.stack(datas) if not (len(items) == 1 and np.asarray(datas[0]).ndim == 3) else datas[0]
    if x.ndim != 3:
        raise ValueError(f"observations must be (C, B) or (N, C, B), got shape {x.shape}")
    if x.shape[1] != bank.n_channels:
        raise ValueError(
            f"observation has {x.shape[1]} channels, the database has {bank.n_channels}"
        )
    if x.shape[2] != bank.n_bins:
        raise ValueError(
            f"observation has n_bins={x.shape[2]}, the database has n_bins={bank.n_bins}"
        )
    bad = first_nonfinite(x)
    if bad is not None:
        raise ValueError(
            f"observation contains {bad[0]} non-finite value(s), first at index {bad[1]} "
            "(observation, channel, bin)"
        )
    out = x.astype(dtype)
    over = ~np.isfinite(out)
    if over.any():  # finite, but beyond the database's precision
        first = tuple(int(i) for i in np.argwhere(over)[0])
        raise ValueError(
            f"observation value {float(x[first]):g} at index {first} (observation, channel, "
            f"bin) overflows {np.dtype(dtype).name}, the database's precision; rescale the data"
        )
    return out


def classify(
    prep: PreparedBank,
    obs,
    k: int = 5,
    max_shift: int | None = None,
    n_candidates: int | None = None,
    *,
    noise=None,
    threshold: float = 1e-3,
    neighbours: int = 4,
    resolution_scale: float = 1.0,
) -> Classification:
    """Top-``k`` templates of ``prep`` for each observation (an :class:`Observation`, a list
    of them, or an array (C, B) / (N, C, B)), maximizing the score over shifts
    ``|shift| <= max_shift`` bins (default: all ``B - 1``). In low-rank mode the top
    ``n_candidates`` (default ``max(64, 8 k)``) upper bounds are rescored exactly; see
    :class:`PreparedBank` for the certificate (``Classification.certified``).

    With `noise` (the observations' noise model, e.g. ``PoissonCounts()`` for photo-counts)
    the best template of each observation is also fitted and tested against the noise,
    allowing for the bank's resolution (:func:`inversion._template_fit.template_goodness_of_fit`
    with `threshold`, `neighbours`, `resolution_scale`): ``Classification.fit`` and
    ``Classification.no_template_fits``."""
    x = check_observations(prep, obs)
    b = prep.bank.n_bins
    max_shift = b - 1 if max_shift is None else int(max_shift)
    if not 0 <= max_shift <= b - 1:
        raise ValueError(f"max_shift must lie in [0, {b - 1}], got {max_shift}")
    k = int(min(k, prep.n_templates))
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    t0 = time.perf_counter()
    rhs, xnorm = _obs_terms(
        jnp.asarray(x), prep.w_re, prep.w_im, n_fft=prep.n_fft, b=b, max_shift=max_shift
    )
    if prep.rank is None:
        idx, sc, lg, fr = _exact_all(prep, rhs, xnorm, max_shift, k)
        certified = np.ones(len(x), bool)
        n_rescored = np.full(len(x), prep.n_templates)
    else:
        idx, sc, lg, fr, certified, n_rescored = _lowrank(
            prep, x, rhs, xnorm, max_shift, k, n_candidates
        )
    res = Classification(idx, sc, lg, lg + fr, time.perf_counter() - t0, certified, n_rescored)
    res.no_signal = ~np.any(np.asarray(x) > 0, axis=(1, 2))
    if noise is None:
        return res
    from ._template_fit import template_goodness_of_fit

    fits = template_goodness_of_fit(
        prep,
        check_observations(prep, obs, np.float64),
        res,
        noise,
        threshold=threshold,
        neighbours=neighbours,
        resolution_scale=resolution_scale,
    )
    res.fit = fits
    res.no_template_fits = np.array([f.model_mismatch for f in fits])
    res.seconds = time.perf_counter() - t0
    return res


def _exact_all(prep, rhs, xnorm, max_shift, k):
    spec = prep.spec
    chunks = range(len(prep.valid))
    if spec is None:  # low-rank bank: spectra on the fly
        wj = jnp.asarray(prep.weights)
        sigs = prep.bank.signatures

        def spec_of(i):
            y = np.zeros((prep.chunk, *sigs.shape[1:]), np.float32)
            part = sigs[i * prep.chunk : (i + 1) * prep.chunk]
            y[: len(part)] = part
            return _template_spectra(jnp.asarray(y), wj, prep.n_fft)
    else:

        def spec_of(i):
            return spec[i]

    out = [
        _score_chunk(spec_of(i), prep.valid[i], rhs, xnorm, n_fft=prep.n_fft, max_shift=max_shift)
        for i in chunks
    ]
    res = _merge_topk(*(jnp.concatenate([o[j] for o in out], 1) for j in range(3)), k)
    return tuple(np.asarray(a) for a in res)


def _lowrank(prep, x, rhs, xnorm, max_shift, k, n_candidates, max_rescore=16384):
    """Bound every template, rescore exactly the top ``m`` bounds, then every template whose
    bound still reaches the k-th best exact score (so the result is the exhaustive one);
    exhaustive search only if more than ``max_rescore`` templates would need rescoring."""
    g = _basis_corr(prep.basis_spec, rhs, xnorm, n_fft=prep.n_fft, max_shift=max_shift)
    bound = jnp.concatenate(
        [_bound_chunk(a, r, g) for a, r in zip(prep.coef, prep.resid, strict=True)], 1
    )
    m = int(min(prep.n_templates, max(64, 8 * k) if n_candidates is None else n_candidates))
    m = max(m, k)
    _, cand = jax.lax.top_k(bound, m)
    cand = np.asarray(cand)
    bound = np.asarray(bound)
    wj = jnp.asarray(prep.weights)
    n = len(x)
    out = [
        np.zeros((n, k), np.int64),
        np.zeros((n, k), np.float32),
        np.zeros((n, k), np.int64),
        np.zeros((n, k), np.float32),
    ]
    n_rescored = np.zeros(n, np.int64)
    sigs = prep.bank.signatures

    def rescore(j, rows):
        """Exact (score, lag, frac) of ``rows`` for observation j, in padded buckets."""
        size = 64
        while size < len(rows):
            size *= 2
        pad = np.zeros(size, np.int64)
        pad[: len(rows)] = rows
        spec = _template_spectra(jnp.asarray(sigs[pad]), wj, prep.n_fft)
        sc, lag, fr = _score_chunk(
            spec,
            jnp.asarray(np.arange(size) < len(rows)),
            rhs[..., [j, n + j]],
            xnorm[j : j + 1],
            n_fft=prep.n_fft,
            max_shift=max_shift,
        )
        return (np.asarray(a[0])[: len(rows)] for a in (sc, lag, fr))

    for j in range(n):
        rows = cand[j]
        sc, lag, fr = rescore(j, rows)
        tau = np.sort(sc)[-k]
        need = np.nonzero(bound[j] >= tau)[0]
        extra = np.setdiff1d(need, rows, assume_unique=False)
        if len(extra) > max_rescore:
            xi = rhs[..., [j, n + j]]
            vals = [a[0] for a in _exact_all(prep, xi, xnorm[j : j + 1], max_shift, k)]
            n_rescored[j] = prep.n_templates
        else:
            if len(extra):
                sc2, lag2, fr2 = rescore(j, extra)
                rows = np.concatenate([rows, extra])
                sc, lag, fr = (np.concatenate(p) for p in ((sc, sc2), (lag, lag2), (fr, fr2)))
            order = np.argsort(-sc, kind="stable")[:k]
            vals = (rows[order], sc[order], lag[order], fr[order])
            n_rescored[j] = len(rows)
        for dst, v in zip(out, vals, strict=True):
            dst[j] = v
    # every template whose bound reaches the final k-th score was scored exactly: exact result
    return (*out, np.ones(n, bool), n_rescored)


@functools.partial(jax.jit, static_argnums=3)
def _merge_topk(scores, lags, fracs, k):
    sc, idx = jax.lax.top_k(scores, k)
    return idx, sc, jnp.take_along_axis(lags, idx, 1), jnp.take_along_axis(fracs, idx, 1)


def score_pair(x: np.ndarray, y: np.ndarray, w: np.ndarray, shift: int) -> float:
    """Direct (non-FFT) score at one shift, float64 NumPy; reference for the tests."""
    x, y, w = (np.asarray(a, np.float64) for a in (x, y, w))
    b = x.shape[-1]
    xs = np.zeros_like(x)
    lo, hi = max(0, -shift), min(b, b - shift)
    xs[:, lo:hi] = x[:, lo + shift : hi + shift]
    num = np.sum(w * xs * y)
    den = np.sqrt(np.sum(w * xs * xs) * np.sum(w * y * y))
    return float(num / den) if den > 0 else 0.0


def _equivalents(q_est, symmetry, mirror: bool, half_turn: bool = False) -> np.ndarray:
    """``(N, G', 4)``: the attitudes equivalent to each estimate, ``q g`` for the rotations
    ``g`` of the symmetry; with ``mirror`` also the mirror images ``P q S`` for its improper
    elements ``S`` (:func:`inversion.mirror_attitude`); with ``half_turn`` also all of those
    turned by 180 deg about the line of sight (:func:`inversion.los_half_turn`).

    ``symmetry``: a named class, a ``(G, 4)`` array of rotations (no improper elements), a
    :class:`ppr.MeshSymmetry` or a :class:`ppr.Mesh` (:func:`inversion.as_symmetry`)."""
    q_est = np.atleast_2d(q_est)
    if isinstance(symmetry, np.ndarray | list | tuple):
        g, sym = np.asarray(symmetry, np.float64), None
    else:
        sym = as_symmetry(symmetry)
        g = sym.quaternions()
    cand = quat_multiply_host(q_est[:, None, :], g[None, :, :])
    if mirror:
        if sym is None or len(sym.improper) == 0:
            raise ValueError(
                "mirror=True needs a symmetry with a mirror plane or another improper element "
                f"(dihedral:n, octahedral, or a mesh that has one), got {_describe(symmetry)}"
            )
        # P R S = C2(w) R (-S), -S proper; world mirror normal +y
        minus_s = np.stack([ppr.matrix_to_quat(-s) for s in sym.improper])
        w = np.array([0.0, 0.0, 1.0, 0.0])
        img = quat_multiply_host(quat_multiply_host(w, q_est)[:, None, :], minus_s[None, :, :])
        cand = np.concatenate([cand, img], 1)
    if half_turn:
        cand = np.concatenate([cand, los_half_turn(cand)], 1)
    return cand


def _describe(symmetry) -> str:
    if isinstance(symmetry, str):
        return repr(symmetry)
    if isinstance(symmetry, ppr.MeshSymmetry):
        return f"a mesh group {symmetry.point_group}"
    if isinstance(symmetry, ppr.Mesh):
        return f"a mesh of group {as_symmetry(symmetry).point_group}"
    return f"an array of {len(np.atleast_2d(symmetry))} rotations"


def _symmetry_arg(symmetry, mesh):
    if mesh is None:
        return symmetry
    if not (isinstance(symmetry, str) and symmetry == "none"):
        raise ValueError(f"pass either symmetry ({_describe(symmetry)}) or mesh, not both")
    if not isinstance(mesh, ppr.Mesh | ppr.MeshSymmetry):
        raise ValueError(f"mesh must be a ppr.Mesh or ppr.MeshSymmetry, got {type(mesh).__name__}")
    return mesh


def attitude_error_deg(
    q_true,
    q_est,
    symmetry="none",
    *,
    mirror: bool = False,
    half_turn: bool = False,
    mesh=None,
) -> np.ndarray:
    """Geodesic angle (deg) between attitudes modulo the shape's symmetry group; with
    ``mirror=True`` also modulo the mirror images (:func:`inversion.mirror_attitude`, world
    mirror through the sensor's x-z plane, with every improper element of the body); with
    ``half_turn=True`` also modulo a half turn about the line of sight
    (:func:`inversion.los_half_turn`), an exact symmetry of every monostatic measurement.

    ``symmetry``: a named class (``"dihedral:4"``), ``(G, 4)`` rotations, or a
    :class:`ppr.MeshSymmetry`; or pass ``mesh=`` (a :class:`ppr.Mesh`, whose own group
    :func:`ppr.mesh_symmetries` finds, or a :class:`ppr.MeshSymmetry`) instead."""
    q_true = np.atleast_2d(q_true)
    cand = _equivalents(q_est, _symmetry_arg(symmetry, mesh), mirror, half_turn)
    return quat_angle_deg(q_true[:, None, :], cand).min(axis=1)


def line_of_sight_error_deg(
    q_true, q_est, symmetry="none", *, mirror: bool = False, mesh=None, los=None
) -> np.ndarray:
    """Angle (deg) between the true and estimated line of sight *in the body frame*
    (``R^T k`` with ``k`` the world direction to the sensor, `los`, default ``+z``), modulo
    the symmetry (``symmetry`` or ``mesh=`` as in :func:`attitude_error_deg`).

    A monostatic range profile depends on the attitude only through this direction; the roll
    about the line of sight enters through the polarization alone, so this error is the
    well-conditioned part of the attitude error.

    ``mirror=True`` also counts the mirrored line of sight ``S v`` as equal for the improper
    elements ``S`` of the body (a mirror plane, :func:`inversion.body_mirror_normal`): the
    mirror image of the scene gives the same range profiles and differs only in the
    off-block Mueller elements (:func:`inversion.mirror_attitude`), which glossy targets do
    not show at all.
    """
    q_true = np.atleast_2d(q_true)
    cand = _equivalents(q_est, _symmetry_arg(symmetry, mesh), mirror)  # (N, G, 4)
    los_t = _body_los(q_true, los)[:, None, :]
    los_e = _body_los(cand, los)
    cos = np.clip(np.sum(los_t * los_e, axis=-1), -1.0, 1.0)
    return np.degrees(np.arccos(cos)).min(axis=1)


def _body_los(q: np.ndarray, los=None) -> np.ndarray:
    """``R(q)^T k``: the world line of sight ``k`` (toward the sensor, default ``+z``: the
    third row of ``R``) in body coordinates; batched over ``q (..., 4)``."""
    q = np.asarray(q, np.float64)
    if los is not None:
        k = np.asarray(los, np.float64)
        return np.einsum("...ij,i->...j", quat_to_matrix_host(q), k / np.linalg.norm(k))
    w, x, y, z = np.moveaxis(q / np.linalg.norm(q, axis=-1, keepdims=True), -1, 0)
    return np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)
