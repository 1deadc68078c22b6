"""A contract bag at another image size: the same frames, masks and poses on fewer (or more) pixels.

    python -m frodo_datasets.rescale IN.mcap OUT.mcap --scale 0.5

Colour images are resampled by area (down) or linearly (up); instance and depth images take the nearest
pixel (labels and depths are never blended); camera_info's intrinsics follow the pixel grid (fx, fy times the
scale; the principal point in pixel-edge coordinates times the scale); every other topic is copied byte for
byte. A `<stem>.gt.json` sidecar next to IN is copied next to OUT with its intrinsics and image size scaled.

For: running a 640x480 capture at 320x240 (four times fewer pixels for the mask work), and comparing the
method at two image sizes on one draw of a synthetic bag's detector noise (`eval_sets` variant `full640`
halved against itself: `src/frodo_datasets/README.md`). Not for: anything that needs the detector to see the
new image (the masks are resampled, not re-detected).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from frodo_common.bag import BagError, BagReader, BagWriter
from frodo_common.conversions import (ConversionError, camera_info_to_K, image_to_numpy, make_camera_info,
                                      numpy_to_image, stamp_to_ns)
from frodo_common.topics import CAMERA_INFO, DEPTH, IMAGE, INSTANCES
from frodo_datasets.convert.common import resize_color, resize_nearest, scale_intrinsics


def scaled_size(width: int, height: int, scale: float) -> tuple[int, int]:
    return max(1, int(round(width * scale))), max(1, int(round(height * scale)))


def rescale_bag(src: str | Path, dst: str | Path, scale: float) -> dict[str, int]:
    """Write `dst`: the bag `src` with its images at `scale` times the size. Returns messages per topic written."""
    if not scale > 0:
        raise ValueError(f'scale must be > 0, got {scale}')
    src, dst = Path(src), Path(dst)
    reader = BagReader(src)
    written: dict[str, int] = {}
    with BagWriter(dst) as writer:
        for topic, (msgtype, _) in reader.topics().items():
            writer.add_topic(topic, msgtype)
        for m in reader.messages():
            if m.topic in (IMAGE, INSTANCES, DEPTH):
                msg = m.decode()
                image = image_to_numpy(msg)
                size = scaled_size(image.shape[1], image.shape[0], scale)
                resized = resize_color(image, size) if m.topic == IMAGE else resize_nearest(image, size)
                out = numpy_to_image(resized, msg.encoding,
                                     stamp_to_ns(msg.header.stamp), msg.header.frame_id)
                writer.write(m.topic, out, m.log_time_ns)
            elif m.topic == CAMERA_INFO:
                msg = m.decode()
                width, height = scaled_size(msg.width, msg.height, scale)
                K = scale_intrinsics(camera_info_to_K(msg), (msg.width, msg.height), (width, height))
                writer.write(m.topic, make_camera_info(K, width, height, stamp_to_ns(msg.header.stamp),
                                                       msg.header.frame_id),
                             m.log_time_ns)
            else:
                writer.write_raw(m.topic, m.msgtype, m.data, m.log_time_ns)
            written[m.topic] = written.get(m.topic, 0) + 1
    sidecar = src.with_suffix('.gt.json')
    if sidecar.is_file():
        doc = json.loads(sidecar.read_text())
        camera = doc.get('camera', {})
        if {'K', 'width', 'height'} <= set(camera):
            size = scaled_size(camera['width'], camera['height'], scale)
            camera['K'] = scale_intrinsics(np.array(camera['K']), (camera['width'], camera['height']), size).tolist()
            camera['width'], camera['height'] = size
        dst.with_suffix('.gt.json').write_text(json.dumps(doc, indent=1) + '\n')
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m frodo_datasets.rescale', description=__doc__.split('\n\n')[0])
    parser.add_argument('src', help='contract bag (.mcap)')
    parser.add_argument('dst', help='output bag (.mcap)')
    parser.add_argument('--scale', type=float, required=True, help='image size factor, e.g. 0.5: 640x480 -> 320x240')
    args = parser.parse_args(argv)
    try:
        written = rescale_bag(args.src, args.dst, args.scale)
    except (BagError, ConversionError, ValueError, FileNotFoundError) as err:
        print(f'rescale: error: {err}', file=sys.stderr)
        return 1
    print(f'{args.dst}: ' + ', '.join(f'{t} {n}' for t, n in sorted(written.items())))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
