"""Phantom body segmentation robust to an MR bias field and noise.

Pipeline: light Gaussian smoothing; an Otsu threshold and the largest connected component
give a first body mask; a smooth bias field (a cubic polynomial in the voxel indices fitted
robustly to the log intensity inside the eroded body) divides the image so that the body
level becomes 1 (the *normalised* image); the final mask is the normalised image above 0.5
(half-way between background and body), without the very bright fiducial blobs, largest
component, holes filled. All work happens in a crop around the body with a margin.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from imaging.errors import SegmentationError
from imaging.volume import Volume

__all__ = ["BodySegmentation", "fit_bias_field", "image_noise", "segment_body"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class BodySegmentation:
    """Result of :func:`segment_body`.

    Attributes
    ----------
    mask : Volume
        uint8 body mask (1 inside) on the scan grid.
    normalised : Volume
        float32 bias-corrected intensity with the body level at 1 (unsmoothed); 0 outside
        the crop around the body.
    smoothed : Volume
        Gaussian-smoothed ``normalised`` (used for thresholds and the surface level set).
    crop : tuple of slice
        Index box (on the scan grid) that holds the body and its margin.
    quality : dict
        ``otsu_threshold`` (raw units), ``bias_min``/``bias_max`` (fitted field range over the
        body, relative), ``body_cv`` (robust spread of the corrected body intensity),
        ``noise_sigma_rel`` (image noise sigma / body level), ``snr``, ``noise_method``
        (where the noise was measured: :func:`image_noise`), ``volume_ml``,
        ``n_components`` (foreground components before keeping the largest).
    """

    mask: Volume
    normalised: Volume
    smoothed: Volume
    crop: tuple[slice, slice, slice]
    quality: dict = field(default_factory=dict)


def robust_sd(values: np.ndarray) -> float:
    """Standard deviation from the median absolute deviation (1.4826 MAD: Gaussian-consistent)."""
    return float(1.4826 * np.median(np.abs(values - np.median(values))))


#: Distinct slices of the fitted voxels an axis needs beyond a polynomial's degree along
#: it: a cubic along an axis the eroded body crosses in 2 slices (a 30 mm dome in 5 mm
#: slices) is determined by nothing but the least-squares minimum norm there, and its
#: extrapolation to the body's edge swung the field from 0.3 to 2.5 (review T).
BIAS_SLICES_BEYOND_DEGREE = 2


#: How far the bias fit's voxels lie inside the body: 2 voxels along an axis whose voxels
#: are at most 2 mm (this over 2 rounds to 2 voxels or more there), 1 along a coarser one
#: (5 mm slices: 1 slice, not 10 mm).
BIAS_EROSION_MM = 3.0
#: The bias field over the body (max over min): beyond BIAS_RANGE_WARN a warning, beyond
#: BIAS_RANGE_MAX the fit is taken for a failure, not for the scanner's. The twin's renderer
#: spans 1.5 (+-0.2); the fits review T saw swung by too few slices spanned 6.6-9.8.
BIAS_RANGE_WARN, BIAS_RANGE_MAX = 4.0, 8.0


def _eroded(mask: np.ndarray, spacing_mm: np.ndarray) -> np.ndarray:
    """``mask`` eroded by 2 voxels (the L1 ball), or 1 along axes coarser than 2 mm."""
    r = [int(max(1, min(2, round(BIAS_EROSION_MM / s)))) for s in spacing_mm]
    grid = np.indices([2 * k + 1 for k in r]) - np.array(r)[:, None, None, None]
    ball = sum(np.abs(g) / k for g, k in zip(grid, r, strict=True)) <= 1.0 + 1e-9
    return ndimage.binary_erosion(mask, structure=ball)


def _poly_basis(degree: int, per_axis: tuple[int, int, int]) -> list[tuple[int, int, int]]:
    """Exponents of total degree ``degree`` at most, and at most ``per_axis[i]`` along axis i."""
    return [
        (a, b, c)
        for a in range(per_axis[0] + 1)
        for b in range(per_axis[1] + 1)
        for c in range(per_axis[2] + 1)
        if a + b + c <= degree
    ]


def _slices_text(mask: np.ndarray) -> str:
    return "/".join(str(n) for n in _slices(mask))


def _slices(mask: np.ndarray) -> list[int]:
    """How many slices along each axis hold some of ``mask``."""
    return [
        int(np.count_nonzero(mask.any(axis=tuple(j for j in range(3) if j != i)))) for i in range(3)
    ]


def _axis_degrees(mask: np.ndarray, degree: int) -> tuple[int, int, int]:
    """The polynomial's degree along each axis: ``degree``, or less where few slices hold mask."""
    return tuple(int(min(degree, max(n - BIAS_SLICES_BEYOND_DEGREE, 0))) for n in _slices(mask))


