"""Single-view code inference and multi-view code fusion (paper Sec. 5.2) without ROS: every kept, associated
detection crop is encoded once into a 64-D code; an object's code is the fusion of its detections' codes.
`shape_node` and the offline pipeline both use `CodeEncoder`; `PARAMS` are the node's parameters."""
from __future__ import annotations

from typing import Any

import numpy as np

from frodo_common import topics
from frodo_common.categories import split_instance_label
from frodo_common.params import ParamSpec
from frodo_common.schemas import CODES_DTYPE, OBJECT_CODES_DTYPE
from frodo_shape.code_store import CodeStore
from frodo_shape.crops import square_crop
from frodo_shape.fusion import fuse_mean, fuse_vote
from frodo_shape.prior import DEFAULT_PRIOR

FUSIONS = ('mean', 'vote')
PARAMS = (
    ParamSpec('prior', DEFAULT_PRIOR, 'Shipped prior name (frodo_shape/priors/<name>) or path to a prior folder.'),
    ParamSpec('device', 'auto', "Torch device for the encoder: 'auto' (cuda if available), 'cpu' or 'cuda'."),
    ParamSpec('fusion', 'mean', "Code fusion (Sec. 5.2): 'mean' or 'vote' (majority of 4 nearest training codes)."),
    ParamSpec('crop_size', 128, 'Side of the square encoder input crop in pixels.'),
    ParamSpec('crop_margin', 0.1, 'Context margin around the detection box, as a fraction of its longer side.'),
    ParamSpec('image_topic', topics.IMAGE, 'Colour image topic.'),
    ParamSpec('max_codes_per_object', 256, 'Codes kept per object for fusion (bounded memory and per-frame cost on '
              'long runs): past this, every second one in stamp order is dropped (code_store.CodeStore).'),
)


class CodeEncoder:
    """Codes of associated detections (bounded `CodeStore`) and the fused code of every object."""

    def __init__(self, prior, values: dict[str, Any] | None = None):
        p = {spec.name: spec.default for spec in PARAMS} | dict(values or {})
        if p['fusion'] not in FUSIONS:
            raise ValueError(f"fusion must be 'mean' or 'vote', got {p['fusion']!r}")
        self.prior = prior
        self.fusion, self.crop_size, self.crop_margin = p['fusion'], int(p['crop_size']), float(p['crop_margin'])
        self.store = CodeStore(int(p['max_codes_per_object']))

    def encode_frame(self, stamp: int, rgb: np.ndarray | None, labels: np.ndarray | None,
                     rows: np.ndarray) -> tuple[np.ndarray, int]:
        """Assign a frame's kept, associated detections (association rows, ASSOCIATION_DTYPE) to their objects,
        encoding the crops not encoded before. rgb (H, W, 3) uint8 and labels (H, W) uint16 are needed only when
        there is something new to encode (a re-send of known detections passes None). Returns (the frame's
        codes table, CODES_DTYPE; number of crops encoded). Raises ValueError when the images' sizes differ."""
        rows = rows[(rows['kept'] == 1) & (rows['object_id'] >= 0)]
        todo = [r for r in rows if (stamp, int(r['label'])) not in self.store]
        if todo:
            if rgb is None or labels is None:
                raise ValueError(f'frame {stamp}: new detections to encode but no image')
            if labels.shape != rgb.shape[:2]:
                raise ValueError(f'detections {labels.shape} and image {rgb.shape[:2]} sizes differ')
            crops, masks = zip(*(square_crop(rgb, labels == r['label'], r['bbox'], self.crop_size, self.crop_margin)
                                 for r in todo))
            for r, code in zip(todo, self.prior.encode(np.stack(crops), np.stack(masks))):
                self.store.add((stamp, int(r['label'])), code)
        out = np.zeros(len(rows), dtype=CODES_DTYPE)
        for i, r in enumerate(rows):
            out[i] = (r['object_id'], r['label'], self.store.codes[(stamp, int(r['label']))])
        self.store.assign_frame(stamp, {int(r['label']): int(r['object_id']) for r in rows})
        return out, len(todo)

    def known(self, stamp: int, rows: np.ndarray) -> bool:
        """True when every kept, associated detection of the rows already has a code (no image needed)."""
        rows = rows[(rows['kept'] == 1) & (rows['object_id'] >= 0)]
        return all((stamp, int(r['label'])) in self.store for r in rows)

    def fused_codes(self) -> np.ndarray:
        """Fused code per object (table of OBJECT_CODES_DTYPE, by id) from the current assignment."""
        members = self.store.members()
        out = np.zeros(len(members), dtype=OBJECT_CODES_DTYPE)
        for i, (oid, keys) in enumerate(sorted(members.items())):
            codes = np.stack([self.store.codes[k] for k in keys])
            cats = [split_instance_label(label)[0] for _, label in keys]
            fused = fuse_mean(codes) if self.fusion == 'mean' else fuse_vote(codes, self.prior.training_codes, k=4)
            out[i] = (oid, max(set(cats), key=cats.count), self.store.num_views(oid, len(keys)),
                      np.asarray(fused, dtype=np.float32))
        return out
