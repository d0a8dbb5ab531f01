"""Step 4 of the greenhouse paper (section 3.5): the obstacle decision.

A connected group (8-connected) of at least ``min_pixels`` (30) suspected pixels that are
(i) above and adjacent to surface pixels and (ii) classified as none of the traversable classes
(bush, pepper; an UNDEFINED pixel is not traversable) is an obstacle. Colour and texture are
judged separately and an obstacle from either counts (colour OR texture: the paper's safe side).

"Above and adjacent": at least one pixel of the group has a surface pixel within ``contact_px``
rows straight below it in the image (1 = the next row, the paper's adjacency).
"""
from __future__ import annotations

import cv2
import numpy as np


def touching_ground(mask: np.ndarray, surface: np.ndarray, contact_px: int = 1) -> np.ndarray:
    """Pixels of ``mask`` with a ``surface`` pixel 1..contact_px rows below them."""
    touch = np.zeros(mask.shape, bool)
    h = mask.shape[0]
    for k in range(1, max(1, contact_px) + 1):
        if k >= h:
            break
        touch[:-k] |= mask[:-k] & surface[k:]
    return touch


def obstacle_groups(candidate: np.ndarray, surface: np.ndarray, min_pixels: int = 30,
                    contact_px: int = 1) -> tuple[np.ndarray, int]:
    """(mask of the candidate pixels that belong to obstacle groups, number of groups)."""
    if not candidate.any():
        return np.zeros(candidate.shape, bool), 0
    n, labels, stats, _ = cv2.connectedComponentsWithStats(candidate.view(np.uint8)
                                                           if candidate.dtype == bool else
                                                           candidate.astype(np.uint8),
                                                           connectivity=8)
    big = stats[:, cv2.CC_STAT_AREA] >= min_pixels
    big[0] = False
    touch = touching_ground(candidate, surface, contact_px)
    grounded = np.zeros(n, bool)
    grounded[np.unique(labels[touch])] = True
    keep = big & grounded
    keep[0] = False
    return keep[labels], int(keep.sum())


def not_traversable(class_map: np.ndarray, traversable_idx: list[int]) -> np.ndarray:
    """Pixels whose class is none of the traversable ones (UNDEFINED = -1 is not traversable)."""
    if not traversable_idx:
        return np.ones(class_map.shape, bool)
    return ~np.isin(class_map, np.asarray(traversable_idx, class_map.dtype))
