"""`frodo convert`: play ScanNet, Redwood and TUM RGB-D sequences (and your own folders) as contract bags
(see `frodo_datasets.convert`).

    frodo convert tum rgbd_dataset_freiburg1_xyz fr1_xyz.mcap --views 35
    frodo convert scannet scans/scene0000_00 scene0000_00.mcap --every 10 --resize 640x480
    frodo convert redwood loft loft.mcap --trajectory loft.log --up 0,1,0
    frodo convert folder my_run my_run.mcap --gravity camera
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from frodo_datasets.convert import FORMATS, ConvertError, ConvertOptions, read_source, write_bag
from frodo_datasets.convert.common import select_keyframes, valid_pose
from frodo_datasets.convert.writer import GRAVITY_MODES, LANDMARK_MODES

# Reader options: flag dest -> (reader keyword, formats that accept it).
READER_FLAGS = {
    'intrinsics': ('intrinsics', ('tum', 'redwood', 'folder')),
    'max_dt': ('max_dt', ('tum', 'folder')),
    'depth_factor': ('depth_factor', ('tum', 'redwood')),
    'trajectory': ('trajectory', ('tum', 'redwood')),
    'mesh': ('mesh', ('redwood',)),
    'mesh_class': ('mesh_class', ('redwood',)),
    'labels_tsv': ('labels_tsv', ('scannet',)),
    'class_map': ('class_map', ('scannet',)),
    'prefer': ('prefer', ('scannet',)),
}


def _vector(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(','))
    except ValueError:
        values = ()
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f'expected x,y,z, got {text!r}')
    return values


def _resize(text: str):
    try:
        if 'x' in text:
            w, h = (int(v) for v in text.lower().split('x'))
            return (w, h)
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'expected WIDTHxHEIGHT (640x480) or a scale (0.5), got {text!r}') from None


def _class_map(text: str) -> dict[str, int]:
    """'chair=62,office chair=62,table=67' -> {name: coco id}."""
    out = {}
    for item in text.split(','):
        name, _, cid = item.partition('=')
        try:
            out[name.strip().lower()] = int(cid)
        except ValueError:
            raise argparse.ArgumentTypeError(f'expected NAME=COCO_ID pairs, got {item!r}') from None
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `frodo convert`."""
    parser.add_argument('format', choices=FORMATS, help='input layout (see the README section per dataset)')
    parser.add_argument('input', type=Path, help='dataset folder (ScanNet scene, Redwood/TUM sequence, your folder)')
    parser.add_argument('output', type=Path, help='output bag (ROS 2 MCAP)')
    frames = parser.add_argument_group('frames')
    frames.add_argument('--views', type=int, default=None, help='N keyframes spread evenly (the paper uses 35)')
    frames.add_argument('--every', type=int, default=1, help='take every K-th usable frame (default 1)')
    frames.add_argument('--max-frames', type=int, default=None, help='write at most M frames')
    frames.add_argument('--resize', type=_resize, default=None, metavar='WxH|SCALE',
                        help='output image size, e.g. 640x480 or 0.5 (intrinsics scaled to match)')
    frames.add_argument('--instances-at', choices=('labels', 'color'), default='labels',
                        help='with instances: resize colour to the label images (default) or labels to colour')
    frames.add_argument('--fps', type=float, default=30.0, help='frame rate for datasets without timestamps (30)')
    world = parser.add_argument_group('world frame (CONTRACT.md: z up)')
    world.add_argument('--gravity', choices=GRAVITY_MODES, default='auto',
                       help='auto: none for ScanNet (z up), floor fit with depth, else camera mean up')
    world.add_argument('--up', type=_vector, default=None, metavar='X,Y,Z',
                       help="the dataset world's up vector, rotated to +z (sets --gravity up)")
    world.add_argument('--landmarks', choices=LANDMARK_MODES, default='auto',
                       help='/slam/points from depth, from ORB features, or none (auto: depth if present, else none)')
    world.add_argument('--slam-every', type=int, default=5, help='publish the landmark map every N frames (5)')
    world.add_argument('--landmark-stride', type=int, default=4, help='depth landmarks: every N-th pixel (4)')
    world.add_argument('--landmark-voxel', type=float, default=0.03, help='landmark pooling voxel, m (0.03)')
    topics = parser.add_argument_group('optional topics')
    topics.add_argument('--no-depth', action='store_true', help='do not write /camera/depth/image_raw')
    topics.add_argument('--no-instances', action='store_true', help='do not write /camera/instances')
    topics.add_argument('--no-ground-truth', action='store_true', help='do not write /ground_truth/objects')
    reader = parser.add_argument_group('format-specific')
    reader.add_argument('--intrinsics', default=None,
                        help='tum: fr1|fr2|fr3|ros or a YAML; redwood/folder: a YAML (fx, fy, cx, cy, width, height)')
    reader.add_argument('--max-dt', type=float, default=None, help='tum/folder: timestamp tolerance, s (0.02)')
    reader.add_argument('--depth-factor', type=float, default=None,
                        help='tum/redwood: depth units per metre (tum 5000, redwood 1000)')
    reader.add_argument('--trajectory', default=None, help='tum: pose file (groundtruth.txt); redwood: the .log')
    reader.add_argument('--mesh', type=Path, default=None, help='redwood: ground-truth mesh (world frame of the .log)')
    reader.add_argument('--mesh-class', default=None, help='redwood: class name of --mesh (default chair)')
    reader.add_argument('--labels-tsv', type=Path, default=None, help='scannet: scannetv2-labels.combined.tsv')
    reader.add_argument('--class-map', type=_class_map, default=None, metavar='NAME=ID,...',
                        help='scannet: raw category -> COCO id (replaces the default map)')
    reader.add_argument('--prefer', choices=('exported', 'sens'), default=None,
                        help='scannet: which to read when both color/ and the .sens file exist (exported)')
    parser.add_argument('--compression', choices=('zstd', 'lz4', 'none'), default='zstd', help='MCAP compression')
    parser.add_argument('--quiet', action='store_true', help='no progress bar')


