"""Detection node (paper Sec. 5.1): per-frame instance masks for the association stage.

In:  /camera/color/image_raw (rgb8/bgr8), /camera/instances (16UC1, backend 'external' only).
Out: /frodo/detections (16UC1, the image's stamp and frame id; all zero when nothing was detected).

Backend 'external' matches each image with the instance image of the same stamp (bounded cache) and
filters it; backend 'maskrcnn' runs torchvision Mask R-CNN on each image and filters its output.
Frames with invalid data are counted, reported on /diagnostics and skipped.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from sensor_msgs.msg import Image

from frodo_common import conversions as conv
from frodo_common import topics
from frodo_common.categories import category_by_id
from frodo_common.frame_cache import FrameCache
from frodo_common.node import FrodoNode, run_node
from frodo_common.torch_threads import call_in_passing_thread
from frodo_detection.config import PARAMS, filter_config, make_detector
from frodo_detection.core import MaskRCNNDetector, filter_instances

class DetectionNode(FrodoNode):
    """Publishes the filtered instance image of every image frame on /frodo/detections."""

    def __init__(self, detector: MaskRCNNDetector | None = None, **kwargs):
        super().__init__('detection_node', PARAMS, **kwargs)
        p = self.params
        self.filter_cfg = filter_config(p)
        self.detector = detector if detector is not None else call_in_passing_thread(lambda: make_detector(p))
        self.cache = FrameCache(('image', 'instances'), int(p['match_window']))
        self._warned_encodings: set[str] = set()
        self._warned_categories: set[int] = set()
        self.pub = self.create_publisher(Image, topics.DETECTIONS, topics.FRAME_QOS)
        self.create_subscription(Image, p['image_topic'], self.guarded(self._on_image, 'image'), topics.FRAME_QOS)
        if p['backend'] == 'external':
            self.create_subscription(Image, p['instances_topic'], self.guarded(self._on_instances, 'instances'),
                                     topics.FRAME_QOS)

    # ------------------------------------------------------------ callbacks
    def _on_image(self, msg: Image) -> None:
        self.count('frames_received')
        if self.detector is not None:
            self._process(msg, None)
            return
        frame = self.cache.add(conv.stamp_to_ns(msg.header.stamp), 'image', msg)
        if frame is not None:
            self._process(frame.parts['image'], frame.parts['instances'])

    def _on_instances(self, msg: Image) -> None:
        self.count('instances_received')
        frame = self.cache.add(conv.stamp_to_ns(msg.header.stamp), 'instances', msg)
        if frame is not None:
            self._process(frame.parts['image'], frame.parts['instances'])

    def _process(self, image: Image, instances: Image | None) -> None:
        """Filter (or detect and filter) one frame and publish it; invalid frames are dropped and reported.

        Checked here, at the graph's entrance, so that later nodes see only valid frames: the colour image
        decodes (rgba8/bgra8/mono8 are accepted and counted as converted), the instance image is 16UC1 of
        the image's size; instances of category ids the graph does not know are counted and ignored.
        """
        stamp = conv.stamp_to_ns(image.header.stamp)
        try:
            rgb = conv.image_to_rgb(image)
            if instances is None:
                raw = self.detector.detect(rgb)
            else:
                if instances.encoding != '16UC1':
                    raise conv.ConversionError(f'instances encoding must be 16UC1, got {instances.encoding!r}')
                raw = conv.image_to_numpy(instances)
                conv.check_same_size((raw.shape[1], raw.shape[0]), conv.image_size(image), 'instance image',
                                     'colour image')
        except conv.ConversionError as err:
            self.count('frames_dropped')
            self.report_error(f'frame {stamp}', err)
            return
        self._note_conversion(image.encoding)
        self._note_unknown_categories(raw)
        filtered, detections = filter_instances(raw, self.filter_cfg)
        # counted before publishing: a listener that has the frame finds it counted on /diagnostics
        self.count('frames_published')
        self.count('detections_published', len(detections))
        self.pub.publish(conv.numpy_to_image(filtered, '16UC1', stamp, image.header.frame_id))
        if not detections:
            self.count('frames_without_detections')
        self.cache.frames.pop(stamp, None)  # processed: free the images (the stamp stays marked complete)

    def _note_conversion(self, encoding: str) -> None:
        """Count an accepted non-contract colour encoding; warn once per encoding."""
        if encoding in conv.COLOUR_ENCODINGS:
            return
        self.count('images_converted')
        if encoding not in self._warned_encodings:
            self._warned_encodings.add(encoding)
            self.report_error('image', f'encoding {encoding} converted to RGB (the contract asks for rgb8 or bgr8)',
                              counter='warnings')

    def _note_unknown_categories(self, instances: np.ndarray) -> None:
        """Count instances whose category id (high byte) is no class the graph knows; warn once per id."""
        labels = np.unique(instances)
        unknown = [int(v) for v in labels if v and category_by_id(int(v) >> 8) is None]
        if not unknown:
            return
        self.count('instances_unknown_category', len(unknown))
        new = sorted({v >> 8 for v in unknown} - self._warned_categories)
        if new:
            self._warned_categories.update(new)
            self.report_error('instances', f'unknown category id(s) {new} (label = category * 256 + k, COCO ids); '
                              'those instances are ignored', counter='warnings')

    def diagnostic_values(self) -> dict[str, Any]:
        return {'backend': self.params['backend'], 'frames_cached': len(self.cache),
                'frames_unmatched': self.cache.evicted_incomplete}


def main(args=None) -> int:
    """Entry point of `detection_node`."""
    return run_node(DetectionNode, args)


if __name__ == '__main__':
    main()