def fit_bias_field(
    image: np.ndarray, mask: np.ndarray, *, degree: int = 3, n_samples: int = 100_000, seed: int = 0
) -> np.ndarray:
    """Fit a smooth multiplicative field to an image inside a mask.

    ``log(image) ~ P(u, v, w)``, P a polynomial of total degree ``degree`` in the index
    coordinates scaled to [-1, 1]; three robust passes drop voxels more than 2.5 robust
    sigmas off (inclusions, markers). Returns ``exp(P)`` (same shape as ``image``, float32),
    which carries the body level as well as the bias.

    Along an axis on which the mask spans few slices (thick slices, a flat body) the
    degree drops to the slices less :data:`BIAS_SLICES_BEYOND_DEGREE` (0: constant), and
    the field along that axis is held at its value at the mask's first and last slice
    beyond them: a polynomial is not extrapolated along an axis it was not fitted on.
    """
    idx = np.flatnonzero(mask)
    if idx.size < 50:
        raise SegmentationError("bias fit: fewer than 50 body voxels")
    rng = np.random.default_rng(seed)
    if idx.size > n_samples:
        idx = np.sort(rng.choice(idx, n_samples, replace=False))
    ijk = np.array(np.unravel_index(idx, image.shape), float).T
    scale = np.maximum(np.array(image.shape, float) - 1.0, 1.0)
    u = 2.0 * ijk / scale - 1.0
    per_axis = _axis_degrees(mask, degree)
    exps = _poly_basis(degree, per_axis)
    X = np.stack([u[:, 0] ** a * u[:, 1] ** b * u[:, 2] ** c for a, b, c in exps], 1)
    y = np.log(np.maximum(image.ravel()[idx].astype(float), 1e-6))
    keep = np.ones(len(y), bool)
    for _ in range(3):
        coef = np.linalg.lstsq(X[keep], y[keep], rcond=None)[0]
        r = y - X @ coef
        sigma = robust_sd(r[keep])
        keep = np.abs(r) < 2.5 * max(sigma, 1e-6)
    axes = [np.linspace(-1.0, 1.0, n) for n in image.shape]
    for i, d in enumerate(per_axis):
        if d < degree:  # a reduced axis: held at the mask's end slices beyond them
            axes[i] = np.clip(axes[i], u[:, i].min(), u[:, i].max())
    logf = np.zeros(image.shape, np.float32)
    for (a, b, c), w in zip(exps, coef, strict=True):
        logf += np.float32(w) * (
            (axes[0] ** a)[:, None, None]
            * (axes[1] ** b)[None, :, None]
            * (axes[2] ** c)[None, None, :]
        ).astype(np.float32)
    return np.exp(logf)


def _largest_component(mask: np.ndarray) -> tuple[np.ndarray, int]:
    lab, n = ndimage.label(mask)
    if n == 0:
        return mask.astype(bool), 0
    counts = np.bincount(lab.ravel())
    counts[0] = 0
    return lab == int(np.argmax(counts)), n


def _otsu(values: np.ndarray) -> float:
    from skimage.filters import threshold_otsu

    hi = np.percentile(values, 99.5)
    return float(threshold_otsu(np.minimum(values, hi)))


def _crop_box(mask: np.ndarray, margin: np.ndarray) -> tuple[slice, slice, slice]:
    nz = np.argwhere(mask)
    lo = np.maximum(nz.min(axis=0) - margin, 0)
    hi = np.minimum(nz.max(axis=0) + margin + 1, mask.shape)
    return tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))  # type: ignore[return-value]


