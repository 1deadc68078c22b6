"""Shape node: encodes every kept, associated detection crop into a 64-D code and fuses the codes of
each object (paper Sec. 5.2: single-view shape code inference and multi-view code fusion).

In:  /camera/color/image_raw, /frodo/detections (16UC1), /frodo/associations (table).
Out: /frodo/codes (per-frame table: object_id, label, code[64]; the frame's stamp),
     /frodo/object_codes (latched table: object_id, category, num_views, code[64]; stamped with the newest
     frame stamp encoded so far: data time, never the node clock).
"""
from __future__ import annotations

from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.frame_cache import FrameCache
from frodo_common.node import FrodoNode, run_node
from frodo_common.torch_threads import call_in_passing_thread
from frodo_shape.encoding import PARAMS, CodeEncoder
from frodo_shape.prior import ShapePrior
from sensor_msgs.msg import Image, PointCloud2


class ShapeNode(FrodoNode):
    """Encodes detections as they are associated and republishes the fused code of every object."""

    def __init__(self, **kwargs):
        super().__init__('shape_node', PARAMS, **kwargs)
        prior = call_in_passing_thread(lambda: ShapePrior.load(self.params['prior'], device=self.params['device']))
        self.encoder = CodeEncoder(prior, self.params)
        self.store = self.encoder.store   # codes and their objects, bounded
        self.cache = FrameCache(['image', 'detections', 'associations'], self.params['frame_cache_size'])
        self.newest_stamp = 0   # newest frame stamp encoded (a re-send of an older frame does not move it back)
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
        rows = conv.cloud_to_table(frame.parts['associations'])
        stamp = frame.stamp_ns
        rgb = labels = None
        if not self.encoder.known(stamp, rows):
            rgb = conv.image_to_rgb(frame.parts['image'])
            labels = conv.image_to_numpy(frame.parts['detections'])
        try:
            codes, encoded = self.encoder.encode_frame(stamp, rgb, labels, rows)
        except ValueError as err:
            raise conv.ConversionError(str(err)) from err
        self.count('crops_encoded', encoded)
        if len(self.store) - len(self.store.assignment) > self.cache.capacity:   # amortised: unassigned codes
            self.store.forget_unassigned(lambda s: s in self.cache.frames)      # of frames no re-send can reach
        frame_id = frame.parts['associations'].header.frame_id
        if len(codes):
            self.codes_pub.publish(conv.table_to_cloud(codes, stamp, frame_id))
        self.newest_stamp = max(self.newest_stamp, stamp)
        self._publish_objects(frame_id)

    def _publish_objects(self, frame_id: str) -> None:
        fused = self.encoder.fused_codes()
        self.objects_pub.publish(conv.table_to_cloud(fused, self.newest_stamp, frame_id))
        self.count('object_codes_published')

    def diagnostic_values(self) -> dict:
        return {'objects': len(set(self.store.assignment.values())), 'codes': len(self.store),
                'prior': self.params['prior'], 'frames_cached': len(self.cache)}


def main(args=None) -> int:
    """Entry point of `shape_node`."""
    return run_node(ShapeNode, args)


if __name__ == '__main__':
    main()
