"""Step 4 of the greenhouse paper (section 3.5): the obstacle decision, in one place.

The paper's rule: a connected group (8-connected) of at least ``min_pixels`` (30) suspected
pixels that are (i) above and adjacent to surface pixels and (ii) classified as none of the
traversable classes (bush, pepper; an UNDEFINED pixel is not traversable) is an obstacle. Colour
and texture are judged separately and an obstacle from either counts (colour OR texture: the
paper's safe side).

"Above and adjacent": at least one pixel of the group has a surface pixel within ``contact_px``
rows straight below it in the image (1 = the next row, the paper's adjacency).

Every cue enters :func:`decide` as a per-pixel map (colour class, texture class, height above
the ground plane); a new cue (e.g. a learned obstacle score) is one more input there and one
more line in its combination, the rest of the pipeline does not change. What :class:`Rule`
adds to the paper (each off in ``Rule.paper()``, each measured in docs/rgbd.md):

- ``ground_max_height_m`` > 0: the *surface* an obstacle must stand on is low ground (height
  above the mount's ground plane under this), not any level patch -- bush tops are level too.
- ``ground_classes``: a pixel of such a class (the "ground" of the model) lower than
  ``ground_max_height_m`` is traversable: ground texture at ground height is the path, a clod,
  a leaf lying on it. The paper lists only bush and pepper as traversable.
- ``texture_contact_px``: texture decides per window (20x20); the window that straddles an
  obstacle's foot holds ground texture (traversable at ground height), so the obstacle's
  texture group ends up to a window above the ground: it may touch the surface that far below.
- ``open_px``: a morphological opening of each candidate map before grouping: scattered
  undefined pixels in the leaves (shading) do not add up to a group of 30.
- ``bottom_rows``: a group reaching the last rows of the image stands on ground the camera
  cannot see (close obstacles: the lowest ray of the greenhouse camera meets the ground 1.5 m
  ahead of it); the paper's any-level-surface rule found those on their own top faces.
- ``min_height_m``: a group must reach this height above the ground plane (at least
  TALL_MIN_PX pixels): leaves and clods lying on the path are not obstacles.
- ``ground_class_contact``: a colour group may stand on the surface through steep pixels of a
  ground class at ground height right below it. An obstacle coloured like the ground (a
  soil-coloured bucket) has its lower face traversable by the ground-class rule; without this
  only its top above ``ground_max_height_m`` is left, floating, with no surface under it.
- ``texture_role = "traversable-colour"``: texture judges only the pixels colour called
  traversable (it is there for obstacles coloured like a class: the bush-green crate) and its
  UNDEFINED windows are no evidence there (``texture_undefined = False``); the paper's
  ``"or"`` lets texture turn any suspected pixel into an obstacle.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

UNDEFINED = -1
NOT_CLASSIFIED = -2
TALL_MIN_PX = 10        # pixels above min_height_m a group needs (one noisy pixel is not height)


def touching_ground(mask: np.ndarray, surface: np.ndarray, contact_px: int = 1) -> np.ndarray:
    """Pixels of ``mask`` with a ``surface`` pixel 1..contact_px rows below them."""
    k = max(1, contact_px)
    if k == 1:
        touch = np.zeros(mask.shape, bool)
        touch[:-1] = mask[:-1] & surface[1:]
        return touch
    # one dilation by a column kernel that looks 1..k rows down (anchor on its empty top cell)
    kern = np.ones((k + 1, 1), np.uint8)
    kern[0] = 0
    below = cv2.dilate(surface.view(np.uint8) if surface.dtype == bool else
                       surface.astype(np.uint8), kern, anchor=(0, 0),
                       borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return mask & below.view(bool)


def obstacle_groups(candidate: np.ndarray, surface: np.ndarray, min_pixels: int = 30,
                    contact_px: int = 1, open_px: int = 0, bottom_rows: int = 0,
                    tall: np.ndarray | None = None,
                    bridge: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """(mask of the candidate pixels that belong to obstacle groups, number of groups).
    ``open_px`` > 1: a morphological opening by that square first (speckle is no group).
    ``bottom_rows`` > 0: a group reaching the last ``bottom_rows`` image rows stands on ground
    the camera cannot see. ``tall`` (bool map): a group needs at least TALL_MIN_PX of them.
    ``bridge`` (bool map): pixels that are not candidates themselves but through which a group
    may stand on the surface (the lower face of an obstacle of the ground's colour, which the
    rule calls traversable at ground height): groups are labelled on ``candidate | bridge``,
    their size and height counted on the candidate pixels only, and only candidate pixels are
    returned."""
    if not candidate.any():
        return np.zeros(candidate.shape, bool), 0
    cand8 = candidate.view(np.uint8) if candidate.dtype == bool else candidate.astype(np.uint8)
    if open_px > 1:
        cand8 = cv2.morphologyEx(cand8, cv2.MORPH_OPEN, np.ones((open_px, open_px), np.uint8))
        candidate = cand8 > 0
    ext = candidate
    if bridge is not None and bridge.any():
        ext = candidate | bridge
        cand8 = ext.view(np.uint8)
    # labels only (the statistics of connectedComponentsWithStats cost 10x the labelling);
    # the areas are one bincount
    n, labels = cv2.connectedComponents(cand8, connectivity=8, ltype=cv2.CV_32S)
    if n <= 1:
        return np.zeros(candidate.shape, bool), 0
    keep = np.bincount(labels[candidate], minlength=n) >= min_pixels   # areas
    keep[0] = False
    if not keep.any():
        return np.zeros(candidate.shape, bool), 0
    touch = touching_ground(ext, surface, contact_px)
    grounded = np.zeros(n, bool)
    grounded[labels[touch]] = True
    if bottom_rows > 0:
        grounded[labels[-bottom_rows:][ext[-bottom_rows:]]] = True
    keep &= grounded
    if tall is not None and keep.any():
        keep &= np.bincount(labels[tall & candidate], minlength=n)[:n] >= TALL_MIN_PX
    keep[0] = False
    ids = np.flatnonzero(keep)
    if len(ids) == 0:
        return np.zeros(candidate.shape, bool), 0
    if len(ids) <= 4:                  # a few groups: compares are cheaper than a gather
        out = labels == ids[0]
        for i in ids[1:]:
            out |= labels == i
    else:
        out = keep.view(np.uint8)[labels].view(bool)
    if ext is not candidate:
        out &= candidate
    return out, len(ids)


def class_lut(traversable_idx, n_classes: int) -> np.ndarray:
    """Lookup table over class map values (NOT_CLASSIFIED, UNDEFINED, 0..n-1, offset by 2):
    True where the class is NOT traversable."""
    lut = np.ones(n_classes + 2, bool)
    for i in traversable_idx:
        if 0 <= i < n_classes:
            lut[i + 2] = False
    return lut


def _apply(lut: np.ndarray, class_map: np.ndarray) -> np.ndarray:
    """lut[class_map + 2] as a bool map; OpenCV's 256-entry LUT when the classes fit a byte."""
    if lut.size <= 256:
        table = np.zeros(256, np.uint8)
        table[:lut.size] = lut
        idx = (class_map + np.int16(2)).astype(np.uint8)
        return cv2.LUT(idx, table).view(bool)
    return lut[class_map.astype(np.intp) + 2]