#: Room kept around a marker beyond the crop's margin (mm): the marker detection measures
#: a blob's background in a shell a few voxels outside it.
MARKER_PAD_MM = 8.0
#: Volume-equivalent radii (mm) of a bright blob beyond the margin that the crop grows
#: to hold: the marker detection's accepted range (:func:`imaging.detect.detect_fiducials`).
FAR_MARKER_RADIUS_MM = (1.0, 6.0)


def _with_far_markers(crop, bright: np.ndarray, voxel_mm3: float, pad: np.ndarray, src: str):
    """``crop`` grown to hold every marker-sized ``bright`` blob outside it, padded.

    Markers on a frame farther from the body than the margin were cut off by the crop
    (and ingest found too few). ``bright``: voxels over the marker ratio times the body's
    median intensity, before bias correction. Only blobs of a marker's size reaching
    outside the crop count (a larger bright object in the field of view, such as a
    reference vial, stays out); inside the margin nothing changes.
    """
    inside = np.zeros(bright.shape, bool)
    inside[crop] = True
    lab, n = ndimage.label(bright)
    if n == 0:
        return crop
    counts = np.bincount(lab.ravel(), minlength=n + 1)
    out = np.bincount(lab[~inside].ravel(), minlength=n + 1)
    r_eq = (3.0 * counts * voxel_mm3 / (4.0 * np.pi)) ** (1.0 / 3.0)
    lo_r, hi_r = FAR_MARKER_RADIUS_MM
    far = [k for k in range(1, n + 1) if out[k] > 0 and lo_r <= r_eq[k] <= hi_r]
    if not far:
        return crop
    nz = np.argwhere(np.isin(lab, far))
    lo = np.minimum([c.start for c in crop], np.maximum(nz.min(axis=0) - pad, 0))
    hi = np.maximum([c.stop for c in crop], np.minimum(nz.max(axis=0) + pad + 1, bright.shape))
    log.info(
        "%s: the crop grows to hold %d marker-sized bright blobs beyond its margin", src, len(far)
    )
    return tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))


#: A background whose median lies farther from zero than this many of its own robust sds
#: (IQR / 1.349) carries an intensity offset. A magnitude image's noise floor (Rayleigh:
#: median 1.177 sigma, IQR 0.907 sigma) sits at 1.75 sds, a zero-mean one at 0: both are
#: left as they are.
OFFSET_SDS = 3.0
#: A positive offset must also exceed this share of the body's level: a sum-of-squares
#: image's noise floor sits at 2.65, 3.87, 5.56 sds for 2, 4, 8 coils, a median of up to
#: 0.16 of the body at a per-coil SNR of 25 (8 coils), and is not an offset. A negative
#: one never is a noise floor (magnitudes are >= 0).
OFFSET_MIN_SHARE = 0.2
#: A Rayleigh noise floor's median over its sigma, sqrt(2 ln 2).
RAYLEIGH_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))
#: The band a background's upper over lower quartile must lie in to be read as a
#: Rayleigh floor, whose ratio is sqrt(ln 4 / ln(4/3)) = 2.195 (review AE: a real-valued
#: Gaussian background read 1e-5 of the body, an 8-coil sum of squares 3.3 times the
#: truth, a zero-filled floor 0). Ten thousand voxels hold the ratio to about 1 %; a
#: 2-coil floor reads 1.67, a zero-mean Gaussian one is negative.
RAYLEIGH_RATIO_BAND = (1.9, 2.5)
#: The band of an offset floor's shape, blind to the offset: (q3 - median) / (median -
#: q1), 1.164 for a Rayleigh floor (quantiles sqrt(2 ln(1/(1-p)))), 1.096 for a 2-coil sum
#: of squares, 1 for a Gaussian one.
RAYLEIGH_SHAPE_BAND = (1.13, 1.21)
#: Voxels an offset floor needs for its shape to be read: the shape's sd is 0.015 at
#: 50,000 (a Rayleigh floor inside the band 99 % of the time, a 2-coil one 1 %), 0.032 at
#: 10,000 (77 %; review AH: 30 % at 1,000).
OFFSET_FLOOR_MIN_VOXELS = 50_000
#: Distinct values a floor needs between its quartiles to be read (a floor of a few
#: quantisation steps, integer counts or a rescale slope's, reads 0.81-0.85 of its sigma
#: at 1 count per sigma; review AH: 0.955-1.019 from 5 counts, 5 levels, up).
MIN_FLOOR_LEVELS = 5
#: Distinct values the interior's differences need between their quartiles for their
#: median absolute deviation (whose steps bias it by up to half a step over its size:
#: review AH, 0.975-1.027 at 11-14 counts per sigma, 20 levels); fewer, their clipped sd.
MIN_DIFF_LEVELS = 40
#: The interior's differences farther than this many robust sds from their median are
#: edges (inclusions, partial volumes), not noise.
DIFF_CLIP_SDS = 5.0


