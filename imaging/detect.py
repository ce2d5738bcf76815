"""Fiducial markers and inclusions in a segmented, bias-corrected scan.

Both detectors work on the normalised image of :func:`imaging.segment.segment_body` (body
level 1). Sub-voxel positions are intensity-weighted centroids of the partial-volume
fractions; an inclusion's equivalent diameter comes from the sum of its partial-volume
fractions (its volume), ``d = (6 V / pi)^(1/3)``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Literal, get_args

import numpy as np
from scipy import ndimage

from imaging.errors import FiducialError, SegmentationError
from imaging.segment import BodySegmentation, enclosed_blobs, robust_sd
from imaging.volume import Volume

__all__ = [
    "FiducialDetection",
    "InclusionDetection",
    "InclusionMask",
    "Polarity",
    "detect_fiducials",
    "detect_inclusions",
    "segment_inclusion_at",
]

log = logging.getLogger(__name__)
#: Which inclusions :func:`detect_inclusions` looks for: brighter or darker than the body,
#: or both.
Polarity = Literal["bright", "dark", "both"]


@dataclass(frozen=True, eq=False)
class FiducialDetection:
    """Fiducial markers found in a scan.

    ``centres_lps_mm`` (k, 3), ``radii_mm`` (k,) volume-equivalent,
    ``peak`` (k,) normalised peak intensity, and ``quality`` (``n_candidates``, ``threshold``,
    ``n_found``, ``n_dropped``).

    Attributes
    ----------
    centres_lps_mm : numpy.ndarray, shape (k, 3)
        Marker centres, scan LPS, mm: centroids weighted by the partial-volume fractions
        above the blob's surroundings; sorted by L, then P, then S.
    radii_mm : numpy.ndarray, shape (k,)
        Volume-equivalent radius of each marker (from its summed partial-volume
        fractions), mm.
    peak : numpy.ndarray, shape (k,)
        Highest value of the smoothed normalised image in each marker (body level = 1).
    quality : dict
        ``n_candidates`` (blobs over the threshold, not enclosed by tissue; with
        ``apart``, those apart from the body),
        ``threshold`` (the marker threshold used, times the body level), ``n_found``
        (markers kept), ``n_dropped`` (a surplus left out by brightness), and ``apart``
        (True, only where dim markers apart from the body were taken).
    """

    centres_lps_mm: np.ndarray
    radii_mm: np.ndarray
    peak: np.ndarray
    quality: dict = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class InclusionDetection:
    """Inclusions found in a scan.

    ``centres_lps_mm`` (n, 3), ``diameters_mm`` (n,) volume-equivalent,
    ``contrast`` (n,) relative to the body level (positive: brighter), ``quality``.

    Attributes
    ----------
    centres_lps_mm : numpy.ndarray, shape (n, 3)
        Inclusion centres, scan LPS, mm: centroids weighted by the partial-volume
        fractions; in the order found (bright ones before dark ones with
        ``polarity="both"``).
    diameters_mm : numpy.ndarray, shape (n,)
        Volume-equivalent diameter of each inclusion, ``(6 V / pi)^(1/3)``, mm.
    contrast : numpy.ndarray, shape (n,)
        Signed difference of each inclusion's level from the body level on the normalised
        image (body level about 1): a fraction of the body level, positive brighter.
    quality : dict
        ``body_level`` (median of the smoothed normalised image inside the body),
        ``min_contrast``, ``noise_sd`` (robust sd of that image inside the body),
        ``threshold`` (the contrast threshold used), ``n_found``, ``n_surface_layer``
        (candidates left out as a surface layer's inner tail) and ``n_too_large``
        (candidates past the largest diameter).
    """

    centres_lps_mm: np.ndarray
    diameters_mm: np.ndarray
    contrast: np.ndarray
    quality: dict = field(default_factory=dict)


def _weighted_centroid(weights: np.ndarray, offset: np.ndarray) -> np.ndarray:
    ijk = np.argwhere(weights > 0)
    w = weights[weights > 0]
    return (ijk * w[:, None]).sum(0) / w.sum() + offset


#: Blobs named in a message (the rest are counted).
_LISTED = 8


def _at(c) -> str:
    return f"({c[0]:.1f}, {c[1]:.1f}, {c[2]:.1f})"


def detect_fiducials(
    seg: BodySegmentation,
    *,
    expected: int | None = 3,
    marker_ratio: float = 2.0,
    radius_range_mm: tuple[float, float] = (1.0, 6.0),
) -> FiducialDetection:
    """Find the small, very bright, compact marker blobs.

    Parameters
    ----------
    seg : BodySegmentation
        Output of :func:`imaging.segment.segment_body`.
    expected : int or None
        Expected marker count; ``None`` accepts any count. When more blobs pass, the
        ``expected`` brightest are kept only if they stand clear of the rest (the faintest
        kept at least :data:`MARKER_PEAK_GAP` times as far above the body level as the
        brightest left out: noisy inclusions lifted over the threshold); a warning names
        what was left out and ``quality["n_dropped"]`` counts it. Where fewer pass, blobs
        apart from the body are looked for down to :data:`MARKER_RATIO_APART` and taken
        where exactly ``expected`` are found, with a warning (``quality["apart"]``).
    marker_ratio : float
        Threshold on the smoothed normalised image (body = 1).
    radius_range_mm : (float, float)
        Accepted volume-equivalent radii of a blob.

    Raises
    ------
    FiducialError
        The number of markers found differs from ``expected`` (and a surplus does not
        stand apart by brightness); the message lists them with their peaks, and where
        too few were found the bright blobs rejected (and why) and the brightest point
        under the threshold (dim markers, as on thick slices).
    """
    crop = seg.crop
    ns = seg.smoothed.array[crop]
    bright = ns > marker_ratio
    # blobs that tissue encloses are inclusions brighter than the threshold, not markers
    enclosed = enclosed_blobs(seg.normalised.array[crop], bright)
    lab, nlab = ndimage.label(bright & ~enclosed)
    centres, radii, peaks, rejected = _blobs(seg, lab, radius_range_mm)
    found = len(centres)
    source = seg.mask.source.replace(" [body mask]", "")
    quality = {
        "n_candidates": int(nlab),
        "threshold": float(marker_ratio),
        "n_found": found,
        "n_dropped": 0,
    }
    apart_found = None
    if expected is not None and found < expected and marker_ratio > MARKER_RATIO_APART:
        # dim markers (thick slices, another contrast): blobs apart from the body, lower
        body = seg.mask.array[crop].astype(bool)
        low, _ = ndimage.label(ns > MARKER_RATIO_APART)
        touching = np.unique(low[body])
        low[np.isin(low, touching[touching > 0])] = 0
        n_low = len(np.unique(low[low > 0]))  # candidate blobs apart from the body
        apart = _blobs(seg, low, radius_range_mm)
        apart_found = len(apart[0])
        if apart_found == expected:
            log.warning(
                "%s: %d of %d fiducial markers over %g times the body level; %d compact "
                "blobs apart from the body over %g times it (peaks %s) taken as the "
                "markers (dim markers: thick slices or another contrast)",
                source,
                found,
                expected,
                marker_ratio,
                expected,
                MARKER_RATIO_APART,
                ", ".join(f"{p:.2f}" for p in apart[2]),
            )
            centres, radii, peaks, rejected = apart
            found = expected
            quality |= {"threshold": MARKER_RATIO_APART, "n_found": found, "apart": True}
            quality["n_candidates"] = n_low
    if expected is not None and found > expected:
        keep = _clear_markers(np.array(peaks), expected)
        if keep is not None:
            gone = sorted(set(range(found)) - set(keep))
            kept = ", ".join(f"{peaks[i]:.2f}" for i in keep)
            left = "; ".join(
                f"({centres[i][0]:.1f}, {centres[i][1]:.1f}, {centres[i][2]:.1f}) "
                f"r={radii[i]:.1f} mm, peak {peaks[i]:.2f}"
                for i in gone[:_LISTED]
            )
            if len(gone) > _LISTED:  # a bright skin breaks into hundreds of blobs
                left += f" and {len(gone) - _LISTED} more"
            log.warning(
                "%s: %d bright blobs for %d fiducials: kept the brightest (peaks %s times "
                "the body level) and left out %s (less than 1/%.1f as far above the body)",
                source,
                found,
                expected,
                kept,
                left,
                MARKER_PEAK_GAP,
            )
            centres, radii, peaks = ([x[i] for i in keep] for x in (centres, radii, peaks))
            quality["n_dropped"] = len(gone)
            found = len(centres)
    if expected is not None and found != expected:
        listing = "; ".join(
            f"{_at(c)} r={r:.1f} mm peak {p:.2f} x body"
            for c, r, p in zip(centres, radii, peaks, strict=True)
        )
        said = f"{source}: found {found} fiducial markers, expected {expected}"
        said += f": {listing}" if listing else ""
        if found < expected:  # what a user needs to see why markers were missed
            if rejected:
                said += f"; bright blobs rejected: {'; '.join(rejected[:_LISTED])}"
                said += f" and {len(rejected) - _LISTED} more" if len(rejected) > _LISTED else ""
            # away from the blobs over the threshold (their rims lie just under it)
            under = ns[~ndimage.binary_dilation(lab > 0, iterations=3)]
            if under.size:
                said += (
                    f"; away from those, the brightest point under the marker threshold "
                    f"({marker_ratio:g} times the body level) reaches {float(under.max()):.2f}"
                )
            if apart_found is not None:
                said += (
                    f"; apart from the body, {apart_found} compact blobs over "
                    f"{MARKER_RATIO_APART:g} times the body level"
                )
        raise FiducialError(said)
    order = np.lexsort(np.array(centres).T[::-1]) if centres else np.array([], int)
    return FiducialDetection(
        np.array(centres, float).reshape(-1, 3)[order],
        np.array(radii, float)[order],
        np.array(peaks, float)[order],
        quality,
    )


def _blobs(seg: BodySegmentation, lab: np.ndarray, radius_range_mm):
    """Marker-like blobs among the labelled components ``lab`` (of the cropped image).

    Returns the centres (LPS mm), volume-equivalent radii, peaks and, for those rejected,
    a line each saying where and why.
    """
    vol = seg.smoothed
    sp, vv = vol.spacing_mm, vol.voxel_volume_mm3
    crop = seg.crop
    ns = vol.array[crop]
    n = seg.normalised.array[crop]
    offset = np.array([s.start for s in crop], float)
    centres, radii, peaks, rejected = [], [], [], []
    for k, sl in enumerate(ndimage.find_objects(lab), start=1):
        if sl is None:  # a label cleared (a component touching the body)
            continue
        pad = tuple(
            slice(max(s.start - 3, 0), min(s.stop + 3, dim))
            for s, dim in zip(sl, ns.shape, strict=True)
        )
        comp = lab[pad] == k
        core = ndimage.binary_dilation(comp, iterations=2)
        shell = ndimage.binary_dilation(comp, iterations=3) & ~core
        base = float(np.median(n[pad][shell])) if shell.any() else 0.0
        peak = float(ns[pad][comp].max())
        w = np.where(core, np.clip(n[pad] - base, 0.0, None), 0.0)
        frac_vol = float(np.clip(w / max(peak - base, 1e-6), 0, 1).sum() * vv)
        r_eq = (3.0 * frac_vol / (4.0 * np.pi)) ** (1.0 / 3.0)
        extent = (np.array([s.stop - s.start for s in sl]) * sp).max()
        why = None
        if not radius_range_mm[0] <= r_eq <= radius_range_mm[1]:
            why = f"radius outside {radius_range_mm[0]:g}-{radius_range_mm[1]:g} mm"
        elif extent > 4.0 * r_eq + 2 * sp.max():
            why = f"extent {extent:.1f} mm, not compact"
        if why is not None:
            log.debug("rejected bright blob %d: r_eq %.2f mm, extent %.1f mm", k, r_eq, extent)
            box = offset + np.array([(s.start + s.stop - 1) / 2.0 for s in sl])
            at = _at(vol.index_to_lps(box[None])[0])
            rejected.append(f"{at} r={r_eq:.1f} mm peak {peak:.2f} ({why})")
            continue
        offs = offset + np.array([s.start for s in pad], float)
        centres.append(vol.index_to_lps(_weighted_centroid(w, offs)[None])[0])
        radii.append(r_eq)
        peaks.append(peak)
    return centres, radii, peaks, rejected


#: Where fewer than the expected markers pass the marker threshold, blobs apart from the
#: body (no voxel of theirs in its mask) are looked for again over this level (body = 1),
#: and taken where exactly the expected number of compact ones is found: markers dimmer
#: than twice the body (a 2.5 mm marker in 5 mm slices peaked under 2 from partial volume,
#: review T; another contrast agent). It lies clear of the smoothed background noise
#: (its peaks: 0.3-0.6 at SNR 8), whose specks are smaller than a marker in any case.
MARKER_RATIO_APART = 1.3


#: A surplus of bright blobs is resolved only when the faintest of the ``expected``
#: brightest stands this many times as far above the body level (1) as the brightest
#: of the rest: on the quick twin rendered at SNR 8 the markers peaked at 3.45-3.70 and
#: two inclusions, lifted by the noise, at 2.01-2.02 (a ratio of 2.4).
MARKER_PEAK_GAP = 1.5


def _clear_markers(peaks: np.ndarray, expected: int) -> list[int] | None:
    """Indices of the ``expected`` brightest blobs if they stand clear of the rest, else None."""
    order = np.argsort(-peaks, kind="stable")
    keep, rest = order[:expected], order[expected:]
    faintest, brightest_left = peaks[keep].min() - 1.0, peaks[rest].max() - 1.0
    if faintest >= MARKER_PEAK_GAP * brightest_left:
        return sorted(int(i) for i in keep)
    return None


def _rises_outward(dev_s: np.ndarray, depth: np.ndarray, peak: tuple[int, ...]) -> bool:
    """Whether a neighbour of ``peak`` nearer the surface (inside the body) is as extreme.

    A surface layer's contrast grows towards the surface, so the extreme of its inner
    tail has such a neighbour in the margin; an inclusion's extreme is its own (review
    BM: with the rule on depth alone, a 4.7 mm inclusion 7.5 mm deep in 6 mm slices lay
    within one voxel of the margin and was dropped as a layer).
    """
    box = tuple(slice(max(i - 1, 0), i + 2) for i in peak)
    d, v = depth[box], dev_s[box]
    return bool(((d < depth[peak]) & (d > 0) & (v >= dev_s[peak])).any())


def detect_inclusions(
    seg: BodySegmentation,
    *,
    min_contrast: float = 0.15,
    noise_sigmas: float = 4.5,
    diameter_range_mm: tuple[float, float] = (2.0, 15.0),
    edge_margin_mm: float = 2.0,
    polarity: Polarity = "bright",
) -> InclusionDetection:
    """Find compact regions of distinct intensity inside the body.

    Parameters
    ----------
    seg : BodySegmentation
        Output of :func:`imaging.segment.segment_body`.
    min_contrast : float
        Minimum relative difference from the body level (smoothed image) of a candidate.
    noise_sigmas : float
        The threshold is at least this many standard deviations of the smoothed image's
        noise inside the body (a robust MAD): at SNR 8 a threshold of 0.15 alone let
        1,384 noise blobs through on the quick twin (19 inclusions; 31 found with this
        bound), and tracking them across postures ran out of memory. At the twins' SNR
        of 30 the smoothed noise sd is 0.032, so ``min_contrast`` (0.15 > 4.5 x 0.032)
        stays the threshold.
    diameter_range_mm : (float, float)
        Accepted volume-equivalent diameters.
    edge_margin_mm : float
        Voxels closer than this to the body surface are ignored (skin, partial volume).
        A candidate whose extreme lies within one voxel of that margin and has a
        neighbour nearer the surface as extreme (:func:`_rises_outward`) is not a blob but
        the inner tail of a surface layer (a skin brighter or darker than the body: its
        contrast grows towards the surface) and is left out, counted in
        ``quality["n_surface_layer"]``. On a rendered 1.5 mm skin 1.3-1.9 times the body,
        20-97 such fragments were taken for inclusions.
    polarity : {"bright", "dark", "both"}
        Which contrast sign to look for.

    Returns
    -------
    InclusionDetection
        ``centres_lps_mm`` (n, 3) in the scan's LPS frame, ``diameters_mm`` (n,),
        ``contrast`` (n,) and the ``quality`` record.

    Raises
    ------
    ValueError
        ``polarity`` is not one of the three choices.
    """
    if polarity not in get_args(Polarity):
        raise ValueError(f"polarity must be 'bright', 'dark' or 'both', got {polarity!r}")
    from skimage.segmentation import expand_labels

    crop = seg.crop
    body = seg.mask.array[crop].astype(bool)
    sp, vv = seg.mask.spacing_mm, seg.mask.voxel_volume_mm3
    depth = ndimage.distance_transform_edt(body, sampling=sp)
    inner = depth > edge_margin_mm
    layer_depth = edge_margin_mm + float(np.max(sp))
    n_layer = 0
    ns, n = seg.smoothed.array[crop], seg.normalised.array[crop]
    level = float(np.median(ns[inner])) if inner.any() else 1.0
    noise_sd = robust_sd(ns[inner]) if inner.any() else 0.0
    threshold = max(float(min_contrast), noise_sigmas * noise_sd)
    signs = {"bright": [1.0], "dark": [-1.0], "both": [1.0, -1.0]}[polarity]
    offset = np.array([s.start for s in crop], float)
    centres, diams, contrasts = [], [], []
    too_large = []  # (diameter, centre) of candidates past the upper diameter
    for sgn in signs:
        dev_s, dev = sgn * (ns - level), sgn * (n - level)
        lab, nlab = ndimage.label((dev_s > threshold) & inner)
        region = expand_labels(lab, distance=2) * inner
        for k, sl in enumerate(ndimage.find_objects(region), start=1):
            if sl is None:
                continue
            comp, reg = lab[sl] == k, region[sl] == k
            top = float(dev_s[sl][comp].max())
            peak = tuple(
                int(a.start + i)
                for a, i in zip(sl, np.argwhere(comp)[np.argmax(dev_s[sl][comp])], strict=True)
            )
            if depth[peak] < layer_depth and _rises_outward(dev_s, depth, peak):
                n_layer += 1  # its extreme on the margin: a surface layer's inner tail
                continue
            c = float(np.median(dev[sl][comp & (dev_s[sl] >= 0.9 * top)]))
            f = np.where(reg, dev[sl] / max(c, 1e-6), 0.0)
            d_eq = float((6.0 * f.sum() * vv / np.pi) ** (1.0 / 3.0)) if f.sum() > 0 else 0.0
            if d_eq < diameter_range_mm[0]:
                continue
            w = np.clip(f, 0.0, 1.0)
            idx = _weighted_centroid(w, offset + np.array([s.start for s in sl], float))
            centre = seg.mask.index_to_lps(idx[None])[0]
            if d_eq > diameter_range_mm[1]:
                too_large.append((d_eq, centre))
                continue
            centres.append(centre)
            diams.append(d_eq)
            contrasts.append(sgn * c)
    quality = {
        "body_level": level,
        "min_contrast": float(min_contrast),
        "noise_sd": noise_sd,
        "threshold": threshold,
        "n_found": len(diams),
        "n_surface_layer": n_layer,
        "n_too_large": len(too_large),
    }
    if too_large:
        log.warning(
            "%s: %d region(s) of inclusion contrast larger than the %g mm the detection "
            "accepts were left out (volume-equivalent diameters %s mm, centres LPS %s): an "
            "inclusion or tumour that large is not detected, nor tracked",
            seg.mask.source,
            len(too_large),
            diameter_range_mm[1],
            ", ".join(f"{d:.1f}" for d, _ in too_large[:_LISTED]),
            " ".join(_at(c) for _, c in too_large[:_LISTED]),
        )
    return InclusionDetection(
        np.array(centres, float).reshape(-1, 3), np.array(diams), np.array(contrasts), quality
    )


@dataclass(frozen=True, eq=False)
class InclusionMask:
    """Lesion or inclusion grown from a seed.

    ``mask`` (uint8 Volume on the scan grid),
    ``centre_lps_mm`` (3,), ``diameter_mm`` (volume-equivalent), ``threshold`` (raw units).

    Attributes
    ----------
    mask : Volume
        uint8 volume on the scan's grid (its affine and source): 1 in the object, 0
        elsewhere.
    centre_lps_mm : numpy.ndarray, shape (3,)
        Centroid of the object's voxels (unweighted), scan LPS, mm.
    diameter_mm : float
        Volume-equivalent diameter of the object's voxels, ``(6 V / pi)^(1/3)``, mm.
    threshold : float
        The local threshold on the lightly smoothed image, in the scan's own intensity
        units: half-way between the seed's neighbourhood level and the box's median.
    """

    mask: Volume
    centre_lps_mm: np.ndarray
    diameter_mm: float
    threshold: float


def _ball(radius_mm: float, spacing_mm: np.ndarray) -> np.ndarray:
    """Boolean structuring element: voxel offsets within an ellipsoid of radius_mm."""
    half = np.floor(radius_mm / spacing_mm).astype(int)
    grids = np.meshgrid(
        *[np.arange(-h, h + 1) * s for h, s in zip(half, spacing_mm, strict=True)], indexing="ij"
    )
    return sum(g**2 for g in grids) <= radius_mm**2 + 1e-9


def segment_inclusion_at(
    volume: Volume,
    seed_lps_mm: np.ndarray,
    *,
    radius_mm: float = 20.0,
    smoothing_mm: float = 0.5,
    opening_mm: float = 0.8,
) -> InclusionMask:
    """Segment the bright object that contains a seed point (local threshold + region growing).

    Inside a box of half-size ``radius_mm`` around the seed the image is lightly smoothed;
    the threshold is half-way between the object level (median of the seed's neighbourhood)
    and the surrounding tissue level (median of the box); a morphological opening with a
    ball of radius ``opening_mm`` cuts thin bright bridges (vessels) to neighbouring
    structures; the connected component holding the seed (or the nearest one) is kept,
    its opened rim restored within the threshold mask, and its holes are filled slice by
    slice and in 3-D.

    Raises
    ------
    SegmentationError
        The seed lies outside the volume, or no object brighter than its surroundings is there.
    """
    seed = np.asarray(seed_lps_mm, float).reshape(3)
    ijk = np.rint(volume.lps_to_index(seed[None])[0]).astype(int)
    shape = np.array(volume.shape)
    if np.any(ijk < 0) or np.any(ijk >= shape):
        raise SegmentationError(f"{volume.source}: seed {seed.tolist()} mm lies outside the volume")
    sp = volume.spacing_mm
    half = np.ceil(radius_mm / sp).astype(int)
    lo, hi = np.maximum(ijk - half, 0), np.minimum(ijk + half + 1, shape)
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
    a = ndimage.gaussian_filter(np.asarray(volume.array[box], np.float32), smoothing_mm / sp)
    s = ijk - lo
    nb = a[tuple(slice(max(v - 1, 0), v + 2) for v in s)]
    obj, tissue = float(np.median(nb)), float(np.median(a))
    if obj <= tissue:
        raise SegmentationError(
            f"{volume.source}: no bright object at {seed.tolist()} mm (level {obj:.3g} <= "
            f"surroundings {tissue:.3g})"
        )
    thr = 0.5 * (obj + tissue)
    above = a > thr
    st = _ball(opening_mm, sp)
    lab, _ = ndimage.label(ndimage.binary_opening(above, st) if st.sum() > 1 else above)
    k = lab[tuple(s)]
    if k == 0:
        pts = np.argwhere(lab > 0)
        k = lab[tuple(pts[np.argmin(np.linalg.norm((pts - s) * sp, axis=1))])]
    comp = lab == k
    if st.sum() > 1:  # give back the rim the opening took, within the threshold mask
        comp = ndimage.binary_dilation(comp, st) & above
    for z in range(comp.shape[2]):
        comp[:, :, z] = ndimage.binary_fill_holes(comp[:, :, z])
    comp = ndimage.binary_fill_holes(comp)
    mask = np.zeros(volume.shape, np.uint8)
    mask[box] = comp
    centre = volume.index_to_lps((np.argwhere(comp).mean(0) + lo)[None])[0]
    d = float((6.0 * comp.sum() * volume.voxel_volume_mm3 / np.pi) ** (1.0 / 3.0))
    return InclusionMask(Volume(mask, volume.affine_lps_from_index, volume.source), centre, d, thr)
