"""`frodo synth`: render a synthetic room into a contract bag with ground truth (see `frodo_datasets.synth`).

    frodo synth OUT.mcap --scene walk --objects 4 --classes chair,"dining table" --frames 60 --seed 0
    python -m frodo_datasets.cli_synth OUT.mcap --scene orbit --objects 1 --frames 35
    frodo synth OUT.mcap --preset handheld --objects 4 --frames 35 --seed 5      # real-capture regime
    frodo synth OUT.mcap --preset realwalk --objects 5 --seed 5                   # inside-out walk (issue 27)

A preset sets defaults (`realcapture.preset_kwargs`); any option given explicitly overrides it.
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

from frodo_datasets.realcapture import PRESETS, preset_kwargs
from frodo_datasets.scene import CONTINUOUS_PATHS, FAMILY_SETS, TRAJECTORIES
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
    parser.add_argument('--preset', choices=PRESETS, default='clean',
                        help='clean: exact masks, poses and images (default); handheld: every real-capture '
                             'condition at realistic levels (close-range hand-held scan, 35 keyframes, chairs '
                             'under tables, clutter, mask and pose errors, camera effects); realwalk: the '
                             'handheld conditions on an inside-out walk through the middle of a room looking '
                             'outwards (every object seen from one side in a few keyframes, chairs behind tables)')
    parser.add_argument('--scene', choices=TRAJECTORIES, default=None,
                        help='walk: ScanNet-like room walk (default); orbit: Redwood-like loop around one '
                             'object/group; handheld: close-range scan, frames spread over a long path; '
                             'insideout: furniture along the walls, a slow walk through the middle panning round '
                             '(rotation-dominated, narrow baseline)')
    parser.add_argument('--objects', type=int, default=3, help='number of objects (default 3)')
    parser.add_argument('--classes', type=_classes, default=('chair', 'dining table'),
                        help='comma-separated classes, cycled over the objects (default: chair,"dining table")')
    parser.add_argument('--frames', type=int, default=None, help='frames (default 60 walk, 35 orbit)')
    parser.add_argument('--width', type=int, default=320, help='image width (default 320)')
    parser.add_argument('--height', type=int, default=240, help='image height (default 240)')
    parser.add_argument('--hfov', type=float, default=60.0, help='horizontal field of view, degrees (default 60)')
    parser.add_argument('--fps', type=float, default=10.0, help='frame rate of the stamps (default 10)')
    parser.add_argument('--seed', type=int, default=0, help='seed of scene, trajectory and noise (default 0)')
    room = parser.add_argument_group('room (default: the preset\'s)')
    room.add_argument('--families', choices=FAMILY_SETS, default=None,
                      help='shape families: train (the prior\'s training families, default), heldout '
                           '(evaluation-only designs), all (both), extra (training + the broader prior\'s extra designs)')
    room.add_argument('--tuck-chairs', type=float, default=None, metavar='P',
                      help='probability that a chair is pushed under a table (default 0)')
    room.add_argument('--clutter', type=int, default=None, metavar='N',
                      help='unlabelled small items on each table top (default 0)')
    noise = parser.add_argument_group('degradations (default: the preset\'s; clean: none)')
    noise.add_argument('--mask-noise', type=int, default=None, metavar='PX',
                       help='erode/dilate each instance mask by a random radius up to PX pixels')
    noise.add_argument('--mask-boundary', type=float, default=None, metavar='PX',
                       help='std of a smooth random displacement of each mask outline, pixels')
    noise.add_argument('--mask-holes', type=float, default=None, metavar='R',
                       help='expected holes per instance mask')
    noise.add_argument('--mask-bleed', type=int, default=None, metavar='PX',
                       help='each mask spills up to PX pixels into its neighbours on one side')
    noise.add_argument('--drop-rate', type=float, default=None, help='probability of missing a detection')
    noise.add_argument('--wrong-class-rate', type=float, default=None,
                       help='probability of reporting a detection with another class')
    noise.add_argument('--spurious-rate', type=float, default=None,
                       help='expected spurious detections (random blobs of any known class) per frame')
    noise.add_argument('--pose-noise', type=_floats(2, '--pose-noise'), default=None, metavar='DEG,M',
                       help='white noise on published poses: rotation std (deg), translation std (m)')
    noise.add_argument('--pose-drift', type=_floats(2, '--pose-drift'), default=None, metavar='DEG,M',
                       help='random-walk drift of published poses: per-frame rotation (deg) and translation (m) '
                            'std (per second of capture with --scene handheld or insideout)')
    noise.add_argument('--image-noise', type=float, default=None, metavar='SIGMA',
                       help='Gaussian pixel noise std (0-255 scale)')
    noise.add_argument('--slam-texture', type=float, default=None, metavar='MIN',
                       help='SLAM landmarks only where the surface texture reaches MIN (0 = everywhere)')
    noise.add_argument('--slam-noise', type=float, default=None, metavar='M', help='landmark position std (0.01)')
    camera = parser.add_argument_group('camera and rendering (default: the preset\'s; clean: none)')
    camera.add_argument('--exposure', type=_floats(2, '--exposure'), default=None, metavar='GAIN,WB',
                        help='std of the log exposure gain and of the per-channel white balance, per frame')
    camera.add_argument('--vignetting', type=float, default=None, help='brightness lost at the corners (0-1)')
    camera.add_argument('--sensor-noise', type=_floats(2, '--sensor-noise'), default=None, metavar='SHOT,READ',
                        help='Poisson-Gaussian noise: variance = SHOT * intensity + READ^2 (0-255 scale)')
    camera.add_argument('--motion-blur', type=float, default=None, metavar='S',
                        help='exposure time (s) for motion blur (needs --scene handheld or insideout)')
    camera.add_argument('--distortion', type=_floats(2, '--distortion'), default=None, metavar='K1,K2',
                        help='radial lens distortion applied to images, masks and depth, written to camera_info d '
                             '(the graph assumes undistorted images)')
    camera.add_argument('--ao', type=int, default=None, metavar='N', help='ambient-occlusion rays per pixel')
    camera.add_argument('--soft-shadows', type=float, default=None, metavar='DEG',
                        help='angular radius of the light for soft shadows')
    camera.add_argument('--specular', type=float, default=None, help='strength of specular highlights')
    extra = parser.add_argument_group('extra output')
    extra.add_argument('--depth', action='store_true', help='also write aligned depth (16UC1 mm)')
    extra.add_argument('--depth-topic', default=None,
                       help='depth topic (default: CONTRACT v1.1 /camera/depth/image_raw, where the nodes listen)')
    extra.add_argument('--depth-noise', action=argparse.BooleanOptionalAction, default=None,
                       help='Kinect-like depth noise and holes (the handheld preset turns it on)')
    extra.add_argument('--no-slam', action='store_true', help='do not write /slam/points')
    extra.add_argument('--slam-every', type=int, default=5, help='publish the SLAM map every N frames (default 5)')
    extra.add_argument('--no-sidecar', action='store_true', help='do not write the <stem>.gt.json sidecar')
    extra.add_argument('--compression', choices=('zstd', 'lz4', 'none'), default='zstd', help='MCAP chunk compression')
    parser.add_argument('--quiet', action='store_true', help='no progress bar')


def _given(**values) -> dict:
    """The keyword arguments whose value was given (not None)."""
    return {k: v for k, v in values.items() if v is not None}


def config_from_args(args: argparse.Namespace) -> SynthConfig:
    """SynthConfig from parsed `frodo synth` arguments: the preset's values, overridden by explicit options."""
    base = SynthConfig(**preset_kwargs(args.preset))
    scene = args.scene or base.scene
    frames = args.frames if args.frames is not None else (
        base.frames if args.preset != 'clean' else (60 if scene == 'walk' else 35))
    pose_noise, pose_drift = args.pose_noise or (None, None), args.pose_drift or (None, None)
    mask = replace(base.mask_noise, **_given(
        morph_px=args.mask_noise, drop_rate=args.drop_rate, wrong_class_rate=args.wrong_class_rate,
        spurious_rate=args.spurious_rate, boundary_px=args.mask_boundary, hole_rate=args.mask_holes,
        bleed_px=args.mask_bleed))
    pose = replace(base.pose_noise, **_given(rot_deg=pose_noise[0], trans_m=pose_noise[1],
                                             drift_rot_deg=pose_drift[0], drift_trans_m=pose_drift[1]))
    if scene in CONTINUOUS_PATHS:
        pose = replace(pose, drift_per_second=True)
    exposure, sensor = args.exposure or (None, None), args.sensor_noise or (None, None)
    capture = replace(base.capture, **_given(
        exposure_std=exposure[0], white_balance_std=exposure[1], vignetting=args.vignetting, shot_noise=sensor[0],
        read_noise=sensor[1], motion_blur_s=args.motion_blur,
        distortion=tuple(args.distortion) if args.distortion else None, depth_noise=args.depth_noise))
    realism = replace(base.realism, **_given(ao_samples=args.ao, soft_shadow_deg=args.soft_shadows,
                                             specular=args.specular))
    return replace(base, **_given(
        scene=scene, objects=args.objects, classes=tuple(args.classes), frames=frames, width=args.width,
        height=args.height, seed=args.seed, fps=args.fps, hfov_deg=args.hfov, mask_noise=mask, pose_noise=pose,
        image_noise=args.image_noise, depth=args.depth or base.depth, slam=not args.no_slam,
        slam_every=args.slam_every, compression=args.compression, family_set=args.families,
        tuck_chairs=args.tuck_chairs, clutter=args.clutter, capture=capture, realism=realism,
        slam_texture_min=args.slam_texture, slam_noise_m=args.slam_noise, depth_topic=args.depth_topic))


def run(args: argparse.Namespace) -> int:
    """Synthesise the bag; prints what was written. Returns 0, or 2 on invalid options."""
    try:
        config = config_from_args(args)
        if config.objects < 1 or config.frames < 1 or config.slam_every < 1:
            raise ValueError('--objects, --frames and --slam-every must be >= 1')
        if config.capture.motion_blur_s > 0 and config.scene not in CONTINUOUS_PATHS:
            raise ValueError('--motion-blur needs --scene handheld or insideout (a continuous camera path)')
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
