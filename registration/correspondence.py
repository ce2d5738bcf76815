"""Correspondence of two point constellations under a smooth deformation (inclusion tracking).

:func:`match_constellation` gives every point of a scan (inclusion centres mapped into the
reference frame by the fiducial registration) the identity of a reference point, or none,
all at once: the sizes of the points, their relative positions and a smooth deformation
prior decide together, so a large motion (tens of millimetres, more than the spacing of
the points) keeps every identity. Four stages:

1. **Initial maps**: the identity (the rigid registration has removed the rigid motion);
   with anchors (points of known correspondence, e.g. the nipple) their mean translation
   and, given a base plane, their displacement as a shear growing from the plane; and the
   two best affine maps of a size-gated RANSAC (Fischler & Bolles 1981): minimal samples
   of size-compatible pairs (three plus one anchor, or four) scored by how many
   reference points land near a scan point.
2. **Coherent point drift** (Myronenko & Song 2010) from each map, affine then
   non-rigid, with the sizes as a fixed-variance feature of each Gaussian component
   and the anchors as points of known assignment.
3. **Assignment with a leave-one-out field**: the displacement of the matched points
   is modelled as a Gaussian process with an affine mean (Rasmussen & Williams 2006,
   §2.7), kernel width and noise by restricted maximum likelihood. Each reference
   point's position is predicted from all *other* matches (Rippa 1999's closed form),
   so no match explains itself; a one-to-one assignment
   (``scipy.optimize.linear_sum_assignment``, Crouse 2016) of the negative
   log-likelihoods (a Student t of the position, the size difference, and dummy rows
   and columns for a missed reference point or an extra detection) is solved and the
   field refitted until the assignment repeats.
4. **Rating**: every candidate assignment is rated by its whole negative
   log-likelihood ``C`` (:func:`_score`: the joint Gaussian-process density of the
   matched displacements, the size densities, the miss and extra probabilities), the
   lowest wins. For every identity, rivals that change it are generated (the best
   assignment forbidding it, with the field held and refitted; for a match also the
   same assignment without it) and rated; a better rival is adopted. The
   **confidence** of an identity is ``1 / (1 + exp(-(C' - C*)))``, ``C*`` the chosen
   assignment's and ``C'`` the best rated assignment's that changes this identity:
   the posterior probability of the identity against its best competitor (equal
   priors). 0.5 is a tie; 0.95 means the competitor is 19 times less likely.

Pure numpy/scipy; no dependency on how the scans were made.

References
----------
Myronenko A, Song X (2010) Point set registration: coherent point drift. IEEE TPAMI
32(12):2262-2275.
Rasmussen CE, Williams CKI (2006) Gaussian Processes for Machine Learning. MIT Press.
Fischler MA, Bolles RC (1981) Random sample consensus. Commun ACM 24(6):381-395.
Rippa S (1999) An algorithm for selecting a good value for the parameter c in radial basis
function interpolation. Adv Comput Math 11:193-210.
Crouse DF (2016) On implementing 2D rectangular assignment algorithms. IEEE TAES
52(4):1679-1696.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from registration.errors import RegistrationError

__all__ = [
    "CONFIDENCE_DEFINITION",
    "AmbiguousMatchWarning",
    "ConstellationError",
    "ConstellationMatch",
    "match_constellation",
]

log = logging.getLogger(__name__)

#: One-line definition of :attr:`ConstellationMatch.confidence` (for output files).
CONFIDENCE_DEFINITION = (
    "two-way posterior probability (equal priors) of this identity against the best "
    "competing one-to-one assignment of the whole constellation alone (further rivals "
    "would lower it): 1 / (1 + exp(-(C' - C*))), C* the chosen "
    "assignment's negative log-likelihood (sizes, positions under a smooth Gaussian-"
    "process deformation, missed and extra detections), C' that of the best rated "
    "assignment that changes this identity (0.5: a tie; 0.95: the competitor is 19 "
    "times less likely)"
)

#: Degrees of freedom of the Student t likelihood of a predicted position in the
#: assignment costs (heavier tails than a Gaussian: a leave-one-out prediction 4 sd off
#: costs 6.2 log-units instead of 8, one 6 sd off 9.9 instead of 18).
_T_DOF = 10.0
#: A rival assignment within this many log-likelihood units gets its own refitted field.
_REFIT_BELOW = 15.0
#: Noise of an anchor's displacement in the field, in units of the field's amplitude
#: variance: an anchor (the nipple: a surface landmark, not a material point) guides the
#: field without pinning it.
_ANCHOR_NOISE = 1.0
_CHI2_3_MEDIAN = 2.3660  # median of the chi-square distribution with 3 degrees of freedom
_BIG = 1.0e9  # cost of a forbidden cell of the assignment matrix (finite: always feasible)
_LOG2PI = math.log(2.0 * math.pi)


class ConstellationError(RegistrationError):
    """Bad input to :func:`match_constellation` (shapes, non-finite values, sizes)."""


class AmbiguousMatchWarning(UserWarning):
    """A correspondence that a competing assignment explains about as well (low confidence)."""


@dataclass(frozen=True, eq=False)
class ConstellationMatch:
    """Identity of every point of a scan constellation among the reference points.

    Attributes
    ----------
    reference_index : numpy.ndarray of int, shape (m,)
        Reference point matched by each scan point; -1 for none (an extra detection).
    confidence : numpy.ndarray, shape (m,)
        Confidence of each scan point's identity (matched or unmatched), see
        :data:`CONFIDENCE_DEFINITION`.
    runner_up : numpy.ndarray of int, shape (m,)
        The identity each scan point has in the best rated assignment that changes it
        (-1: unmatched there).
    scan_index : numpy.ndarray of int, shape (n,)
        Scan point matched by each reference point; -1 for none (missed in this scan).
    reference_confidence : numpy.ndarray, shape (n,)
        The same confidence seen from each reference point.
    reference_runner_up : numpy.ndarray of int, shape (n,)
        The scan point each reference point has in the best rated assignment that
        changes its match (-1: unmatched there).
    reference_alternatives : tuple of tuple of (int, float)
        Per reference point, every other partner it has in a rated assignment, as
        ``(scan index or -1, probability against the chosen one)``, most probable first
        (those above 0.001): the candidates of an ambiguous match.
    predicted_mm : numpy.ndarray, shape (n, 3)
        Each reference point's position predicted from all *other* matches (the
        leave-one-out field), reference frame, mm.
    predicted_sd_mm : numpy.ndarray, shape (n,)
        Per-axis standard deviation of that prediction, mm.
    cost : float
        Negative log-likelihood ``C*`` of the chosen assignment (see the module doc).
    hypothesis : str
        The initial map the chosen solution started from (``+ local search`` for each
        time a better rival was adopted).
    field_checked : bool
        True when the chosen assignment, and each rival that drops one of its matches,
        holds enough matches to fit a deformation field (with the anchors, at least two
        more sites than the field's mean has coefficients). False for a constellation of
        one or two points: a match is then rated by size and the initial maps alone (a
        missed point against an extra detection is not weighed by position), and the
        confidences do not mean what they say.
    """

    reference_index: np.ndarray
    confidence: np.ndarray
    runner_up: np.ndarray
    scan_index: np.ndarray
    reference_confidence: np.ndarray
    reference_runner_up: np.ndarray
    reference_alternatives: tuple
    predicted_mm: np.ndarray
    predicted_sd_mm: np.ndarray
    cost: float
    hypothesis: str
    field_checked: bool = True

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            v = getattr(self, name)
            if isinstance(v, np.ndarray):
                v = v.copy()
                v.flags.writeable = False
                object.__setattr__(self, name, v)

    def residual_mm(self, points_mm: np.ndarray) -> np.ndarray:
        """Distance of each matched scan point from its leave-one-out prediction.

        Parameters
        ----------
        points_mm : array_like, shape (m, 3)
            The scan points given to :func:`match_constellation`.

        Returns
        -------
        numpy.ndarray, shape (m,)
            Millimetres; NaN for unmatched scan points.
        """
        p = np.asarray(points_mm, float).reshape(-1, 3)
        out = np.full(len(p), np.nan)
        ok = self.reference_index >= 0
        out[ok] = np.linalg.norm(p[ok] - self.predicted_mm[self.reference_index[ok]], axis=1)
        return out


# --------------------------------------------------------------------------------------
# input checks


def _points(a, name: str) -> np.ndarray:
    p = np.array(a, dtype=float, copy=True)
    if p.size == 0:
        return p.reshape(0, 3)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ConstellationError(f"{name}: expected an (n, 3) array of points, got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ConstellationError(f"{name}: contains NaN or infinite coordinates")
    return p


def _sizes(a, n: int, name: str) -> np.ndarray:
    d = np.array(a, dtype=float, copy=True).reshape(-1)
    if len(d) != n:
        raise ConstellationError(f"{name}: {len(d)} sizes for {n} points")
    if not np.all(np.isfinite(d)) or np.any(d <= 0):
        raise ConstellationError(f"{name}: sizes must be finite and positive, got {d.tolist()}")
    return d


# --------------------------------------------------------------------------------------
# the size likelihood


def _size_logpdf(d_ref: np.ndarray, d: np.ndarray, sd_mm: float, span_mm: float) -> np.ndarray:
    """Log density (n, m) of the size difference: Gaussian, with 0.5 % of a uniform tail.

    Two measurements of sd ``sd_mm`` differ with sd ``sqrt(2) sd_mm``; the uniform tail
    (over ``span_mm``) keeps one badly measured size from vetoing a match.
    """
    s = math.sqrt(2.0) * sd_mm
    diff = d[None, :] - d_ref[:, None]
    gauss = -0.5 * (diff / s) ** 2 - math.log(s) - 0.5 * _LOG2PI
    return np.logaddexp(math.log(0.995) + gauss, math.log(0.005 / span_mm))


# --------------------------------------------------------------------------------------
# coherent point drift with sizes and anchors (stage 2)


def _gauss_kernel(a: np.ndarray, b: np.ndarray, beta: float) -> np.ndarray:
    d2 = ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)
    return np.exp(-d2 / (2.0 * beta**2))


def _e_step(TX, Y, log_size, sigma2, log_outlier):
    """CPD posteriors P (n, m) with sizes; returns P and the data log-likelihood."""
    n = len(TX)
    d2 = ((Y[None, :, :] - TX[:, None, :]) ** 2).sum(-1)
    logp = -d2 / (2.0 * sigma2) - 1.5 * (_LOG2PI + math.log(sigma2)) + log_size - math.log(n)
    top = np.maximum(logp.max(0), log_outlier)
    e = np.exp(logp - top)
    lse = top + np.log(e.sum(0) + np.exp(log_outlier - top))
    return e * np.exp(top - lse)[None, :], float(lse.sum()), d2


def _affine_solve(X, targets, w, B_prior, ridge):
    """Weighted least squares ``targets ~ X B^T + t`` with a ridge pulling B to ``B_prior``."""
    sw = np.sqrt(np.maximum(w, 0.0))[:, None]
    H = np.column_stack([X, np.ones(len(X))]) * sw
    rhs = targets * sw
    reg = np.sqrt(ridge) * np.eye(4)[:3]  # rows on the B part only
    H = np.vstack([H, reg])
    rhs = np.vstack([rhs, np.sqrt(ridge) * B_prior.T])
    sol, *_ = np.linalg.lstsq(H, rhs, rcond=None)
    return sol[:3].T, sol[3]


def _cpd(
    X, Y, log_size, log_outlier, anchors, anchor_sd, B0, t0, sigma0,
    *, beta, lam, spread, max_iter, tol,
):  # fmt: skip
    """Affine then non-rigid CPD from the initial map ``x -> B0 x + t0``; returns T(X).

    ``sigma0`` None starts from CPD's usual variance (the mean squared distance of all
    pairs: the initial map hardly matters), a value from that sd (the map matters).
    """
    A_ref, A = anchors
    k = len(A_ref)
    B, t = B0.copy(), t0.copy()
    TX = X @ B.T + t
    if sigma0 is None:
        sigma2 = max(float(((Y[None] - TX[:, None]) ** 2).sum() / (3 * len(X) * len(Y))), 1.0)
    else:
        sigma2 = float(sigma0) ** 2
    floor2 = (1e-3 * spread) ** 2
    ridge_unit = 1e-2 * spread**2
    prev = -np.inf
    for _ in range(max_iter):  # affine stage, Eq. (7) of Myronenko & Song with anchors
        P, ll, _ = _e_step(TX, Y, log_size, sigma2, log_outlier)
        P1 = P.sum(1)
        targets = np.vstack([P @ Y / np.maximum(P1, 1e-300)[:, None], A])
        w = np.concatenate([P1 / sigma2, np.full(k, 1.0 / anchor_sd**2)])
        B, t = _affine_solve(np.vstack([X, A_ref]), targets, w, B, ridge_unit * w.sum())
        TX = X @ B.T + t
        d2 = ((Y[None] - TX[:, None]) ** 2).sum(-1)
        sigma2 = max(float((P * d2).sum() / (3.0 * max(P.sum(), 1e-12))), floor2)
        if abs(ll - prev) <= tol * abs(ll):
            break
        prev = ll
    X0 = np.vstack([X, A_ref]) @ B.T + t  # affine-aligned reference points and anchors
    G = _gauss_kernel(X0, X0, beta)
    W = np.zeros_like(X0)
    prev = -np.inf
    for _ in range(max_iter):  # non-rigid stage, Eq. (14) of Myronenko & Song with anchors
        TXa = X0 + G @ W
        P, ll, d2 = _e_step(TXa[: len(X)], Y, log_size, sigma2, log_outlier)
        P1 = np.concatenate([P.sum(1), np.full(k, sigma2 / anchor_sd**2)])
        PY = np.vstack([P @ Y, P1[len(X) :, None] * A])
        W = np.linalg.solve(P1[:, None] * G + lam * sigma2 * np.eye(len(X0)), PY - P1[:, None] * X0)
        TXa = X0 + G @ W
        d2 = ((Y[None] - TXa[: len(X), None]) ** 2).sum(-1)
        sigma2 = max(float((P * d2).sum() / (3.0 * max(P.sum(), 1e-12))), floor2)
        if abs(ll - prev) <= tol * abs(ll):
            break
        prev = ll
    return TXa[: len(X)], math.sqrt(sigma2)


# --------------------------------------------------------------------------------------
# initial maps: the anchors, a size-gated RANSAC over affine maps (stage 1)


def _anchor_maps(A_ref, A, base_plane, spread):
    maps = {}
    if not len(A_ref):
        return maps
    d = (A - A_ref).mean(0)
    maps["anchor translation"] = (np.eye(3), d)
    if base_plane is not None:
        p0 = np.asarray(base_plane[0], float).reshape(3)
        nrm = np.asarray(base_plane[1], float).reshape(3)
        nrm = nrm / np.linalg.norm(nrm)
        h = float(((A_ref - p0) @ nrm).mean())
        if abs(h) > 1e-6 * spread:
            B = np.eye(3) + np.outer(d, nrm) / h  # u(x) = d ((x - p0) . n) / h
            maps["anchor shear"] = (B, p0 - B @ p0)
    return maps


#: Distances the RANSAC scoring holds at once (float64: 32 MB): 1,340 scan and 1,364
#: reference points (the noise blobs of a scan at SNR 8) asked for 20.6 GiB in one go.
_BLOCK_ENTRIES = 4_000_000


def _ransac_maps(X, Y, log_size, anchors, spread, tol_mm, rng, *, samples=2000, keep=2):
    """Affine maps from minimal samples of size-compatible pairs, best consensus first.

    Each sample draws reference points and, for each, a scan point with probability
    proportional to the size likelihood; with the anchors they fix an affine map (four
    pairs). A map scores the sum over reference points of ``min(r^2 / tol^2, 9)``, r its
    distance to the nearest scan point; the best maps are refitted on their consensus.
    """
    A_ref, A = anchors
    n, m = len(X), len(Y)
    k_draw = max(4 - len(A_ref), 1)
    if n < k_draw or m < k_draw:
        return {}
    w = np.exp(log_size - log_size.max(1, keepdims=True))
    w /= w.sum(1, keepdims=True)
    cum = np.cumsum(w, 1)
    refs = np.argsort(rng.random((samples, n)), axis=1)[:, :k_draw]  # distinct per sample
    u = rng.random(refs.shape)
    scans = np.minimum((cum[refs] < u[..., None]).sum(-1), m - 1)  # inverse-cdf draws
    distinct = np.array([len(set(row)) == k_draw for row in scans])
    refs, scans = refs[distinct], scans[distinct]
    S = len(refs)
    if S == 0:
        return {}
    src = np.concatenate([X[refs], np.broadcast_to(A_ref, (S, *A_ref.shape))], 1)
    dst = np.concatenate([Y[scans], np.broadcast_to(A, (S, *A.shape))], 1)
    c = src.mean(1, keepdims=True)
    sv = np.linalg.svd(src - c, compute_uv=False)
    good = sv[:, -1] > 0.1 * spread  # well spread in 3-D: a well-conditioned affine map
    src, dst, c = src[good], dst[good], c[good]
    if not len(src):
        return {}
    H = np.concatenate([src, np.ones((*src.shape[:2], 1))], 2)
    HtH = np.einsum("spi,spj->sij", H, H) + 1e-9 * spread**2 * np.eye(4)
    params = np.linalg.solve(HtH, np.einsum("spi,spj->sij", H, dst))  # (S, 4, 3)
    Xh = np.column_stack([X, np.ones(n)])

    def scaled_d2(rows):  # (len(rows), n, m) squared distances of the mapped X to Y, / tol^2
        TX = np.einsum("ni,sij->snj", Xh, params[rows])
        d2 = (TX**2).sum(-1)[..., None] + (Y**2).sum(-1) - 2 * np.einsum("snd,md->snm", TX, Y)
        return np.maximum(d2, 0.0) / tol_mm**2

    # in blocks of samples, so memory stays near _BLOCK_ENTRIES floats whatever n and m
    block = max(1, _BLOCK_ENTRIES // (n * m))
    blocks = [np.arange(a, min(a + block, len(params))) for a in range(0, len(params), block)]
    score = np.concatenate([np.minimum(scaled_d2(b).min(-1), 9.0).sum(-1) for b in blocks])
    out = {}
    for rank, s_ in enumerate(np.argsort(score)[: keep * 4]):
        # refit on the consensus: mutual nearest pairs within 2 tol
        d2s = scaled_d2(np.array([s_]))[0]
        j = d2s.argmin(1)
        i_back = d2s.argmin(0)
        ok = (d2s[np.arange(n), j] < 4.0) & (i_back[j] == np.arange(n))
        if ok.sum() + len(A_ref) < 4:
            continue
        P = np.vstack([X[ok], A_ref])
        Q = np.vstack([Y[j[ok]], A])
        Ph = np.column_stack([P, np.ones(len(P))])
        sol, *_ = np.linalg.lstsq(Ph, Q, rcond=None)
        B, t = sol[:3].T, sol[3]
        if any(
            np.allclose(B, b, atol=1e-3) and np.allclose(t, t2, atol=0.1) for b, t2 in out.values()
        ):
            continue
        out[f"ransac {rank + 1}"] = (B, t)
        if len(out) >= keep:
            break
    return out


# --------------------------------------------------------------------------------------
# the leave-one-out field, the assignment and its rating (stages 3 and 4)


@dataclass(frozen=True)
class _Field:
    mean: np.ndarray  # (n, 3) predicted position of every reference point
    sd: np.ndarray  # (n,) per-axis predictive sd


_WIDTHS = (0.5, 0.75, 1.0, 1.5, 2.0, 3.0)  # kernel widths, in units of the spread
_RATIOS = (1e-4, 1e-3, 1e-2, 3e-2, 0.1, 0.3, 1.0)  # noise / signal variance


def _design(X, pairs, Y, anchors, spread):
    """Data of the displacement field: sites (N, 3), displacements (N, 3), mean basis (N, q).

    The sites are the matched reference points and the anchors; the mean is affine when
    the constellation has 10 or more points (a translation otherwise), in coordinates
    centred on the reference centroid and scaled by ``spread`` (the same for every
    assignment of one call, so their likelihoods compare).
    """
    A_ref, A = anchors
    i_idx = np.array([i for i, _ in pairs], int)
    j_idx = np.array([j for _, j in pairs], int)
    Xd = np.vstack([X[i_idx], A_ref])
    U = np.vstack([Y[j_idx] - X[i_idx], A - A_ref])
    extra = np.concatenate([np.zeros(len(i_idx)), np.full(len(A_ref), _ANCHOR_NOISE)])
    q = 4 if len(X) + len(A_ref) >= 10 else 1

    def basis(p):
        return np.column_stack([(p - X.mean(0)) / spread, np.ones(len(p))])[:, 4 - q :]

    return i_idx, j_idx, Xd, U, extra, basis


def _gp_select(Xd, U, H, extra, spread):
    """Best (kernel width, noise ratio) on the grid by the restricted likelihood.

    ``extra`` (N,) is noise added per site in units of the amplitude (the anchors').
    Returns ``(log-likelihood, width, ratio)`` (amplitude profiled, constants included:
    the density of the 3 (N - q) error contrasts, R&W Eq. (2.45) with a flat prior on the
    mean's coefficients), or None when the data cannot determine a field (N - q < 2).
    """
    N, q = H.shape
    if N - q < 2:
        return None
    d2 = ((Xd[:, None] - Xd[None]) ** 2).sum(-1)
    widths = spread * np.asarray(_WIDTHS)
    ratios = np.asarray(_RATIOS)
    W, R = len(widths), len(ratios)
    # every (width, ratio) of the grid at once: A = K + r I + diag(extra), (W R, N, N)
    A = np.repeat(np.exp(-d2[None] / (2 * widths[:, None, None] ** 2)), R, axis=0)
    idx = np.arange(N)
    A[:, idx, idx] += np.tile(ratios, W)[:, None] + extra[None, :]
    try:
        L = np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        return None
    logdet = 2.0 * np.log(np.diagonal(L, axis1=1, axis2=2)).sum(1)
    AiHU = np.linalg.solve(A, np.broadcast_to(np.hstack([H, U]), (W * R, N, q + 3)))
    AiH, AiU = AiHU[..., :q], AiHU[..., q:]
    S = np.einsum("na,gnb->gab", H, AiH)  # H^T A^-1 H
    sgn, logdet_s = np.linalg.slogdet(S)
    b = np.einsum("na,gnd->gad", H, AiU)  # H^T A^-1 U
    quad = np.einsum("nd,gnd->g", U, AiU) - np.einsum("gad,gad->g", b, np.linalg.solve(S, b))
    tau2 = np.maximum(quad / (3 * (N - q)), 1e-12)
    ll = -1.5 * ((N - q) * (np.log(2 * np.pi * tau2) + 1.0) + logdet + logdet_s)
    ll[sgn <= 0] = -np.inf
    k = int(np.argmax(ll))
    if not np.isfinite(ll[k]):
        return None
    return float(ll[k]), float(widths[k // R]), float(ratios[k % R])


def _field(X, pairs, Y, anchors, spread, min_sd, fallback: _Field) -> _Field:
    """Gaussian-process displacement field with an affine mean through the matches.

    Every matched reference point gets its leave-one-out prediction (Rippa 1999 for the
    bordered system: residual ``c_k / (M^-1)_kk``, variance ``tau^2 / (M^-1)_kk``); every
    other reference point the full prediction. Hyperparameters (kernel width, noise
    ratio) maximise the restricted likelihood over a grid; the amplitude is estimated
    robustly from the leave-one-out residuals (a wrong match must not widen its own
    prediction).
    """
    i_idx, j_idx, Xd, U, extra, basis = _design(X, pairs, Y, anchors, spread)
    H = basis(Xd)
    N, q = H.shape
    best = _gp_select(Xd, U, H, extra, spread)
    if best is None:
        return fallback
    _, beta, r = best
    K = np.exp(-((Xd[:, None] - Xd[None]) ** 2).sum(-1) / (2 * beta**2))
    M = np.block([[K + np.diag(r + extra), H], [H.T, np.zeros((q, q))]])
    try:
        Minv = np.linalg.inv(M)
    except np.linalg.LinAlgError:
        return fallback
    coef = Minv[:, :N] @ U  # (N + q, 3): kernel weights then mean coefficients
    Q = Minv[:N, :N]
    diag = np.diag(Q)
    tau2 = max(float(np.einsum("id,ij,jd->", U, Q, U)) / (3 * (N - q)), 1e-12)
    if N >= 8:
        z2 = (coef[:N] ** 2).sum(1) / diag  # = |LOO residual|^2 (M^-1)_kk = tau^2 chi2_3
        tau2 = max(float(np.median(z2)) / _CHI2_3_MEDIAN, 1e-12)
    ks = np.exp(-((X[:, None] - Xd[None]) ** 2).sum(-1) / (2 * beta**2))
    kh = np.hstack([ks, basis(X)])
    mean = X + kh @ coef
    var = tau2 * (1.0 + r - np.einsum("ij,jk,ik->i", kh, Minv, kh))
    n_pairs = len(i_idx)
    mean[i_idx] = Y[j_idx] - coef[:n_pairs] / diag[:n_pairs, None]  # leave-one-out
    var[i_idx] = tau2 / diag[:n_pairs]
    return _Field(mean, np.maximum(np.sqrt(np.maximum(var, 0.0)), min_sd))


@dataclass(frozen=True)
class _Model:
    """What the assignment costs are made of (fixed for one call)."""

    X: np.ndarray
    Y: np.ndarray
    log_size: np.ndarray
    log_extra: float
    log_miss: float
    log_hit: float
    anchors: tuple
    spread: float
    min_sd: float
    scores: dict = dataclasses.field(default_factory=dict)  # assignment -> _score (cache)


def _cost_matrix(md: _Model, field: _Field) -> np.ndarray:
    """Square (n + m) assignment matrix of negative log-likelihoods with dummy cells."""
    n, m = md.log_size.shape
    s = field.sd[:, None]
    d2 = ((md.Y[None] - field.mean[:, None]) ** 2).sum(-1)
    nu = _T_DOF  # multivariate Student t of the position: robust to a misjudged sd
    if math.isinf(nu):
        log_t = -d2 / (2 * s**2) - 3 * np.log(s) - 1.5 * _LOG2PI
    else:
        log_t = (
            math.lgamma((nu + 3) / 2) - math.lgamma(nu / 2) - 1.5 * math.log(nu * math.pi)
            - 3 * np.log(s) - (nu + 3) / 2 * np.log1p(d2 / (nu * s**2))
        )  # fmt: skip
    match = -log_t - md.log_size - md.log_hit
    C = np.full((n + m, m + n), _BIG)
    C[:n, :m] = match
    C[np.arange(n), m + np.arange(n)] = -md.log_miss  # reference point i missed in the scan
    C[n + np.arange(m), np.arange(m)] = -md.log_extra  # scan point j is an extra detection
    C[n:, m:] = 0.0
    return C


def _assign(C, n, m):
    """Optimal assignment: reference index of each scan point (-1: none) and its cost."""
    rows, cols = linear_sum_assignment(C)
    ref_of = np.full(m, -1)
    for r_, c_ in zip(rows, cols, strict=True):
        if r_ < n and c_ < m:
            ref_of[c_] = r_
    return ref_of, float(C[rows, cols].sum())


def _inverse(ref_of, n):
    scan_of = np.full(n, -1)
    for j, i in enumerate(ref_of):
        if i >= 0:
            scan_of[i] = j
    return scan_of


def _pairs(ref_of):
    return [(int(i), int(j)) for j, i in enumerate(ref_of) if i >= 0]


def _refine(md: _Model, field: _Field, iterations: int, forbid=None):
    """Alternate assignment and leave-one-out field until the assignment repeats.

    Returns the assignment, the field fitted to it and its cost (negative log-likelihood
    under that field); ``forbid`` is a cell of the assignment matrix kept out of every
    assignment.
    """
    n, m = md.log_size.shape
    prev, visited = None, set()
    for _ in range(max(iterations, 1) + 1):
        C = _cost_matrix(md, field)
        if forbid is not None:
            C[forbid] = _BIG
        ref_of, cost = _assign(C, n, m)
        key = ref_of.tobytes()
        if (prev is not None and np.array_equal(ref_of, prev)) or key in visited:
            break  # converged (the field is this assignment's), or a cycle
        visited.add(key)
        prev = ref_of
        field = _field(md.X, _pairs(ref_of), md.Y, md.anchors, md.spread, md.min_sd, field)
    return ref_of, field, cost


def _field_checked(md: _Model, ref_of: np.ndarray) -> bool:
    """Whether ``ref_of`` with any one match dropped still admits a field (N - q >= 2).

    The field's sites are the matches and the anchors; the mean's size ``q`` depends on
    the constellation only (:func:`_design`), so the count decides.
    """
    pairs = _pairs(ref_of)
    if not pairs:
        return False
    _, _, Xd, _, _, basis = _design(md.X, pairs[1:], md.Y, md.anchors, md.spread)
    N, q = basis(Xd).shape
    return N - q >= 2


def _score(md: _Model, ref_of: np.ndarray, lsa_cost: float) -> float:
    """Negative log-likelihood of a whole assignment (what assignments are compared by).

    The joint density of the matched displacements (and the anchors') under the
    Gaussian-process field (restricted likelihood, hyperparameters profiled), the size
    densities of the matched pairs, and the miss and extra-detection probabilities —
    every scan point's position and size has a density under every assignment. Unlike
    the assignment's own leave-one-out costs, no point's misfit is counted twice (once
    itself, once through its neighbours' predictions). Constellations too small for a
    field fall back to ``lsa_cost``.
    """
    n, m = md.log_size.shape
    key = ref_of.tobytes()
    if key in md.scores:
        return md.scores[key]
    pairs = _pairs(ref_of)
    _, _, Xd, U, extra, basis = _design(md.X, pairs, md.Y, md.anchors, md.spread)
    best = _gp_select(Xd, U, basis(Xd), extra, md.spread)
    if best is None:
        return lsa_cost
    i_idx = np.array([i for i, _ in pairs], int)
    j_idx = np.array([j for _, j in pairs], int)
    size = float(md.log_size[i_idx, j_idx].sum()) if len(pairs) else 0.0
    n_hit = len(pairs)
    md.scores[key] = (
        -best[0] - size - n_hit * md.log_hit
        - (n - n_hit) * md.log_miss - (m - n_hit) * md.log_extra
    )  # fmt: skip
    return md.scores[key]


# --------------------------------------------------------------------------------------
# the public function


def match_constellation(
    reference_mm: np.ndarray,
    reference_sizes_mm: np.ndarray,
    points_mm: np.ndarray,
    sizes_mm: np.ndarray,
    *,
    anchors_reference_mm: np.ndarray | None = None,
    anchors_mm: np.ndarray | None = None,
    base_plane: tuple[np.ndarray, np.ndarray] | None = None,
    size_sd_mm: float = 0.3,
    anchor_sd_mm: float = 2.0,
    min_sd_mm: float = 0.5,
    miss_probability: float = 0.05,
    smoothness_mm: float | None = None,
    cpd_lambda: float = 2.0,
    max_iterations: int = 200,
    refinements: int = 10,
    seed: int = 0,
) -> ConstellationMatch:
    """Match every scan point to a reference point (or none) under a smooth deformation.

    Both constellations must be in one frame (the scan's points mapped by the rigid
    registration); what remains is a deformation that may move the points by more than
    their spacing. See the module docstring for the method and the confidence.

    Parameters
    ----------
    reference_mm : array_like, shape (n, 3)
        Reference points (inclusion centres), mm.
    reference_sizes_mm : array_like, shape (n,)
        Their sizes (volume-equivalent diameters, which a nearly incompressible
        deformation keeps), mm.
    points_mm : array_like, shape (m, 3)
        Scan points in the reference frame, mm.
    sizes_mm : array_like, shape (m,)
        Their sizes, mm.
    anchors_reference_mm, anchors_mm : array_like, shape (k, 3), optional
        Points of known correspondence (e.g. the nipple) in the reference and the scan
        (reference frame), mm; measured with sd ``anchor_sd_mm`` per axis.
    base_plane : (point (3,), normal (3,)), optional
        A plane where the deformation is small (the back plate), reference frame. With
        anchors it adds an initial map: the anchors' displacement growing linearly with
        the distance from this plane.
    size_sd_mm : float
        Standard deviation of one size measurement, mm.
    anchor_sd_mm : float
        Per-axis standard deviation of an anchor's correspondence, mm.
    min_sd_mm : float
        Floor of the per-axis sd of a predicted position (localisation noise), mm.
    miss_probability : float
        Prior probability that a point is missed in one constellation, or extra in the
        other (the dummy cost of the assignment).
    smoothness_mm : float, optional
        Kernel width of the non-rigid drift; default the RMS spread of the reference
        points about their centroid.
    cpd_lambda : float
        Motion-coherence weight of the non-rigid drift (Myronenko & Song's lambda).
    max_iterations : int
        EM iterations per drift stage.
    refinements : int
        Most assignment / field refits.
    seed : int
        Seed of the random samples of the initial maps (the result is deterministic).

    Returns
    -------
    ConstellationMatch

    Raises
    ------
    ConstellationError
        Shapes, non-finite coordinates, non-positive sizes, anchors given in one frame
        only, or options out of range.
    """
    X = _points(reference_mm, "reference_mm")
    Y = _points(points_mm, "points_mm")
    dX = _sizes(reference_sizes_mm, len(X), "reference_sizes_mm")
    dY = _sizes(sizes_mm, len(Y), "sizes_mm")
    if (anchors_reference_mm is None) != (anchors_mm is None):
        raise ConstellationError("anchors_reference_mm and anchors_mm: give both or neither")
    A_ref = _points([] if anchors_reference_mm is None else anchors_reference_mm, "anchors")
    A = _points([] if anchors_mm is None else anchors_mm, "anchors_mm")
    if A_ref.shape != A.shape:
        raise ConstellationError(f"anchors: {len(A_ref)} reference and {len(A)} scan points")
    for name, v, lo, hi in (
        ("size_sd_mm", size_sd_mm, 0.0, math.inf),
        ("anchor_sd_mm", anchor_sd_mm, 0.0, math.inf),
        ("min_sd_mm", min_sd_mm, 0.0, math.inf),
        ("miss_probability", miss_probability, 0.0, 1.0),
        ("cpd_lambda", cpd_lambda, 0.0, math.inf),
    ):
        if not (math.isfinite(v) and lo < v < hi):
            raise ConstellationError(f"{name} must lie in ({lo}, {hi}), got {v}")
    n, m = len(X), len(Y)
    if n == 0 or m == 0:
        return ConstellationMatch(
            np.full(m, -1), np.ones(m), np.full(m, -1), np.full(n, -1), np.ones(n),
            np.full(n, -1), ((),) * n, np.full((n, 3), np.nan), np.full(n, np.nan), 0.0,
            "empty",
        )  # fmt: skip
    spread = max(float(np.sqrt(((X - X.mean(0)) ** 2).sum(1).mean())), 1.0)
    beta = spread if smoothness_mm is None else float(smoothness_mm)
    if not (math.isfinite(beta) and beta > 0):
        raise ConstellationError(f"smoothness_mm must be positive, got {smoothness_mm}")
    allp = np.vstack([X, Y])
    box = np.ptp(allp, axis=0) + 4.0 * spread / n ** (1 / 3)
    log_volume = float(np.log(np.maximum(box, 1.0)).sum())
    span = float(np.ptp(np.concatenate([dX, dY]))) + 6.0 * size_sd_mm
    log_size = _size_logpdf(dX, dY, size_sd_mm, span)
    md = _Model(
        X, Y, log_size,
        log_extra=math.log(miss_probability) - log_volume - math.log(span),
        log_miss=math.log(miss_probability), log_hit=math.log1p(-miss_probability),
        anchors=(A_ref, A), spread=spread, min_sd=min_sd_mm,
    )  # fmt: skip
    log_outlier = math.log(0.1) - log_volume - math.log(span)  # CPD's uniform component

    # initial maps: identity (annealed from CPD's usual broad start), then maps that are
    # followed from a moderate sd (the anchors' maps, RANSAC's best affine maps)
    tol = max(3.0 * min_sd_mm, 0.15 * spread)
    maps = {"identity": (np.eye(3), np.zeros(3), None)}
    starts = _anchor_maps(A_ref, A, base_plane, spread)
    starts |= _ransac_maps(X, Y, log_size, md.anchors, spread, tol, np.random.default_rng(seed))
    maps |= {k: (B, t, tol) for k, (B, t) in starts.items()}
    best = None
    pool: dict[bytes, tuple[float, np.ndarray]] = {}  # every assignment rated: key -> (cost, it)
    for name, (B0, t0, s0) in maps.items():
        TX, sigma = _cpd(
            X, Y, log_size, log_outlier, md.anchors, anchor_sd_mm, B0, t0, s0,
            beta=beta, lam=cpd_lambda, spread=spread, max_iter=max_iterations, tol=1e-7,
        )  # fmt: skip
        start = _Field(TX, np.full(n, max(sigma, min_sd_mm)))
        ref_of, field, lsa_cost = _refine(md, start, refinements)
        cost = _score(md, ref_of, lsa_cost)
        pool[ref_of.tobytes()] = (cost, ref_of)
        log.debug("constellation hypothesis %s: cost %.2f", name, cost)
        if best is None or cost < best[0] - 1e-9:
            best = (cost, name, ref_of, field)
    cost, name, ref_of, field = best
    for _ in range(5):  # adopt a competing assignment that turns out better, then re-rate
        out = _with_confidence(md, ref_of, cost, field, name, refinements, pool)
        if isinstance(out, ConstellationMatch):
            return out
        cost, ref_of, field = out
        name += " + local search"
    return _with_confidence(md, ref_of, cost, field, name, refinements, pool, adopt=False)


def _with_confidence(md: _Model, ref_of, cost, field, name, refinements, pool, *, adopt=True):
    """Confidence of every identity from the best rated assignment without it.

    For each identity (a match, a missed reference point, an extra detection) rivals
    are generated: the best assignment forbidding it with the field held, again with
    the field refitted to it (when within ``_REFIT_BELOW``), and for a match the same
    assignment without it. All are rated by :func:`_score` and added to ``pool`` (every
    assignment rated so far, the initial maps' included); an identity's rival is the
    best pooled assignment that changes it. Returns the :class:`ConstellationMatch`, or
    (``adopt``) a better assignment found on the way, as ``(cost, ref_of, field)``.
    """
    n, m = md.log_size.shape
    scan_of = _inverse(ref_of, n)
    C = _cost_matrix(md, field)
    fields = {}

    def add(a, c, f=None):
        key = a.tobytes()
        if key not in pool or c < pool[key][0]:
            pool[key] = (c, a)
        if f is not None:
            fields[key] = f

    for cell in [(int(i), j) if i >= 0 else (n + j, j) for j, i in enumerate(ref_of)] + [
        (int(i), m + int(i)) for i in np.flatnonzero(scan_of < 0)
    ]:
        C2 = C.copy()
        C2[cell] = _BIG
        alt, alt_lsa = _assign(C2, n, m)
        alt_cost = _score(md, alt, alt_lsa)
        add(alt, alt_cost)
        if alt_cost - cost < _REFIT_BELOW:  # a close rival: let the field follow it
            alt2, field2, lsa2 = _refine(md, field, refinements, forbid=cell)
            add(alt2, _score(md, alt2, lsa2), field2)
        if cell[0] < n and cell[1] < m:  # a match: also the assignment that just drops it
            drop = ref_of.copy()
            drop[cell[1]] = -1
            add(drop, _score(md, drop, np.inf))
    costs = np.array([c for c, _ in pool.values()])
    assignments = np.array([a for _, a in pool.values()]).reshape(len(pool), m)
    k = int(np.argmin(costs))
    if adopt and costs[k] < cost - 1e-6:
        a = assignments[k]
        f = fields.get(a.tobytes())
        if f is None:
            f = _field(md.X, _pairs(a), md.Y, md.anchors, md.spread, md.min_sd, field)
        return float(costs[k]), a, f

    def rated(changed: np.ndarray) -> tuple[float, int]:
        """Confidence and the index (in the pool) of the best assignment in ``changed``."""
        if not changed.any():
            return 1.0, -1
        k = int(np.flatnonzero(changed)[np.argmin(costs[changed])])
        delta = max(float(costs[k]) - cost, 0.0)
        return 1.0 / (1.0 + math.exp(-min(delta, 700.0))), k

    conf, runner = np.ones(m), np.full(m, -1)
    ref_conf, ref_runner = np.ones(n), np.full(n, -1)
    inverse = np.array([_inverse(a, n) for a in assignments]).reshape(len(pool), n)
    for j in range(m):
        conf[j], k = rated(assignments[:, j] != ref_of[j])
        runner[j] = assignments[k, j] if k >= 0 else -1
    alternatives = []
    for i in range(n):
        ref_conf[i], k = rated(inverse[:, i] != scan_of[i])
        ref_runner[i] = inverse[k, i] if k >= 0 else -1
        alt = {}
        for a_i, c in zip(inverse[:, i], costs, strict=True):
            if a_i != scan_of[i]:
                alt[int(a_i)] = min(alt.get(int(a_i), np.inf), float(c) - cost)
        probs = sorted(((j, 1.0 / (1.0 + math.exp(min(max(d, 0.0), 700.0)))) for j, d in
                        alt.items()), key=lambda t: -t[1])  # fmt: skip
        alternatives.append(tuple((j, p) for j, p in probs if p > 1e-3))
    return ConstellationMatch(
        reference_index=ref_of,
        confidence=conf,
        runner_up=runner,
        scan_index=scan_of,
        reference_confidence=ref_conf,
        reference_runner_up=ref_runner,
        reference_alternatives=tuple(alternatives),
        predicted_mm=field.mean,
        predicted_sd_mm=field.sd,
        cost=cost,
        hypothesis=name,
        field_checked=_field_checked(md, ref_of),
    )
