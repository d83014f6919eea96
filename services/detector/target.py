"""The target face in a downscaled membership map: its region, ring ellipses, centre and a
confidence that means something (below the threshold the face is reported as not seen).

`find_face` tells the method: the region of target colour fitted with a robust ellipse, the
nested ring discs of the target GMM's colours fitted inside it and the centre extrapolated from
them (`rings`); `FaceFit` tells what its confidence multiplies. All positions are pixels of
the downscaled map.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from archery.services.detector.arcs import ring_from_arcs
from archery.services.detector.pieces import joined_hull
from archery.services.detector.rings import (
    Ellipse,
    centre_spread,
    fit_disc,
    nested_centre,
    radial_position,
)

__all__ = ["FaceFit", "colour_groups", "find_face", "merge_faces"]

_MEMBER = 96  # membership (0..255) of a pixel counted as target colour
_CANDIDATES = 5  # largest regions examined
_JOIN_BELOW = 0.75  # a best region less confident than this: its pieces are joined too
_JOIN_SEEDS = 3  # largest regions whose neighbouring pieces are joined
_MIN_COMPONENT_SHARE = 0.03  # a GMM component with fewer of the region's pixels is no ring
_SAME_RING = 0.15  # components whose median radial positions differ less share a ring
_EDGE_INSIDE = 0.6  # least share of a disc's colours just inside its ellipse
_EDGE_OUTSIDE = 0.35  # largest share of them just outside it
_EDGE_MIN_RADIUS = 8.0  # px: a smaller ring's edge is not judged (its bands are 1–2 px)
_EDGE_POINTS = 3000  # about this many of the face's pixels judge the edges
_SMALL_RING = 20.0  # px: a lone inner ring this small is judged by a lower support
_WHOLE = 0.95  # support of a ring fit that its disc's pieces joined cannot better
_RINGED_COLOUR = (0.1, 0.3)  # colour agreement ramp of a face whose inner rings agree
_ELLIPTIC_IOU = 0.9  # a region overlapping its ellipse less is bridged across slits, judged again
_SLIT = 0.2  # widest slit bridged, over the outer radius
_SPACING = 0.1  # an inner ring's size may differ this much from k / (colours) of the outer one
_MAX_SPREAD = 0.03  # rings whose centres stray farther from the perspective model (over the
# outer radius) are not the face's


@dataclass(frozen=True)
class FaceFit:
    """A face found in the map: centre (px), its ring ellipses inner → outer (px; the last is
    the outer boundary of the coloured rings), confidence 0..1 and its factors.

    The confidence multiplies how much of the outer boundary was seen (or, for a face cut by
    the border, of its inner rings), how elliptic the region is, how well its colours match the
    calibration (judged more leniently once inner rings agree), how many inner rings agree (a
    lone one as far as it is seen whole) and how many of the calibrated colours (ring groups of
    the GMM's components) the face shows; the factors' ranges were set on the development set
    (`tests.devset`) so that wrong centres score below 0.5.
    """

    centre: tuple[float, float]
    ellipses: tuple[Ellipse, ...]
    confidence: float
    factors: dict[str, float]
    colours: frozenset[int] = frozenset()  # the calibrated colours (ring groups) it shows
    n_colours: int = 0  # how many the calibration has
    agreement: float = 0.0  # mean target membership (0..1) inside the outer ellipse
    side: int = 0  # px: the map's longer side (bounds the perspective shift of its rings)

    @property
    def outer(self) -> Ellipse:
        """The coloured rings' outer boundary."""
        return self.ellipses[-1]


def _ramp(value: float, low: float, high: float) -> float:
    return min(1.0, max(0.0, (value - low) / (high - low)))


def _ellipse_mask(ellipse: Ellipse, shape: tuple[int, int]) -> np.ndarray:
    mask = np.zeros(shape, np.uint8)
    cv2.ellipse(mask, ellipse.cv_box(), 1, thickness=cv2.FILLED)
    return mask


def _fill(region: np.ndarray) -> np.ndarray:
    """The region with its holes filled (largest outline only)."""
    contours, _ = cv2.findContours(region, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    filled = np.zeros_like(region)
    if contours:
        cv2.drawContours(filled, [max(contours, key=cv2.contourArea)], -1, 1, cv2.FILLED)
    return filled


def _pieces_joined(disc: np.ndarray) -> np.ndarray | None:
    """When a shaft cuts a ring's disc into pieces: their convex hull filled
    (`pieces.joined_hull`), else None."""
    outlines, _ = cv2.findContours(disc, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    if len(outlines) < 2:
        return None
    areas = [cv2.contourArea(outline) for outline in outlines]
    hull = joined_hull(outlines, areas, int(np.argmax(areas)))
    if hull is None:
        return None
    filled = np.zeros_like(disc)
    cv2.drawContours(filled, [hull], -1, 1, cv2.FILLED)
    return filled


def _edge(ring: Ellipse, points: np.ndarray, ours: np.ndarray) -> bool:
    """Whether a fitted disc's ellipse is where its colours end: of the target-coloured
    `points` (N, 2) just inside it most are the disc's (`ours`, N booleans), of those just
    outside few (an ellipse fitted to a disc half hidden by arrows and fletchings cuts through
    its colours). A ring too small for bands of a few pixels passes; so does one with no
    target colour just outside it."""
    if ring.radius < _EDGE_MIN_RADIUS:
        return True
    rho = radial_position(ring, points)
    inside, outside = (rho > 0.7) & (rho < 0.95), (rho > 1.08) & (rho < 1.3)
    if inside.sum() < 10 or ours[inside].mean() < _EDGE_INSIDE:
        return False
    return bool(outside.sum() < 10 or ours[outside].mean() <= _EDGE_OUTSIDE)


def _agrees(ring: Ellipse, outer: Ellipse) -> bool:
    """Whether an inner ring's ellipse can be one of the face whose outer ring is `outer`:
    near its centre, smaller, of its shape and well supported."""
    shift = math.hypot(ring.centre[0] - outer.centre[0], ring.centre[1] - outer.centre[1])
    return (
        shift < 0.25 * outer.radius
        # rings of a face: ≤ 2/3 of the next; the gold, the smallest, a third of the outer
        and 0.25 < ring.radius / outer.radius < 0.8
        and abs(ring.ratio - outer.ratio) < 0.15 + 0.5 * (1.0 - ring.support)
        and ring.support > 0.5
    )


def colour_groups(
    means: np.ndarray, weights: np.ndarray, distance: float = 30.0, least: float = 0.2
) -> np.ndarray:
    """Group id per GMM component (K,): components whose UV means (K, 2) chain within
    `distance` UV levels are one colour (one ring of the face); a group of total prior below
    `least` (stray calibration pixels, ring borders) gets id −1, a colour a face need not show."""
    count = len(means)
    group = np.arange(count)
    for i in range(count):
        for j in range(i + 1, count):
            if np.hypot(*(means[i] - means[j])) < distance:
                group[group == group[j]] = group[i]
    ids = np.unique(group, return_inverse=True)[1]
    mass = np.bincount(ids, weights=weights)
    kept = {int(old): new for new, old in enumerate(np.flatnonzero(mass >= least))}
    return np.array([kept.get(int(i), -1) for i in ids], dtype=np.int64)


def _inner_rings(
    outer: Ellipse,
    mask: np.ndarray,
    components: np.ndarray,
    kernel: np.ndarray,
    groups: np.ndarray,
) -> tuple[list[Ellipse], set[int]]:
    """Fitted cumulative discs inside `outer` that agree with it, and which of the calibrated
    colours (`groups`: colour per component) the face shows."""
    ys, xs = np.nonzero(mask)
    if len(xs) < 30:
        return [], set()
    rho = radial_position(outer, np.stack([xs, ys], axis=1))
    labels = components[ys, xs]
    inside = rho < 1.05
    order = []
    for k in np.unique(labels[inside]):
        share = labels[inside] == k
        if share.mean() >= _MIN_COMPONENT_SHARE:
            order.append((float(np.median(rho[inside][share])), int(k)))
    order.sort()
    shown = {int(groups[k]) for _, k in order if k < len(groups) and groups[k] >= 0}
    rings: list[list[int]] = []
    last = -1.0
    for position, k in order:
        if rings and position - last < _SAME_RING:
            rings[-1].append(k)
        else:
            rings.append([k])
        last = position
    found: list[Ellipse] = []
    chosen: list[int] = []
    step = max(1, len(xs) // _EDGE_POINTS)  # the edge bands judged on a sample of the pixels
    points, sampled = np.stack([xs, ys], axis=1)[::step], labels[::step]

    def ours(chosen: list[int]) -> np.ndarray:
        return np.isin(sampled, chosen)

    def better(ring: Ellipse | None, best: Ellipse | None, chosen: list[int]) -> bool:
        """A fit better supported than `best`, in the outer ring's shape and on the edge of
        the colours `chosen`."""
        return (
            ring is not None
            and (best is None or ring.support > best.support)
            and _agrees(ring, outer)
            and _edge(ring, points, ours(chosen))
        )

    for ring_components in rings[:-1]:
        chosen += ring_components
        disc: np.ndarray = (mask & np.isin(components, chosen)).astype(np.uint8)
        disc = cv2.morphologyEx(disc, cv2.MORPH_CLOSE, kernel)
        # the disc's largest piece or, unless that is seen whole, its pieces joined (a shaft
        # cuts it): the better seen
        best: Ellipse | None = None
        for fill in (_fill, _pieces_joined):
            if best is not None and best.support >= _WHOLE:
                break
            filled = fill(disc)
            ring = fit_disc(filled) if filled is not None else None
            if better(ring, best, chosen):
                best = ring
        if best is None or best.support < _WHOLE:  # arrows cut it up: the arcs of its edge
            rest = (mask & ~np.isin(components, chosen)).astype(np.uint8)
            ring = ring_from_arcs(outer, disc, rest, kernel)
            if better(ring, best, chosen):
                best = ring
        if best is not None:
            found.append(best)
    return found, shown


def _concentric(rings: list[Ellipse], outer: Ellipse) -> list[Ellipse]:
    """The inner rings less those that break the perspective model of concentric rings
    (`rings.centre_spread`; fits to what covers the gold, a colour of no ring): the one whose
    removal helps most, until the rest agree; of two, the one farther off the outer ring's
    centre for its size."""
    rings = list(rings)
    while len(rings) >= 2 and centre_spread([*rings, outer]) > _MAX_SPREAD:
        if len(rings) == 2:  # either alone fits the model: judge each against the outer ring
            off = [math.dist(ring.centre, outer.centre) / ring.radius for ring in rings]
            del rings[int(np.argmax(off))]
            continue
        spreads = [centre_spread([*rings[:i], *rings[i + 1 :], outer]) for i in range(len(rings))]
        del rings[int(np.argmin(spreads))]
    return rings


def _spaced(ring: Ellipse, outer: Ellipse, n_colours: int) -> bool:
    """Whether an inner ring's size fits the face's rings of equal width: the disc of k of
    its `n_colours` colours is k / n_colours of the outer one across (a lone ring of another
    size is a fit to what covers the face, or the outer ring was fitted inside its colours)."""
    share = ring.radius / outer.radius * n_colours
    return abs(share - round(share)) <= _SPACING * round(share)


def _seen(factors: dict[str, float]) -> float:
    """How much of the outer ring was seen: its support times its share inside the image."""
    return factors["support"] * factors["visible"]


def _rings_factor(outer: Ellipse, inner: list[Ellipse], n_colours: int) -> float:
    """Trust from the inner rings that agree with the outer one: two or more make the centre
    sure; a lone one as far as it is seen whole (arrows over the gold leave fits to what covers
    it); with none, an oblique view (a flat ellipse) leaves the perspective shift of the outer
    ellipse's centre unknown, so the trust falls with its axis ratio."""
    if len(inner) >= 2:
        return 1.0
    if len(inner) == 1 and not _spaced(inner[0], outer, n_colours):
        return 0.0
    if len(inner) == 1:  # a small ring's support is limited by its pixels
        low = 0.75 if inner[0].radius >= _SMALL_RING else 0.6
        return 0.8 * _ramp(inner[0].support, low, low + 0.25)
    return 0.6 * _ramp(outer.ratio, 0.6, 0.9)


def _colour_factor(agreement: float, inner: list[Ellipse]) -> float:
    """Trust from how well the face's colours match the calibration (`agreement`: mean
    membership 0..1 inside the outer ellipse); two inner rings or more that agree with the outer
    one, or one seen whole, show the calibrated colours' layout, so paler colours (sun, light,
    JPEG, ring blends on a small face) are trusted sooner."""
    if len(inner) >= 2 or (inner and inner[0].support >= _WHOLE):
        return _ramp(agreement, *_RINGED_COLOUR)
    return _ramp(agreement, 0.15, 0.5)


def _overlap(
    filled_crop: np.ndarray, corner: tuple[int, int], ellipse: np.ndarray, box: tuple[int, int]
) -> float:
    """Intersection over union of a filled region (a crop of the map with its corner (x, y)
    px) and an ellipse's mask (drawn in its box, whose corner is `box` (x, y) px)."""
    x0, y0 = box
    height, width = ellipse.shape
    filled = np.zeros_like(ellipse)  # the filled region in the ellipse's box
    cx, cy = corner
    sx0, sy0 = max(x0, cx), max(y0, cy)
    sx1 = min(x0 + width, cx + filled_crop.shape[1])
    sy1 = min(y0 + height, cy + filled_crop.shape[0])
    if sx1 > sx0 and sy1 > sy0:
        filled[sy0 - y0 : sy1 - y0, sx0 - x0 : sx1 - x0] = filled_crop[
            sy0 - cy : sy1 - cy, sx0 - cx : sx1 - cx
        ]
    outside = np.count_nonzero(filled_crop) - np.count_nonzero(filled)
    union = float(np.count_nonzero(ellipse | filled)) + outside
    return float(np.count_nonzero(ellipse & filled)) / union


def _examine(
    member: np.ndarray,
    components: np.ndarray | None,
    groups: np.ndarray | None,
    region: np.ndarray,
    corner: tuple[int, int],
    kernel: np.ndarray,
    needed: float,
) -> FaceFit | None:
    """The face a region (a crop of the map with its corner (x, y) px) is, or None; the rings
    are only looked at when the rest of the evidence could reach `needed` confidence."""
    height, width = member.shape
    filled_crop = _fill(region)
    outer = fit_disc(filled_crop, corner, (height, width))
    if outer is None or outer.radius < 3.0:
        return None
    full_area = math.pi * outer.axes[0] * outer.axes[1] / 4
    if full_area > 6 * height * width:
        return None
    x0, y0, x1, y1 = outer.box((height, width))
    local = outer.moved(-x0, -y0)
    ellipse = _ellipse_mask(local, (y1 - y0, x1 - x0))
    inside_image = float(ellipse.sum())
    if inside_image < 20:
        return None
    iou = _overlap(filled_crop, corner, ellipse, (x0, y0))
    if iou < _ELLIPTIC_IOU:  # a slit (a shaft's shadow) may open the hole left by the gold
        slit = max(3, round(_SLIT * outer.radius) | 1)
        bridge = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (slit, slit))
        bridged = _fill(cv2.morphologyEx(region, cv2.MORPH_CLOSE, bridge))
        iou = max(iou, _overlap(bridged, corner, ellipse, (x0, y0)))
    box_member = member[y0:y1, x0:x1]
    agreement = float(box_member[ellipse > 0].mean()) / 255.0
    factors = {
        "support": _ramp(outer.support, 0.55, 0.85),
        "visible": _ramp(inside_image / full_area, 0.6, 0.9),
        # a one-pixel boundary error costs a disc of radius r about 4/r of IoU: small faces
        # are judged by what their pixels allow
        "elliptic": _ramp(iou + min(0.15, 2.0 / outer.radius), 0.75, 0.92),
        "colour": _colour_factor(agreement, []),
    }
    rings: list[Ellipse] = []
    shown: set[int] = set()
    n_colours = 0
    if components is not None and groups is not None:
        # the most its rings could make of it (a face cut by the border may be seen by them)
        best_case = factors["elliptic"] * _colour_factor(agreement, [outer, outer])
        if best_case < needed:
            return FaceFit(outer.centre, (outer,), 0.0, factors)  # the rings cannot save it
        mask = (box_member > _MEMBER).astype(np.uint8) & ellipse
        found, shown = _inner_rings(local, mask, components[y0:y1, x0:x1], kernel, groups)
        rings = [ring.moved(x0, y0) for ring in found]
        rings = _concentric(rings, outer)
        n_colours = max(1, int(groups.max()) + 1)
        # a face cut by the border: its inner rings (or one seen whole) say it is seen
        if len(rings) >= 2 or (rings and rings[0].support >= _WHOLE):
            inner = _ramp(min(ring.support for ring in rings), 0.55, 0.85)
            if inner > _seen(factors):
                factors["support"], factors["visible"] = inner, 1.0
        factors["rings"] = _rings_factor(outer, rings, n_colours)
        factors["colour"] = _colour_factor(agreement, rings)
        # a face showing fewer of the calibrated colours is a part of it (the yellow alone)
        factors["complete"] = _ramp(len(shown) / n_colours, 0.2, 1.0)
    confidence = math.prod(factors.values())
    ellipses = (*sorted(rings, key=lambda e: e.radius), outer)
    side = max(height, width)
    centre = nested_centre(list(ellipses), side)
    return FaceFit(
        centre, ellipses, confidence, factors, frozenset(shown), n_colours, agreement, side
    )


def merge_faces(first: FaceFit, second: FaceFit) -> FaceFit | None:
    """One face from two fits of it under different colour corrections (e.g. the yellow found
    as is, the blue only after white balance): their rings together, if concentric; None if
    they are not the same face or have no ring colours to join."""
    if not first.n_colours or first.n_colours != second.n_colours:
        return None
    small = min(first.outer.radius, second.outer.radius)
    if math.dist(first.outer.centre, second.outer.centre) > 0.15 * small:
        return None
    rings: list[Ellipse] = []
    for ring in sorted((*first.ellipses, *second.ellipses), key=lambda e: e.radius):
        if rings and ring.radius < 1.08 * rings[-1].radius:
            if ring.support > rings[-1].support:
                rings[-1] = ring
            continue
        rings.append(ring)
    if centre_spread(rings) > _MAX_SPREAD:
        return None
    owner = first if first.outer.radius >= second.outer.radius else second
    factors = {k: v for k, v in owner.factors.items() if k not in ("rings", "complete")}
    factors["rings"] = _rings_factor(rings[-1], rings[:-1], first.n_colours)
    factors["colour"] = _colour_factor(owner.agreement, rings[:-1])
    colours = first.colours | second.colours
    factors["complete"] = _ramp(len(colours) / first.n_colours, 0.2, 1.0)
    confidence = math.prod(factors.values())
    ellipses = tuple(rings)
    centre = nested_centre(rings, owner.side)
    return FaceFit(
        centre, ellipses, confidence, factors, colours, first.n_colours, owner.agreement, owner.side
    )


def find_face(
    member: np.ndarray,
    components: np.ndarray | None = None,
    groups: np.ndarray | None = None,
    *,
    close_fraction: float = 0.01,
    min_fraction: float = 5e-4,
    needed_confidence: float = 0.0,
) -> FaceFit | None:
    """The most confident face in a membership map (uint8 0..255, downscaled), or None.

    The target's colour membership is thresholded, closed (ring lines, holes) and split into
    regions by their outer contours; each of the largest few is filled and its outer boundary
    fitted with a robust ellipse (`rings.fit_disc`); when none is sure, the pieces of a face
    cut by shafts are joined too (`pieces.joined_hull`). With the target GMM's component of
    every pixel, the components are ordered by their radial position inside that ellipse
    (yellow, red, blue…) and the cumulative discs (yellow; yellow + red; …) are fitted too (from
    their pieces joined when a shaft cuts them): an inner ring must end where its colours end,
    and concentric ellipses of one shape validate each other (rings off the perspective model
    are dropped), and the centre is extrapolated from them (`rings.nested_centre`), which holds
    when arrows and fletchings cover part of the yellow. A disc that arrows and their shadows
    cut up beyond both is fitted from the arcs where its colours meet the next ring's, in the
    outer ring's shape (`arcs.ring_from_arcs`). A region's shape is judged once slits (a
    shaft's shadow reaching the hidden gold) are bridged, and a lone inner ring only if its
    size is k/n of the outer ring's (the rings are of equal width).

    Args:
        member: target membership per pixel.
        components: the target GMM's most responsible component per pixel (uint8), or None to
            fit the outer boundary only.
        groups: the colour (ring) of each component (`colour_groups`), with `components`.
        close_fraction: closing kernel over the map's shorter side (bridges ring lines).
        min_fraction: smallest region examined, as a fraction of the map.
        needed_confidence: a region that cannot reach this is not analysed ring by ring.
    """
    mask = (member > _MEMBER).astype(np.uint8)
    size = max(3, round(min(member.shape) * close_fraction) | 1)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    closed = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel)
    outlines, _ = cv2.findContours(closed, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    areas = [cv2.contourArea(outline) for outline in outlines]
    best: FaceFit | None = None
    pad = 2
    smallest = max(20.0, min_fraction * member.size)
    for index in np.argsort(areas)[::-1][:_CANDIDATES]:
        if areas[index] < smallest:
            break
        x, y, w, h = cv2.boundingRect(outlines[index])
        x0, y0 = max(0, x - pad), max(0, y - pad)
        region = np.zeros((h + y - y0 + pad, w + x - x0 + pad), np.uint8)
        cv2.drawContours(region, outlines, int(index), 1, cv2.FILLED, offset=(-x0, -y0))
        needed = needed_confidence if best is None else max(needed_confidence, best.confidence)
        fit = _examine(member, components, groups, region, (x0, y0), kernel, needed)
        if fit is not None and (best is None or fit.confidence > best.confidence):
            best = fit
    if best is None or best.confidence < _JOIN_BELOW:  # a face cut into pieces by shafts?
        for seed in np.argsort(areas)[::-1][:_JOIN_SEEDS]:
            if areas[seed] < smallest:
                break
            hull = joined_hull(outlines, areas, int(seed))
            if hull is None:
                continue
            x, y, w, h = cv2.boundingRect(hull)
            region = np.zeros((h + 2 * pad, w + 2 * pad), np.uint8)
            cv2.drawContours(region, [hull], -1, 1, cv2.FILLED, offset=(pad - x, pad - y))
            needed = needed_confidence if best is None else max(needed_confidence, best.confidence)
            fit = _examine(member, components, groups, region, (x - pad, y - pad), kernel, needed)
            if fit is not None and (best is None or fit.confidence > best.confidence):
                best = fit
    return best
