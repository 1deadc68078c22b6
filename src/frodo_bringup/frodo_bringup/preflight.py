"""Checks of a bag before any work: does it have what the graph needs to find objects? Used by `frodo run`
(before any node starts) and `frodo reconstruct`, so both refuse the same bags with the same words."""
from __future__ import annotations

from frodo_common import topics
from frodo_common.bag import BagReader


class BagRefused(RuntimeError):
    """The bag cannot give objects; the message says why and what to do."""


def check_bag(reader: BagReader, backend: str) -> None:
    """Raise BagRefused, with the cause and the fix, when the bag cannot give objects (`backend`: the detection
    backend, `external` or `maskrcnn`)."""
    available = reader.topics()
    missing = [t for t in (topics.IMAGE, topics.CAMERA_INFO, topics.POSE) if t not in available]
    if missing:
        raise BagRefused(f'{reader.path} has no message on the required input(s) {", ".join(missing)} '
                         f'(CONTRACT.md); it has {", ".join(sorted(available)) or "nothing readable"}')
    if backend == 'external' and topics.INSTANCES not in available:
        raise BagRefused(
            f'{reader.path} has no instance masks ({topics.INSTANCES}) and the detection backend is "external", '
            'which only filters masks that come with the data: no object can be found. Either add masks (for '
            '`frodo convert folder`, 16-bit PNGs in the folder\'s instances/; see `frodo convert --help`) or run '
            'Mask R-CNN on the images: a params file with `detection_node: {ros__parameters: {backend: maskrcnn}}` '
            '(its COCO checkpoint maskrcnn_resnet50_fpn_v2_coco-73cbd019.pth in $TORCH_HOME/hub/checkpoints/ or '
            'weights_path).')
