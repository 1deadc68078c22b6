"""Shape node: encodes every kept, associated detection crop into a 64-D code and fuses the codes of
each object (paper Sec. 4.2: single-view shape code inference and multi-view code fusion).

In:  /camera/color/image_raw, /frodo/detections (16UC1), /frodo/associations (table).
Out: /frodo/codes (per-frame table: object_id, label, code[64]),
     /frodo/object_codes (latched table: object_id, category, num_views, code[64]).
"""
from __future__ import annotations

import numpy as np

from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.categories import split_instance_label
from frodo_common.frame_cache import FrameCache
from frodo_common.node import FrodoNode, run_node
from frodo_common.params import ParamSpec
from frodo_shape.code_store import CodeStore
from frodo_shape.crops import square_crop
from frodo_shape.fusion import fuse_mean, fuse_vote
from frodo_shape.prior import DEFAULT_PRIOR, ShapePrior
from sensor_msgs.msg import Image, PointCloud2

PARAMS = (
    ParamSpec('prior', DEFAULT_PRIOR, 'Shipped prior name (frodo_shape/priors/<name>) or path to a prior folder.'),
    ParamSpec('device', 'auto', "Torch device for the encoder: 'auto' (cuda if available), 'cpu' or 'cuda'."),
    ParamSpec('fusion', 'mean', "Code fusion (Sec. 4.2): 'mean' or 'vote' (majority of 4 nearest training codes)."),
    ParamSpec('crop_size', 128, 'Side of the square encoder input crop in pixels.'),
    ParamSpec('crop_margin', 0.1, 'Context margin around the detection box, as a fraction of its longer side.'),
    ParamSpec('image_topic', topics.IMAGE, 'Colour image topic.'),
    ParamSpec('max_codes_per_object', 256, 'Codes kept per object for fusion (bounded memory and per-frame cost on '
              'long runs): past this, every second one in stamp order is dropped (code_store.CodeStore).'),
)

CODE_DIM = 64
CODES_DTYPE = np.dtype([('object_id', '<i4'), ('label', '<u2'), ('code', '<f4', (CODE_DIM,))])
OBJECT_CODES_DTYPE = np.dtype([('object_id', '<i4'), ('category', '<u2'), ('num_views', '<u4'),
                               ('code', '<f4', (CODE_DIM,))])


class ShapeNode(FrodoNode):
    """Encodes detections as they are associated and republishes the fused code of every object."""

    def __init__(self, **kwargs):
        super().__init__('shape_node', PARAMS, **kwargs)
        self.prior = ShapePrior.load(self.params['prior'], device=self.params['device'])
        if self.params['fusion'] not in ('mean', 'vote'):
            raise ValueError(f"fusion must be 'mean' or 'vote', got {self.params['fusion']!r}")
        self.cache = FrameCache(['image', 'detections', 'associations'], self.params['frame_cache_size'])
        self.store = CodeStore(int(self.params['max_codes_per_object']))   # codes and their objects, bounded
        self.codes_pub = self.create_publisher(PointCloud2, topics.CODES, topics.FRAME_QOS)
        self.objects_pub = self.create_publisher(PointCloud2, topics.OBJECT_CODES, topics.LATCHED_QOS)
        self.create_subscription(Image, self.params['image_topic'],
                                 self.guarded(lambda m: self._add(m, 'image'), 'image'), topics.FRAME_QOS)
        self.create_subscription(Image, topics.DETECTIONS,
                                 self.guarded(lambda m: self._add(m, 'detections'), 'detections'), topics.FRAME_QOS)
        self.create_subscription(PointCloud2, topics.ASSOCIATIONS, self.guarded(self._on_associations, 'associations'),
                                 topics.FRAME_QOS)

    def _add(self, msg, part: str) -> None:
        self.count(f'{part}_received')
        frame = self.cache.add(conv.stamp_to_ns(msg.header.stamp), part, msg)
        if frame is not None:
            self._encode_frame(frame)

    def _on_associations(self, msg: PointCloud2) -> None:
        self.count('associations_received')
        stamp = conv.stamp_to_ns(msg.header.stamp)
        known = self.cache.get(stamp)
        if known is not None and known.has(self.cache.required):
            known.parts['associations'] = msg  # a re-send after merges: re-key and encode what is new
            self._encode_frame(known)
        else:
            self._add(msg, 'associations')

    def _encode_frame(self, frame) -> None:
        table = conv.cloud_to_table(frame.parts['associations'])
        rows = table[(table['kept'] == 1) & (table['object_id'] >= 0)]
        stamp = frame.stamp_ns
        if len(rows) == 0:
            self.store.assign_frame(stamp, {})
            self._publish_objects(frame.parts['associations'].header.frame_id)
            return
        todo = [r for r in rows if (stamp, int(r['label'])) not in self.store]
        if todo:
            rgb = conv.image_to_rgb(frame.parts['image'])
            labels = conv.image_to_numpy(frame.parts['detections'])
            if labels.shape != rgb.shape[:2]:
                raise conv.ConversionError(f'detections {labels.shape} and image {rgb.shape[:2]} sizes differ')
            crops, masks = zip(*(square_crop(rgb, labels == r['label'], r['bbox'], self.params['crop_size'],
                                             self.params['crop_margin']) for r in todo))
            codes = self.prior.encode(np.stack(crops), np.stack(masks))
            for r, code in zip(todo, codes):
                self.store.add((stamp, int(r['label'])), code)
            self.count('crops_encoded', len(todo))
        out = np.zeros(len(rows), dtype=CODES_DTYPE)
        for i, r in enumerate(rows):
            out[i] = (r['object_id'], r['label'], self.store.codes[(stamp, int(r['label']))])
        self.store.assign_frame(stamp, {int(r['label']): int(r['object_id']) for r in rows})
        if len(self.store) - len(self.store.assignment) > self.cache.capacity:   # amortised: unassigned codes
            self.store.forget_unassigned(lambda s: s in self.cache.frames)      # of frames no re-send can reach
        frame_id = frame.parts['associations'].header.frame_id
        self.codes_pub.publish(conv.table_to_cloud(out, stamp, frame_id))
        self._publish_objects(frame_id)

    def fused_codes(self) -> np.ndarray:
        """Fused code per object (table of OBJECT_CODES_DTYPE) from the current assignment."""
        members = self.store.members()
        out = np.zeros(len(members), dtype=OBJECT_CODES_DTYPE)
        for i, (oid, keys) in enumerate(sorted(members.items())):
            codes = np.stack([self.store.codes[k] for k in keys])
            cats = [split_instance_label(label)[0] for _, label in keys]
            fused = fuse_mean(codes) if self.params['fusion'] == 'mean' else \
                fuse_vote(codes, self.prior.training_codes, k=4)
            out[i] = (oid, max(set(cats), key=cats.count), self.store.num_views(oid, len(keys)),
                      np.asarray(fused, dtype=np.float32))
        return out

    def _publish_objects(self, frame_id: str) -> None:
        fused = self.fused_codes()
        now = self.get_clock().now().nanoseconds
        self.objects_pub.publish(conv.table_to_cloud(fused, now, frame_id))
        self.count('object_codes_published')

    def diagnostic_values(self) -> dict:
        return {'objects': len(set(self.store.assignment.values())), 'codes': len(self.store),
                'prior': self.params['prior'], 'frames_cached': len(self.cache)}


def main(args=None) -> int:
    """Entry point of `shape_node`."""
    return run_node(ShapeNode, args)


if __name__ == '__main__':
    main()
