"""Procedural furniture shapes (chairs, dining tables), user mesh loading and the canonical object frame.

Canonical object frame (shared by shape priors, the procedural library and object poses): z up (gravity),
the object's front faces +x (a chair: the direction a seated person looks, so the back is at -x; a table:
+x is the normal of a long side, the long side runs along y), origin at the centre of the axis-aligned
bounding box, units metres (the floor contact is at z = -height / 2). The normalised frame divides by
`scale = half_diagonal / CANONICAL_RADIUS`, so a normalised shape has bounding-box half-diagonal 0.9.

Public API: `generate`, `families`, `extra_families`, `eval_families`, `library`, `procedural_record`, `ShapeRecord`,
`load_user_meshes`, `normalise`, `denormalise`, `CANONICAL_RADIUS`; `gallery.save_gallery` draws a figure of the
families.
"""
from .canonical import CANONICAL_RADIUS, axes_to_canonical, centre_on_bbox, denormalise, normalisation_scale, normalise
from .library import (ShapeRecord, class_names, eval_families, extra_families, families, generate, library,
                      procedural_record)
from .user_meshes import load_user_meshes

__all__ = ['CANONICAL_RADIUS', 'ShapeRecord', 'axes_to_canonical', 'centre_on_bbox', 'class_names', 'denormalise',
           'eval_families', 'extra_families', 'families', 'generate', 'library', 'load_user_meshes',
           'normalisation_scale', 'normalise', 'procedural_record']
