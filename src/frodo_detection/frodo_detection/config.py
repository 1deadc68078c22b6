"""Detection parameters (paper Sec. 5.1) without ROS: the node's parameter specs and the filter / detector they
configure, shared by `detection_node` and the offline pipeline."""
from __future__ import annotations

from typing import Any

from frodo_common import topics
from frodo_common.categories import CATEGORIES, DEFAULT_CLASSES
from frodo_common.params import ParamSpec
from frodo_detection.core import FRAGMENT_POLICIES, FilterConfig, MaskRCNNDetector

BACKENDS = ('external', 'maskrcnn')
_DEFAULT_CLASS_IDS = [c.coco_id for c in CATEGORIES if c.name in DEFAULT_CLASSES]

PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec('backend', 'external', "Where masks come from: 'external' (/camera/instances) or 'maskrcnn' "
              '(torchvision Mask R-CNN on each image).'),
    ParamSpec('classes', _DEFAULT_CLASS_IDS, 'COCO category ids kept (62 chair, 63 couch, 65 bed, 67 dining table).'),
    ParamSpec('min_area', 400, 'Instances with fewer mask pixels are dropped (pixels at 640x480; scaled by '
              'W*H/(640*480) at other resolutions).'),
    ParamSpec('min_box_side', 16, 'Instances whose box is narrower or lower than this are dropped (pixels at '
              '640x480; scaled by sqrt(W*H/(640*480)) at other resolutions).'),
    ParamSpec('drop_truncated', False, 'Drop instances touching the image border (truncated objects).'),
    ParamSpec('border_margin', 2, 'Distance to the border (pixels) below which an instance counts as truncated.'),
    ParamSpec('min_fragment_fraction', 0.05, 'Mask components smaller than this fraction of the instance area '
              'are removed as specks (0 keeps all).'),
    ParamSpec('fragment_policy', 'keep', "Instances still in several pieces: 'keep', 'largest' (keep the largest "
              "piece) or 'drop'."),
    ParamSpec('weights_path', '', 'Mask R-CNN v2 COCO checkpoint (maskrcnn_resnet50_fpn_v2_coco-73cbd019.pth); '
              "'' = $TORCH_HOME/hub/checkpoints/."),
    ParamSpec('device', 'cpu', "Torch device for Mask R-CNN: 'cpu' or 'cuda'."),
    ParamSpec('score_threshold', 0.7, 'Mask R-CNN detections with a lower score are dropped.'),
    ParamSpec('mask_threshold', 0.5, 'Mask R-CNN soft-mask probability threshold.'),
    ParamSpec('input_min_size', 800, 'Mask R-CNN input resize (shorter side, pixels); smaller is faster.'),
    ParamSpec('match_window', 60, "Frames held while waiting for the image's instance image (backend 'external')."),
    ParamSpec('image_topic', topics.IMAGE, 'Colour image topic.'),
    ParamSpec('instances_topic', topics.INSTANCES, "Instance image topic (backend 'external')."),
)



def filter_config(values: dict[str, Any]) -> FilterConfig:
    """The instance filter of {parameter name: value} (defaults for names not given). Raises ValueError for an
    unknown backend or fragment policy."""
    p = {spec.name: spec.default for spec in PARAMS} | dict(values)
    if p['backend'] not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {p['backend']!r}")
    if p['fragment_policy'] not in FRAGMENT_POLICIES:
        raise ValueError(f"fragment_policy must be one of {FRAGMENT_POLICIES}, got {p['fragment_policy']!r}")
    return FilterConfig(classes=tuple(int(c) for c in p['classes']), min_area=int(p['min_area']),
                        min_box_side=int(p['min_box_side']), drop_truncated=bool(p['drop_truncated']),
                        border_margin=int(p['border_margin']), min_fragment_fraction=float(p['min_fragment_fraction']),
                        fragment_policy=p['fragment_policy'])


def make_detector(values: dict[str, Any]) -> MaskRCNNDetector | None:
    """The Mask R-CNN detector for backend 'maskrcnn' (raises WeightsNotFoundError without its checkpoint), None
    for 'external' (masks come with the data)."""
    p = {spec.name: spec.default for spec in PARAMS} | dict(values)
    if p['backend'] != 'maskrcnn':
        return None
    return MaskRCNNDetector(p['weights_path'] or None, p['device'], p['score_threshold'], p['mask_threshold'],
                            filter_config(p).classes, int(p['input_min_size']))