#: Lags (voxels) the interior's differences are taken at, and the rise from one lag to
#: the next that says neighbours are correlated: the estimate moves to the next lag while
#: it rises by this much or more. An interpolation rises by 15 % or more from lag 1 to 2
#: (its lag 1 reads 0.47-0.86 of the truth, review AF); inclusion edges, thick slices and
#: small interiors by 0.1-7.5 %, and a 3 % rule read them as correlation, up to 1.2 times
#: the truth, and climbed onto a zero-filled image's negative correlation (review AL).
MAX_DIFF_LAG = 4
CORRELATED_RISE = 1.15


def _diffs(image: np.ndarray, lag: int = 1) -> np.ndarray:
    """The differences between voxels ``lag`` apart along each axis, where both are finite.

    Pooled over the three axes.
    """
    out = []
    for k in range(3):
        n = image.shape[k]
        d = np.take(image, range(lag, n), axis=k) - np.take(image, range(n - lag), axis=k)
        out.append(d[np.isfinite(d)])
    return np.concatenate(out)


def _quantised(values: np.ndarray, levels: int) -> bool:
    """Fewer than ``levels`` distinct values between the quartiles."""
    q1, q3 = np.percentile(values, [25.0, 75.0])
    sample = values[:: max(1, values.size // 100_000)]
    return np.unique(sample[(sample >= q1) & (sample <= q3)]).size < levels


def _interior_noise(normalised: np.ndarray, raw: np.ndarray) -> float:
    """The noise sd of a bias-corrected interior (NaN elsewhere) from neighbour differences.

    1.4826 times the median absolute deviation of the differences between neighbours,
    over sqrt(2): exact for white noise and blind to the few differences across an
    inclusion's edge (review AF: 1.01-1.04 of the truth with five inclusions, where a
    trimmed sd read 1.06). Where the differences take fewer than
    :data:`MIN_DIFF_LEVELS` values between their quartiles (a quantised image of a few
    counts per sigma, where the median absolute deviation jumps: 0.68 to 1.21 of the
    truth at 1.3-1.7 counts), their sd instead, those farther than
    :data:`DIFF_CLIP_SDS` robust sds from the median left out: continuous in the step,
    and counting its step^2 / 12 as the noise it is. Where neighbours are correlated (an
    interpolated image) the differences of next neighbours read low: the estimate is
    taken at the lag, up to :data:`MAX_DIFF_LAG`, where it stops rising by
    :data:`CORRELATED_RISE` or more (white noise: lag 1; a Gaussian correlation of one
    voxel: lag 3, 0.95 of the truth; zero-filled x2: lag 2, 0.99). The quantisation is
    read on the raw image (``raw``, the same voxels): the bias correction's division
    spreads its steps.
    """
    quantised = _quantised(_diffs(raw), MIN_DIFF_LEVELS)
    sigma = float("nan")
    for lag in range(1, MAX_DIFF_LAG + 1):
        d = _diffs(normalised, lag)
        if not d.size:
            break
        dev = np.abs(d - np.median(d))
        mad = 1.4826 * float(np.median(dev))
        if quantised:
            keep = dev <= DIFF_CLIP_SDS * mad if mad > 0 else np.ones(d.size, bool)
            at_lag = float(np.std(d[keep]) / np.sqrt(2.0))
        else:
            at_lag = mad / float(np.sqrt(2.0))
        if lag > 1 and not at_lag > CORRELATED_RISE * sigma:
            break  # no longer rising: neighbours this far apart are not correlated
        sigma = at_lag
    return sigma


def image_noise(
    background: np.ndarray,
    interior: np.ndarray,
    raw_interior: np.ndarray,
    *,
    level: float,
    offset: float = 0.0,
) -> tuple[float, str]:
    """The image noise sigma, from the background where it is a Rayleigh floor.

    Parameters
    ----------
    background : ndarray
        Intensities beyond the body, the offset subtracted.
    interior : ndarray, shape (I, J, K)
        The bias-corrected image (body level 1) in the body's interior, NaN elsewhere:
        its differences between neighbours give the noise where the background cannot
        (on the raw image a coil bias's gradient read 1.5 times the truth at SNR 300,
        review AF).
    raw_interior : ndarray, shape (I, J, K)
        The same voxels of the image as stored (its quantisation is read there).
    level : float
        The body's level in the image's units (the interior's unit).
    offset : float
        The background offset subtracted (:func:`background_offset`).

    Returns
    -------
    sigma : float
        In the image's units; NaN where neither estimate has voxels.
    method : str
        ``background`` (a Rayleigh floor, :data:`RAYLEIGH_RATIO_BAND`: its median over
        sqrt(2 ln 2), blind to the markers' few bright voxels), ``background (offset)``
        (an offset Rayleigh floor, :data:`RAYLEIGH_SHAPE_BAND`: its interquartile range
        over 0.907), or ``interior`` (anything else: a real-valued, zero-filled or
        multi-coil floor, or one of under :data:`MIN_FLOOR_LEVELS` quantisation steps
        between its quartiles; :func:`_interior_noise`).
    """
    if background.size >= 1000:
        q1, med, q3 = np.percentile(background, [25.0, 50.0, 75.0])
        fine = not _quantised(background, MIN_FLOOR_LEVELS)
        if fine and offset and background.size >= OFFSET_FLOOR_MIN_VOXELS:
            # an offset floor: its shape, then its IQR (0.907 sigma)
            shape = (q3 - med) / (med - q1) if med > q1 else np.nan
            lo, hi = RAYLEIGH_SHAPE_BAND
            if lo < shape < hi:
                return float((q3 - q1) / 0.907), "background (offset)"
        elif fine and not offset:
            lo, hi = RAYLEIGH_RATIO_BAND
            if q1 > 0 and lo < q3 / q1 < hi:
                return float(med / RAYLEIGH_MEDIAN), "background"
    sigma = _interior_noise(interior, raw_interior)
    # under float32's round-off (1.2e-7 of the level; a noiseless image read 1.7e-7): none
    return (0.0 if sigma < 1e-6 else sigma * float(level)), "interior"


def background_offset(image: np.ndarray, body: np.ndarray) -> float:
    """The intensity offset of an image's background (0 where it is a noise floor).

    The thresholds of :func:`segment_body` are fractions of the body's level above zero, so
    an offset (a rescale intercept, a renderer's DC level) moves the surface: +30 % of the
    body level grew the segmented volume by 5 %, -50 % shrank it by 7 %. The offset is the
    median of the voxels more than 3 voxels from ``body`` where it lies more than
    :data:`OFFSET_SDS` robust sds of theirs from zero, and, above zero, more than
    :data:`OFFSET_MIN_SHARE` of the body's median.

    Parameters
    ----------
    image : ndarray, shape (i, j, k)
        Intensities.
    body : ndarray of bool, shape (i, j, k)
        A coarse body mask (the background is what lies beyond it).

    Returns
    -------
    float
        The offset to subtract, in the image's units.
    """
    bg = image[~ndimage.binary_dilation(body, iterations=3)]
    if bg.size < 1000:
        return 0.0
    q1, median, q3 = np.percentile(bg, [25.0, 50.0, 75.0])
    sd = (q3 - q1) / 1.349
    if abs(median) <= OFFSET_SDS * sd:
        return 0.0
    if median > 0 and median <= OFFSET_MIN_SHARE * float(np.median(image[body])):
        return 0.0
    return float(median)


#: Voxels (beyond the first) of the ring around a bright blob whose median level says
#: whether tissue encloses it (:func:`enclosed_blobs`).
RING_VOXELS = 3
#: A blob with background (under a quarter of the body's level) this many voxels from it
#: stands out of the body: a marker, however much tissue surrounds it.
SURFACE_VOXELS = 2


def enclosed_blobs(normalised: np.ndarray, bright: np.ndarray) -> np.ndarray:
    """The blobs of ``bright`` that tissue encloses: inclusions, not markers.

    A blob is enclosed where the median of the normalised image (body level 1) on a ring
    around it, 2 to :data:`RING_VOXELS` + 1 voxels out (past its partial-volume edge), is
    over half the body level, and no background voxel (under a quarter of that level) lies
    within :data:`SURFACE_VOXELS` of it. A marker lies in the background (the plate is not
    imaged), or stands out of the body where sunk into it (reviews AF, AH: one more than
    half inside had a ring median of 0.94-0.97 and was lost); an inclusion brighter than
    the marker threshold lies under the surface. Review AE: inclusions at 2.5 times the
    body were counted as markers (ingest stopped: 22 markers for 3), and at 2.3 times cut
    from the body mask as markers are (a dent where one lay near the surface).

    Parameters
    ----------
    normalised : ndarray, shape (I, J, K)
        The bias-corrected image, body level 1.
    bright : ndarray of bool, shape (I, J, K)
        Voxels over the marker threshold.

    Returns
    -------
    ndarray of bool, shape (I, J, K)
        The voxels of the enclosed blobs.
    """
    lab, _ = ndimage.label(bright)
    out = np.zeros(bright.shape, bool)
    reach = RING_VOXELS + 1
    background = normalised < 0.25
    for k, sl in enumerate(ndimage.find_objects(lab), start=1):
        if sl is None:
            continue
        box = tuple(
            slice(max(s.start - reach, 0), min(s.stop + reach, n))
            for s, n in zip(sl, bright.shape, strict=True)
        )
        comp = lab[box] == k
        near = ndimage.binary_dilation(comp, iterations=1)
        ring = ndimage.binary_dilation(comp, iterations=reach) & ~near & ~bright[box]
        outside = ndimage.binary_dilation(comp, iterations=SURFACE_VOXELS) & background[box]
        if ring.any() and float(np.median(normalised[box][ring])) > 0.5 and not outside.any():
            out[box] |= comp
    return out


#: Segmentations at most, each from the bias-corrected body of the one before, while the
#: body reaches a face of its crop inside the volume (review BM).
CROP_PASSES = 3


def _cut_faces(body: np.ndarray, crop, shape) -> list[str]:
    """The faces of ``crop`` inside the volume that ``body`` (crop coordinates) reaches.

    Named ``"axis 1 low"`` and so on; a face that is the volume's own is the field of
    view's (``imaging.pipeline`` reports those), not the crop's.
    """
    out = []
    for ax, (c, n) in enumerate(zip(crop, shape, strict=True)):
        if c.start > 0 and np.take(body, 0, axis=ax).any():
            out.append(f"axis {ax} low")
        if c.stop < n and np.take(body, -1, axis=ax).any():
            out.append(f"axis {ax} high")
    return out


def _union(a, b):
    """The smallest box holding the boxes (tuples of slices) ``a`` and ``b``."""
    return tuple(
        slice(min(x.start, y.start), max(x.stop, y.stop)) for x, y in zip(a, b, strict=True)
    )


def _held_beyond(field: np.ndarray, crop, shape) -> np.ndarray:
    """``field`` (on ``crop``) over the whole volume, held at the crop's faces beyond it."""
    widths = [(c.start, n - c.stop) for c, n in zip(crop, shape, strict=True)]
    return np.pad(field, widths, mode="edge")


def segment_body(
    volume: Volume,
    *,
    smoothing_mm: float = 0.5,
    margin_mm: float = 30.0,
    bias_degree: int = 3,
    marker_ratio: float = 2.0,
    seed: int = 0,
) -> BodySegmentation:
    """Segment the phantom body.

    An Otsu threshold of the smoothed image gives a first body; the image is cropped
    ``margin_mm`` around it (grown for far markers), its intensity bias fitted inside it
    (a polynomial of ``bias_degree``) and divided out, and the body is what lies over half
    the body level, markers cut from it. Where that body reaches a face of the crop inside
    the volume (a bias that dimmed one end of it under the Otsu threshold), the
    segmentation is made again around it, at most :data:`CROP_PASSES` times
    (``quality["crop_passes"]``).

    Parameters
    ----------
    volume : Volume
        MR intensities (bright body on a dark background).
    smoothing_mm : float
        Gaussian sigma (mm) of the smoothing before thresholds.
    margin_mm : float
        Margin around the body kept in the crop; it grows to hold marker-sized blobs
        brighter than ``marker_ratio`` times the body's median farther out.
    bias_degree : int
        Total degree of the bias polynomial (0 switches bias correction off).
    marker_ratio : float
        Normalised intensity above which voxels count as marker, not body.
    seed : int
        Seeds the voxel subsample of the bias fit.

    Raises
    ------
    SegmentationError
        Empty or degenerate segmentation; the message names the volume's source.
    """
    src = volume.source
    arr = np.asarray(volume.array, np.float32)
    if not np.all(np.isfinite(arr)) or float(arr.max()) <= float(arr.min()):
        raise SegmentationError(f"{src}: image is constant or not finite, nothing to segment")
    sp = volume.spacing_mm
    sigma = smoothing_mm / sp
    sub = arr[::3, ::3, ::3]
    thr = _otsu(sub.ravel())
    smooth = ndimage.gaussian_filter(arr, sigma)
    coarse, n_comp = _largest_component(smooth > thr)
    if coarse.sum() < 100:
        raise SegmentationError(f"{src}: empty segmentation (no body above threshold {thr:.3g})")
    offset = background_offset(arr, coarse)
    if offset:
        level = float(np.median(arr[coarse]))
        msg = "%s: the background lies at %.3g (%.2f of the body's %.3g), not at 0: subtracted"
        log.warning(msg, src, offset, offset / level, level)
        arr, smooth = arr - offset, smooth - offset
    # review BM: the crop and the bias fit's region came from the uncorrected Otsu mask, so
    # under a coil bias the contract accepts (a field of 4-8 over the body) the dim end
    # fell out of it and the body was cut flat at the crop's face, scored as surface. The
    # segmentation is made again from the corrected body while it touches a face of its
    # crop that is not one of the volume's.
    # Markers beyond the margin are looked for again on the corrected image (the field held
    # at its value on the crop's faces beyond them): one the bias dims under twice the
    # body's raw level was cut off, and ingest said too few markers were bright enough.
    region, grown = coarse, None
    pad = np.ceil(MARKER_PAD_MM / sp).astype(int)
    margin = np.ceil(margin_mm / sp).astype(int)
    for passes in range(1, CROP_PASSES + 1):  # noqa: B007 (recorded in quality)
        crop = _with_far_markers(
            _crop_box(region, margin),
            smooth > marker_ratio * float(np.median(smooth[region])),
            volume.voxel_volume_mm3,
            pad,
            src,
        )
        if grown is not None:
            crop = _union(crop, grown)
        a = arr[crop]
        g = ndimage.gaussian_filter(a, sigma)
        inner = _eroded(region[crop], sp)
        if inner.sum() < 50:
            inner = region[crop]
        if bias_degree > 0:
            field_ = fit_bias_field(g, inner, degree=bias_degree, seed=seed)
        else:
            field_ = np.full(a.shape, np.median(g[inner]), np.float32)
        n = a / field_
        ns = g / field_
        bright = ns > marker_ratio
        markers = ndimage.binary_dilation(bright & ~enclosed_blobs(n, bright), iterations=2)
        body = (ns > 0.5) & ~markers
        body, _ = _largest_component(body)
        body = ndimage.binary_fill_holes(body)
        cut = _cut_faces(body, crop, arr.shape)
        corrected = smooth > marker_ratio * _held_beyond(field_, crop, arr.shape)
        grown = _with_far_markers(crop, corrected, volume.voxel_volume_mm3, pad, src)
        if (not cut and grown == crop) or body.sum() < 100:
            break
        region = np.zeros(arr.shape, bool)
        region[crop] = body
    else:
        if cut:  # (a crop that would only grow for a far marker once more is kept)
            raise SegmentationError(
                f"{src}: the body still reaches the segmentation's crop ({', '.join(cut)}) "
                f"after {CROP_PASSES} segmentations, each cropped around the bias-corrected "
                "body of the one before; a bias field stronger than the segmentation corrects"
            )
    if bias_degree > 0:
        # the spread over the body found, not over the region the field was fitted on
        # (review BM: that region lost the body's dim end first, and the warning said 4.07
        # of a field spanning 7.0)
        inside = field_[body if body.sum() >= 100 else inner]
        spread = float(inside.max() / inside.min()) if inside.min() > 0 else float("inf")
        if np.isfinite(spread) and BIAS_RANGE_WARN < spread <= BIAS_RANGE_MAX:
            log.warning(
                "%s: the intensity-bias field fitted inside the body spans a ratio of %.3g "
                "(a strong coil bias, or a fit on few slices: %s of the interior along the "
                "volume's axes); check the segmentation (ingest.json quality.seg_bias_*)",
                src,
                spread,
                _slices_text(inner),
            )
        if not np.isfinite(spread) or spread > BIAS_RANGE_MAX:
            raise SegmentationError(
                f"{src}: the intensity-bias field fitted inside the body spans a ratio of "
                f"{spread:.3g} (at most {BIAS_RANGE_MAX:g} expected); the body spans "
                f"{_slices_text(inner)} slices of its interior along the volume's axes "
                f"(voxels {', '.join(f'{s:g}' for s in sp)} mm): too few to fit the field "
                "on, or a coil bias stronger than the segmentation corrects"
            )
    if body.sum() < 100:
        raise SegmentationError(f"{src}: empty segmentation after bias correction")
    mask = np.zeros(arr.shape, np.uint8)
    mask[crop] = body
    full_n = np.zeros(arr.shape, np.float32)
    full_n[crop] = n
    full_s = np.zeros(arr.shape, np.float32)
    full_s[crop] = ns
    vals = n[ndimage.binary_erosion(body, iterations=2)]
    med = float(np.median(vals)) if vals.size else 1.0
    bg = arr[~ndimage.binary_dilation(coarse | mask.astype(bool), iterations=3)]
    # the background's median, not its mean of squares: the markers read the twins' noise
    # 17-32 % high, by a share that changes with the field of view
    level = float(np.median(field_[inner]))
    interior = (np.where(inner, n, np.nan), np.where(inner, a, np.nan))
    noise, noise_method = image_noise(bg, *interior, level=level, offset=offset)
    quality = {
        "otsu_threshold": thr,
        "bias_min": float(field_[body].min() / level),
        "bias_max": float(field_[body].max() / level),
        "body_cv": float(1.4826 * np.median(np.abs(vals - med)) / med) if vals.size else 0.0,
        "noise_sigma_rel": noise / level,
        "snr": level / noise if noise > 0 else None,  # None: no noise measured
        "noise_method": noise_method,
        "volume_ml": float(body.sum() * volume.voxel_volume_mm3 / 1000.0),
        "n_components": int(n_comp),
        "background_offset": offset,
        "crop_passes": passes,
    }
    A = volume.affine_lps_from_index
    return BodySegmentation(
        mask=Volume(mask, A, f"{src} [body mask]"),
        normalised=Volume(full_n, A, f"{src} [normalised]"),
        smoothed=Volume(full_s, A, f"{src} [normalised, smoothed]"),
        crop=crop,
        quality=quality,
    )
