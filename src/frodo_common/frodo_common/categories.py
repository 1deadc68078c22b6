"""Object categories: COCO ids (CONTRACT.md), names, and metric size priors used to cut box rays to segments."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Category:
    """One object class the graph reconstructs.

    coco_id: high byte of the contract's instance label (`category_id * 256 + k`).
    name: the marker namespace used on `/frodo/objects` and `/frodo/boxes`.
    size_range: (min, max) plausible largest metric extent of an object of this class in metres.
        The association stage uses it to cut the ray through a box centre to a 3D segment
        (paper Sec. 5.1: "knowledge of the object class sets reasonable bounds on the object scale").
    height_range: (min, max) plausible metric height in metres (floor to top). The optimiser's class
        height prior (frodo_optim.support, beyond the paper) keeps reconstructions inside it.
    colour: (r, g, b) in [0, 1], the class's colour wherever objects are drawn by class (the optimiser's
        markers, the Rerun recording's detections and tracks).
    """

    coco_id: int
    name: str
    size_range: tuple[float, float]
    height_range: tuple[float, float] = (0.0, float('inf'))
    colour: tuple[float, float, float] = (0.7, 0.7, 0.7)


# Size ranges cover the procedural library and common real furniture (ScanNet/Redwood chairs
# are 0.4-1.2 m tall; dining tables 0.6-2.4 m long). Heights: chairs from low stools to office chairs
# with head rests (procedural library up to 1.28 m), tables from coffee tables to standing desks.
CATEGORIES: tuple[Category, ...] = (
    Category(62, 'chair', (0.35, 1.3), (0.4, 1.35), (0.95, 0.55, 0.15)),
    Category(63, 'couch', (0.8, 2.6), (0.5, 1.2), (0.6, 0.35, 0.8)),
    Category(65, 'bed', (1.2, 2.4), (0.25, 1.5), (0.85, 0.3, 0.45)),
    Category(67, 'dining table', (0.5, 2.6), (0.3, 1.15), (0.2, 0.6, 0.95)),
)

BY_COCO_ID: dict[int, Category] = {c.coco_id: c for c in CATEGORIES}
BY_NAME: dict[str, Category] = {c.name: c for c in CATEGORIES}

# Classes that have a shipped shape prior and are reconstructed by default.
DEFAULT_CLASSES: tuple[str, ...] = ('chair', 'dining table')


def category_by_id(coco_id: int) -> Category | None:
    """Category for a COCO id, or None when the graph does not know the class."""
    return BY_COCO_ID.get(int(coco_id))


def category_by_name(name: str) -> Category:
    """Category for a class name; raises KeyError naming the known classes."""
    try:
        return BY_NAME[name]
    except KeyError:
        raise KeyError(f'unknown class {name!r}; known: {sorted(BY_NAME)}') from None


def split_instance_label(label: int) -> tuple[int, int]:
    """Split a contract instance pixel value into (coco category id, per-frame instance k)."""
    return int(label) >> 8, int(label) & 0xFF


def make_instance_label(coco_id: int, k: int) -> int:
    """Contract instance pixel value for category `coco_id` and per-frame instance `k` (1..255)."""
    if not 1 <= k <= 255:
        raise ValueError(f'instance index k must be in 1..255, got {k}')
    return (int(coco_id) << 8) | int(k)
