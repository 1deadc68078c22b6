"""Registry of the procedural shape families: seeded generation and shape libraries.

`generate(class_name, seed, family)` is deterministic: the same arguments give identical vertices. Without
a family, seed `k` uses family `families(class_name)[k % len(families)]`, so `generate(c, k)` equals
`generate(c, k, families(c)[k % n])`. Held-out families (`eval_families`) and the extra training families of
the broader prior (`extra_families`) are built only when named.
Meshes come back in the canonical metric frame (see `canonical`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import trimesh

from . import chairs, extra_chairs, extra_tables, heldout, tables
from .canonical import centre_on_bbox

Generator = Callable[[np.random.Generator], trimesh.Trimesh]

FAMILIES: dict[str, dict[str, Generator]] = {
    'chair': {
        'four_leg': chairs.four_leg_chair,
        'office': chairs.office_chair,
        'stool': chairs.stool,
        'armchair': chairs.armchair,
    },
    'dining table': {
        'four_leg': tables.four_leg_table,
        'pedestal': tables.pedestal_table,
        'trestle': tables.trestle_table,
        'coffee': tables.coffee_table,
    },
}

# Extra training designs of the broader prior (issue 9 item 5): `library(..., extra=True)` adds them. They are
# kept out of FAMILIES so that `generate(c, k)` cycling, the synthetic scenes and every evaluation set built
# from them stay as they were.
EXTRA_FAMILIES: dict[str, dict[str, Generator]] = {
    'chair': {
        'shell': extra_chairs.shell_chair,
        'upholstered': extra_chairs.upholstered_chair,
        'spindle': extra_chairs.spindle_chair,
    },
    'dining table': {
        'panel_end': extra_tables.panel_end_table,
        'x_base': extra_tables.x_base_table,
        'side': extra_tables.side_table,
    },
}

# Held-out designs for evaluation only (`heldout`): never in `families()` / `library()`, so no prior is
# trained or tuned on them; `generate()` builds them by name.
EVAL_FAMILIES: dict[str, dict[str, Generator]] = {
    'chair': {
        'cantilever': heldout.cantilever_chair,
        'tub': heldout.tub_chair,
    },
    'dining table': {
        'desk': heldout.desk,
        'round_four_leg': heldout.round_four_leg_table,
    },
}


@dataclass
class ShapeRecord:
    """One shape of a library: a metric mesh in the canonical frame and where it came from.

    `family` is a procedural family name, or 'shapenet' / 'user' for loaded meshes; `seed` is the
    generator seed (-1 for loaded meshes); `watertight` is False for a loaded mesh that could not be
    repaired into a closed volume; `source` is the file it was loaded from (None when procedural).
    """
    name: str
    class_name: str
    family: str
    seed: int
    mesh: trimesh.Trimesh
    watertight: bool = True
    source: Path | None = None


def class_names() -> list[str]:
    """COCO class names with procedural families."""
    return list(FAMILIES)


def families(class_name: str) -> list[str]:
    """Procedural family names of a COCO class ('chair' or 'dining table'): the training families."""
    return list(_families_of(class_name))


def extra_families(class_name: str) -> list[str]:
    """Extra training family names of a COCO class (the broader prior's; never in scenes or `families`)."""
    _families_of(class_name)
    return list(EXTRA_FAMILIES.get(class_name, {}))


def eval_families(class_name: str) -> list[str]:
    """Held-out family names of a COCO class, for evaluation only (never in `families` / `library`)."""
    _families_of(class_name)
    return list(EVAL_FAMILIES.get(class_name, {}))


def _families_of(class_name: str) -> dict[str, Generator]:
    try:
        return FAMILIES[class_name]
    except KeyError as error:
        raise ValueError(f'no procedural shapes for class {class_name!r}; known classes: {class_names()}') from error


def generate(class_name: str, seed: int, family: str | None = None) -> trimesh.Trimesh:
    """Procedural watertight mesh of `class_name` in the canonical metric frame (z up, front +x, bbox
    centred at the origin), deterministic in (`class_name`, `seed`, `family`); `seed` >= 0."""
    generators = _families_of(class_name)
    names = list(generators)
    family = names[seed % len(names)] if family is None else family
    generators = {**generators, **EXTRA_FAMILIES.get(class_name, {}), **EVAL_FAMILIES.get(class_name, {})}
    if family not in generators:
        raise ValueError(f'unknown family {family!r} of class {class_name!r}; families: {list(generators)}')
    mesh = generators[family](np.random.default_rng(seed))
    return centre_on_bbox(mesh)


def library(class_name: str, count: int, seed: int = 0, extra: bool = False) -> list[ShapeRecord]:
    """`count` procedural shapes of `class_name`, families cycling evenly (record i has family i mod n) over
    `families(class_name)`, followed by `extra_families(class_name)` when `extra`.

    Shape seeds are distinct and drawn deterministically from `seed`; each record can be regenerated with
    `generate(record.class_name, record.seed, record.family)`.
    """
    names = families(class_name) + (extra_families(class_name) if extra else [])
    shape_seeds = np.random.default_rng(seed).choice(2**31, size=count, replace=False)
    return [procedural_record(class_name, int(s), names[index % len(names)]) for index, s in enumerate(shape_seeds)]


def procedural_record(class_name: str, seed: int, family: str) -> ShapeRecord:
    """The `ShapeRecord` of `generate(class_name, seed, family)`, named '<class>-<family>-<seed>'."""
    return ShapeRecord(name=f'{class_name.replace(" ", "_")}-{family}-{seed}', class_name=class_name, family=family,
                       seed=seed, mesh=generate(class_name, seed, family))