def options_from_args(args: argparse.Namespace) -> tuple[ConvertOptions, dict]:
    """(ConvertOptions, reader keyword arguments) from parsed arguments; raises ValueError on a bad combination."""
    gravity = 'up' if args.up is not None else args.gravity
    if args.up is not None and args.gravity not in ('auto', 'up'):
        raise ValueError('--up and --gravity are exclusive')
    for name, value in (('--every', args.every), ('--slam-every', args.slam_every),
                        ('--landmark-stride', args.landmark_stride)):
        if value < 1:
            raise ValueError(f'{name} must be >= 1')
    if args.views is not None and args.views < 1 or args.max_frames is not None and args.max_frames < 1:
        raise ValueError('--views and --max-frames must be >= 1')
    if args.landmark_voxel <= 0:
        raise ValueError('--landmark-voxel must be > 0')
    options = ConvertOptions(views=args.views, every=args.every, max_frames=args.max_frames, resize=args.resize,
                             instances_at=args.instances_at, gravity=gravity, up=args.up, landmarks=args.landmarks,
                             slam_every=args.slam_every, landmark_stride=args.landmark_stride,
                             landmark_voxel=args.landmark_voxel, depth=not args.no_depth, instances=not args.no_instances,
                             ground_truth=not args.no_ground_truth, fps=args.fps, compression=args.compression)
    reader = {}
    for dest, (keyword, formats) in READER_FLAGS.items():
        value = getattr(args, dest)
        if value is None:
            continue
        if args.format not in formats:
            flag = '--' + dest.replace('_', '-')
            raise ValueError(f'{flag} does not apply to {args.format} (only to {", ".join(formats)})')
        reader[keyword] = value
    return options, reader


def run(args: argparse.Namespace) -> int:
    """Convert; prints a summary. Returns 0, 1 when the input cannot be converted, 2 on invalid options."""
    try:
        options, reader = options_from_args(args)
    except ValueError as err:
        print(f'frodo convert: error: {err}', file=sys.stderr)
        return 2
    if args.output.suffix != '.mcap':
        print(f'frodo convert: error: the output must be a .mcap file, got {args.output}', file=sys.stderr)
        return 2
    from tqdm import tqdm
    try:
        source = read_source(args.format, args.input, options, **reader)
        usable = sum(valid_pose(f.pose) for f in source.frames)
        total = len(select_keyframes(usable, options.views, options.every, options.max_frames))
        with tqdm(total=total, desc=f'convert {args.input.name}', unit='frame', disable=args.quiet) as bar:
            summary = write_bag(source, args.output, options, progress=bar.update)
    except ConvertError as err:
        print(f'frodo convert: error: {err}', file=sys.stderr)
        return 1
    print(summary.text())
    return 0


def main(argv: list[str] | None = None) -> int:
    """`python -m frodo_datasets.cli_convert ...`"""
    parser = argparse.ArgumentParser(prog='frodo convert', description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == '__main__':
    sys.exit(main())
