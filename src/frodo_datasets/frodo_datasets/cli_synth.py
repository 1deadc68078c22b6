"""`frodo synth`: render a synthetic room into a contract bag with ground truth (see `frodo_datasets.synth`).

    frodo synth OUT.mcap --scene walk --objects 4 --classes chair,"dining table" --frames 60 --seed 0
    python -m frodo_datasets.cli_synth OUT.mcap --scene orbit --objects 1 --frames 35
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from frodo_datasets.degrade import MaskNoise, PoseNoise
from frodo_datasets.shapes import class_names
from frodo_datasets.synth import SynthConfig, sidecar_path, synthesize


def _floats(count: int, name: str):
    """argparse type: 'a' or 'a,b,...' -> tuple of `count` floats (a single value is repeated)."""
    def parse(text: str) -> tuple[float, ...]:
        try:
            values = tuple(float(v) for v in text.split(','))
        except ValueError:
            values = ()
        if len(values) == 1:
            values = values * count
        if len(values) != count:
            raise argparse.ArgumentTypeError(f'{name}: expected {count} comma-separated numbers, got {text!r}')
        return values
    return parse


def _classes(text: str) -> tuple[str, ...]:
    names = tuple(n.strip() for n in text.split(',') if n.strip())
    known = class_names()
    for n in names:
        if n not in known:
            raise argparse.ArgumentTypeError(f'no procedural shapes for class {n!r}; available: {", ".join(known)}')
    if not names:
        raise argparse.ArgumentTypeError('--classes is empty')
    return names


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `frodo synth`."""
    parser.add_argument('out', type=Path, help='output bag (ROS 2 MCAP), e.g. bags/scene.mcap')
    parser.add_argument('--scene', choices=('walk', 'orbit'), default='walk',
                        help='walk: ScanNet-like room walk; orbit: Redwood-like loop around one object/group')
    parser.add_argument('--objects', type=int, default=3, help='number of objects (default 3)')
    parser.add_argument('--classes', type=_classes, default=('chair', 'dining table'),
                        help='comma-separated classes, cycled over the objects (default: chair,"dining table")')
    parser.add_argument('--frames', type=int, default=None, help='frames (default 60 walk, 35 orbit)')
    parser.add_argument('--width', type=int, default=320, help='image width (default 320)')
    parser.add_argument('--height', type=int, default=240, help='image height (default 240)')
    parser.add_argument('--hfov', type=float, default=60.0, help='horizontal field of view, degrees (default 60)')
    parser.add_argument('--fps', type=float, default=10.0, help='frame rate of the stamps (default 10)')
    parser.add_argument('--seed', type=int, default=0, help='seed of scene, trajectory and noise (default 0)')
    noise = parser.add_argument_group('degradations (default: none)')
    noise.add_argument('--mask-noise', type=int, default=0, metavar='PX',
                       help='erode/dilate each instance mask by a random radius up to PX pixels')
    noise.add_argument('--drop-rate', type=float, default=0.0, help='probability of missing a detection')
    noise.add_argument('--wrong-class-rate', type=float, default=0.0,
                       help='probability of reporting a detection with another class')
    noise.add_argument('--spurious-rate', type=float, default=0.0,
                       help='expected spurious detections (random blobs of any known class) per frame')
    noise.add_argument('--pose-noise', type=_floats(2, '--pose-noise'), default=(0.0, 0.0), metavar='DEG,M',
                       help='white noise on published poses: rotation std (deg), translation std (m)')
    noise.add_argument('--pose-drift', type=_floats(2, '--pose-drift'), default=(0.0, 0.0), metavar='DEG,M',
                       help='random-walk drift of published poses: per-frame rotation (deg) and translation (m) std')
    noise.add_argument('--image-noise', type=float, default=0.0, metavar='SIGMA',
                       help='Gaussian pixel noise std (0-255 scale)')
    extra = parser.add_argument_group('extra output')
    extra.add_argument('--depth', action='store_true', help='also write aligned depth (16UC1 mm)')
    extra.add_argument('--no-slam', action='store_true', help='do not write /slam/points')
    extra.add_argument('--slam-every', type=int, default=5, help='publish the SLAM map every N frames (default 5)')
    extra.add_argument('--no-sidecar', action='store_true', help='do not write the <stem>.gt.json sidecar')
    extra.add_argument('--compression', choices=('zstd', 'lz4', 'none'), default='zstd', help='MCAP chunk compression')
    parser.add_argument('--quiet', action='store_true', help='no progress bar')


def config_from_args(args: argparse.Namespace) -> SynthConfig:
    """SynthConfig from parsed `frodo synth` arguments."""
    frames = args.frames if args.frames is not None else (60 if args.scene == 'walk' else 35)
    mask = MaskNoise(morph_px=args.mask_noise, drop_rate=args.drop_rate, wrong_class_rate=args.wrong_class_rate,
                     spurious_rate=args.spurious_rate)
    pose = PoseNoise(rot_deg=args.pose_noise[0], trans_m=args.pose_noise[1],
                     drift_rot_deg=args.pose_drift[0], drift_trans_m=args.pose_drift[1])
    return SynthConfig(scene=args.scene, objects=args.objects, classes=tuple(args.classes), frames=frames,
                       width=args.width, height=args.height, seed=args.seed, fps=args.fps, hfov_deg=args.hfov,
                       mask_noise=mask, pose_noise=pose, image_noise=args.image_noise, depth=args.depth,
                       slam=not args.no_slam, slam_every=args.slam_every, compression=args.compression)


def run(args: argparse.Namespace) -> int:
    """Synthesise the bag; prints what was written. Returns 0, or 2 on invalid options."""
    try:
        config = config_from_args(args)
        if config.objects < 1 or config.frames < 1 or config.slam_every < 1:
            raise ValueError('--objects, --frames and --slam-every must be >= 1')
    except ValueError as err:
        print(f'frodo synth: error: {err}', file=sys.stderr)
        return 2
    from tqdm import tqdm
    with tqdm(total=config.frames, desc=f'synth {args.out.name}', unit='frame', disable=args.quiet) as bar:
        try:
            result = synthesize(config, args.out, progress=bar.update, sidecar=not args.no_sidecar)
        except RuntimeError as err:
            print(f'frodo synth: error: {err}', file=sys.stderr)
            return 1
    size = args.out.stat().st_size / 1e6
    print(f'wrote {args.out} ({size:.2f} MB): {config.frames} frames {config.width}x{config.height}, '
          f'{len(result.scene.objects)} objects ' +
          ', '.join(f'{o.id}:{o.class_name}/{o.family}' for o in result.scene.objects))
    for topic, n in result.counts.items():
        print(f'  {topic:<42} {n:>5}')
    if not args.no_sidecar:
        print(f'ground truth sidecar: {sidecar_path(args.out)}')
    return 0


def main(argv: list[str] | None = None) -> int:
    """`python -m frodo_datasets.cli_synth ...`"""
    parser = argparse.ArgumentParser(prog='frodo synth', description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == '__main__':
    sys.exit(main())