def not_traversable(class_map: np.ndarray, traversable_idx: list[int]) -> np.ndarray:
    """Pixels whose class is none of the traversable ones (UNDEFINED = -1 is not traversable)."""
    if not traversable_idx:
        return np.ones(class_map.shape, bool)
    n = int(max(max(traversable_idx), int(class_map.max()) if class_map.size else 0)) + 1
    return _apply(class_lut(traversable_idx, n), class_map)


@dataclass(frozen=True)
class Rule:
    """The decision's parameters; class indices are of the model's class list."""

    traversable: tuple[int, ...]
    n_classes: int
    ground_classes: tuple[int, ...] = ()
    ground_max_height_m: float = 0.0
    texture_role: str = "or"             # "or" (paper) | "traversable-colour"
    texture_undefined: bool = True        # an UNDEFINED texture window is obstacle evidence
    min_pixels: int = 30
    contact_px: int = 1
    open_px: int = 0                     # opening of the candidates before grouping (0: paper)
    bottom_rows: int = 0                 # a group in the last rows stands on the ground (0: no)
    texture_contact_px: int = 0          # contact_px of texture groups (0: contact_px)
    min_height_m: float = 0.0            # a group must rise this high above the ground (0: any)
    raised_bottom_only: bool = False     # raised level patches count only at the image bottom
    texture_min_pixels: int = 0          # smallest texture group (0: min_pixels)
    ground_class_contact: bool = False   # a colour group may stand on the ground through the
    #                                      steep ground-class pixels at ground height below it

    @classmethod
    def paper(cls, traversable, n_classes: int, min_pixels: int = 30, contact_px: int = 1):
        return cls(tuple(traversable), n_classes, min_pixels=min_pixels, contact_px=contact_px)


@dataclass
class Decision:
    colour: np.ndarray                   # bool: pixels of colour obstacle groups
    texture: np.ndarray | None           # bool: pixels of texture obstacle groups (None: no texture)
    n_colour: int
    n_texture: int
    raised: np.ndarray | None = None     # bool: raised level surfaces of no traversable colour
    n_raised: int = 0
    learned: np.ndarray | None = None    # bool: pixels of learned-cue obstacle groups
    n_learned: int = 0

    @property
    def obstacles(self) -> np.ndarray:
        out = self.colour | self.texture if self.texture is not None else self.colour.copy()
        if self.raised is not None:
            out |= self.raised
        if self.learned is not None:
            out |= self.learned
        return out


