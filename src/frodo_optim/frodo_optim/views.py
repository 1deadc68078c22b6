"""The optimiser's per-object view memory: one frame-to-view extraction for the node and the offline pipeline.

Every associated detection of a frame becomes a compact sparse-stage `View` (mask samples + distance transform,
`sparse.view_from_mask`) and, with the dense stage on, a `DenseView` (label/colour crop + masked depth,
`photometric.dense_view_from_frame`); the full-resolution images are not kept. Views are stored under
(stamp, label) with their object id and kept flag, which later association re-sends can change (`assign`).
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from frodo_optim.config import OptimConfig
from frodo_optim.photometric import DenseView, dense_view_from_frame
from frodo_optim.sparse import View, ViewStore, view_from_mask


class ViewMemory:
    """Bounded sparse and dense views of every detection, by object (`ViewStore` thinning)."""

    def __init__(self, config: OptimConfig, seed: int = 0):
        self.config = config
        self.sparse = ViewStore(config.views_stored)
        self.dense = ViewStore(config.views_stored, capacity=1000)   # same keys
        self.rng = np.random.default_rng(seed)

    def add_frame(self, stamp: int, K: np.ndarray, T_world_camera: np.ndarray, labels: np.ndarray, rows: np.ndarray,
                  rgb: np.ndarray | None = None, depth_m: np.ndarray | None = None,
                  owns: Callable[[int], bool] = lambda oid: True) -> tuple[int, int]:
        """Views of one frame's detections. labels (H, W) uint16 instance image; rows: its association table
        (ASSOCIATION_DTYPE: label, object_id, kept); rgb (H, W, 3) uint8 and depth_m (H, W) metres (NaN or 0 =
        none) for the dense views. Rows of objects `owns` rejects are skipped (another optimiser worker's).
        Returns (views stored, detections whose mask or camera was unusable)."""
        detected = labels > 0
        stored = rejected = 0
        for r in rows:   # all rows: ids of past frames are assigned or changed later by re-sends
            oid = int(r['object_id'])
            if oid >= 0 and not owns(oid):
                continue
            mask = labels == r['label']
            view = view_from_mask(K, T_world_camera, mask, self.config.sparse.mask_samples, detected & ~mask, self.rng,
                                  depth_m)
            if view is None:
                rejected += 1
                continue
            key = (int(stamp), int(r['label']), oid, bool(r['kept']))
            self.sparse.add(*key, view)
            if self.config.dense_on:
                dense_view = dense_view_from_frame(K, T_world_camera, mask, detected & ~mask, rgb, depth_m,
                                                   size=self.config.crop_size, rng=self.rng)
                if dense_view is not None:
                    self.dense.add(*key, dense_view)
            stored += 1
        return stored, rejected

    def assign(self, stamp: int, rows: np.ndarray) -> None:
        """A re-sent association table of a past frame: its views move to their new objects."""
        owners = {int(r['label']): (int(r['object_id']), bool(r['kept'])) for r in rows}
        self.sparse.assign(stamp, owners)
        self.dense.assign(stamp, owners)

    def sparse_views(self, object_id: int) -> list[View]:
        """The object's sparse-stage views (kept ones, filled with pruned ones up to `fill_views`)."""
        return self.sparse.views_of(object_id, self.config.fill_views)

    def dense_views(self, object_id: int) -> list[DenseView]:
        """The object's dense-stage views, chosen like `sparse_views`."""
        return self.dense.views_of(object_id, self.config.fill_views)

    def newest_stamp(self, object_id: int) -> int:
        """Stamp (ns) of the newest frame among the object's views that `sparse_views` and `dense_views` return;
        0 when it has none. The data time of an estimate made from them."""
        keys = (self.sparse.keys_of(object_id, self.config.fill_views)
                + self.dense.keys_of(object_id, self.config.fill_views))
        return max((k[0] for k in keys), default=0)

    def of_object(self, object_id: int) -> 'ViewMemory':
        """A copy holding only the object's stored views (all its stages read), to send to another process."""
        out = ViewMemory(self.config)
        for mine, theirs in ((out.sparse, self.sparse), (out.dense, self.dense)):
            mine.per_object, mine.capacity = theirs.per_object, theirs.capacity
            for key, (oid, kept) in theirs.owner.items():
                if oid == object_id:
                    mine.views[key], mine.owner[key] = theirs.views[key], (oid, kept)
        return out

    def count(self, object_id: int) -> int:
        """Sparse views stored for the object (kept ones only)."""
        return len(self.sparse.views_of(object_id))

    def __len__(self) -> int:
        return len(self.sparse)