def _blocked(class_map: np.ndarray, rule: Rule, low: np.ndarray | None,
             undefined_blocks: bool = True) -> np.ndarray:
    """Pixels whose class says 'not traversable' under the rule (a ground class at ground
    height, ``low``, is traversable)."""
    lut = class_lut(rule.traversable, rule.n_classes)
    if not undefined_blocks:
        lut[UNDEFINED + 2] = False
    ground = low is not None and bool(rule.ground_classes)
    lut_low = lut.copy()
    if ground:
        lut_low[[g + 2 for g in rule.ground_classes]] = False
    if rule.n_classes + 2 <= 128:
        # one byte per pixel: class + 2 in the low 7 bits, 'at ground height' in the top bit,
        # and one OpenCV table lookup
        table = np.zeros(256, np.uint8)
        table[:lut.size] = lut
        table[128:128 + lut.size] = lut_low
        idx = (class_map + np.int16(2)).astype(np.uint8)
        if ground:
            idx |= low.view(np.uint8) << 7
        return cv2.LUT(idx, table).view(bool)
    out = lut[class_map.astype(np.intp) + 2]
    if ground:
        out &= ~low | lut_low[class_map.astype(np.intp) + 2]
    return out


def decide(suspected: np.ndarray, surface: np.ndarray, colour_class: np.ndarray,
           texture_class: np.ndarray | None, rule: Rule,
           height_m: np.ndarray | None = None, raised: np.ndarray | None = None,
           learned: np.ndarray | None = None) -> Decision:
    """The obstacle decision from the cues.

    ``suspected``/``surface``: bool maps from the slope step (``surface`` already limited to low
    ground when the rule asks for it); ``colour_class``/``texture_class``: int class maps
    (NOT_CLASSIFIED outside the suspected pixels, UNDEFINED where no class is near enough;
    ``texture_class`` None = texture did not run); ``height_m``: height above the ground plane
    (needed by ``ground_classes``); ``raised``: level pixels well above the ground (the top of a
    box too near for its face to be in view, a bush top) -- a group of them of no traversable
    colour (``colour_class`` must hold their classes too) is an obstacle. ``learned`` (bool
    map, beyond the paper, issue #8): pixels the learned cue calls obstacle-like; suspected ones
    among them form groups under the same rules as texture's (size, contact within
    ``texture_contact_px``, height), whatever their colour or texture class -- the cue is
    there for obstacles coloured and textured like a traversable class."""
    low = tall = None
    if rule.ground_classes and rule.ground_max_height_m > 0 and height_m is not None:
        low = height_m < np.float32(rule.ground_max_height_m)
    if rule.min_height_m > 0 and height_m is not None:
        tall = height_m >= np.float32(rule.min_height_m)
    grp = dict(min_pixels=rule.min_pixels, contact_px=rule.contact_px, open_px=rule.open_px,
               bottom_rows=rule.bottom_rows, tall=tall)
    colour_blocked = _blocked(colour_class, rule, low)
    bridge = None
    if rule.ground_class_contact and low is not None:
        # the lower face of an obstacle of the ground's colour is ground-class at ground height
        # (traversable); its upper part is not, and stands on the ground through that face
        gl = np.zeros(rule.n_classes + 2, bool)
        gl[[g + 2 for g in rule.ground_classes if 0 <= g < rule.n_classes]] = True
        bridge = suspected & low & _apply(gl, colour_class)
    col, n_col = obstacle_groups(suspected & colour_blocked, surface, bridge=bridge, **grp)
    ras, n_ras = None, 0
    if raised is not None:
        # a raised level patch stands on something by definition: no contact needed -- unless
        # the rule asks for patches cut off by the image bottom only (the top of a box too near
        # for its face and foot to be in view)
        if rule.raised_bottom_only and rule.bottom_rows > 0:
            ras, n_ras = obstacle_groups(raised & colour_blocked, np.zeros_like(raised),
                                         rule.min_pixels, 1, bottom_rows=rule.bottom_rows)
        else:
            ras, n_ras = obstacle_groups(raised & colour_blocked, np.ones_like(raised),
                                         rule.min_pixels, 1)
    grp["contact_px"] = rule.texture_contact_px or rule.contact_px
    lrn, n_lrn = None, 0
    if learned is not None:
        lrn, n_lrn = obstacle_groups(suspected & learned, surface, **grp)
    if texture_class is None:
        return Decision(col, None, n_col, 0, ras, n_ras, lrn, n_lrn)
    if rule.texture_role == "traversable-colour":
        cand = suspected & ~colour_blocked & _blocked(texture_class, rule, low,
                                                      rule.texture_undefined)
    else:
        cand = suspected & _blocked(texture_class, rule, low, rule.texture_undefined)
    if rule.texture_min_pixels:
        grp["min_pixels"] = max(rule.min_pixels, rule.texture_min_pixels)
    tex, n_tex = obstacle_groups(cand, surface, **grp)
    return Decision(col, tex, n_col, n_tex, ras, n_ras, lrn, n_lrn)
