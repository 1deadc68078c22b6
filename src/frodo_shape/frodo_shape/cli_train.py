"""`frodo train decoder|encoder`: train a shape prior (paper Sec. 4 joint embedding, Sec. 5.2 encoder).

    frodo train decoder --config furniture_decoder --out priors/mine [--resume] [--steps N]
                        [--meshes PATH --class NAME]
    frodo train encoder --config furniture_encoder --prior priors/mine [--out DIR] [--resume] [--steps N]
                        [--meshes PATH --class NAME]

Also runnable as `python -m frodo_shape.cli_train ...`. `--config` takes a YAML path or the name of a
config shipped in frodo_shape/configs. With `--meshes`, the user's meshes (ShapeNet layout
<synset>/<id>/models/model_normalized.obj or a plain folder) replace the procedural library, so a prior can
be trained for a new class; pass the same `--meshes/--class` to the encoder stage.
"""
from __future__ import annotations

import argparse
import sys


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the `decoder` and `encoder` sub-commands to `parser`."""
    sub = parser.add_subparsers(dest='stage', required=True, metavar='{decoder,encoder}')
    for stage, help_text, default_cfg in (
            ('decoder', 'stage 1: joint SDF + point auto-decoder and the training codes', 'furniture_decoder'),
            ('encoder', 'stage 2: image encoder regressing the codes of a trained decoder', 'furniture_encoder')):
        p = sub.add_parser(stage, help=help_text, description=help_text)
        p.add_argument('--config', default=default_cfg, help=f'YAML config path or shipped config name (default {default_cfg})')
        if stage == 'decoder':
            p.add_argument('--out', required=True, help='output prior folder (decoder.pt, config.yaml, shapes.yaml, plots)')
        else:
            p.add_argument('--prior', required=True, help='prior folder written by `frodo train decoder`')
            p.add_argument('--out', default=None, help='where encoder.pt goes (default: the prior folder)')
        p.add_argument('--resume', action='store_true', help='continue from <out>/checkpoints if present')
        p.add_argument('--steps', type=int, default=None, help='override the number of training steps')
        p.add_argument('--meshes', default=None, help='train on the meshes under PATH instead of the procedural library')
        p.add_argument('--class', dest='class_name', default=None,
                       help="class name of the meshes (e.g. 'chair'; with ShapeNet layout it selects the synset)")
        p.add_argument('--device', default='auto', help="'auto' (cuda if available), 'cpu' or 'cuda'")
        p.add_argument('--quiet', action='store_true', help='no progress bars')


def run(args: argparse.Namespace) -> int:
    """Run the sub-command parsed by `add_arguments`; returns a process exit code."""
    from frodo_shape.train import load_config, train_decoder, train_encoder
    try:
        config = load_config(args.config)
    except FileNotFoundError as e:
        print(f'frodo train: {e}', file=sys.stderr)
        return 2
    if args.meshes and not args.class_name:
        print('frodo train: --meshes needs --class NAME (the class the meshes belong to)', file=sys.stderr)
        return 2
    common = dict(resume=args.resume, steps=args.steps, device=args.device, progress=not args.quiet,
                  meshes=args.meshes, class_name=args.class_name)
    try:
        if args.stage == 'decoder':
            result = train_decoder(config, args.out, **common)
            where = args.out
        else:
            result = train_encoder(config, args.prior, args.out, **common)
            where = args.out or args.prior
    except (FileNotFoundError, ValueError) as e:
        print(f'frodo train {args.stage}: {e}', file=sys.stderr)
        return 1
    hist = result['history']
    last = {k: v[-1] for k, v in hist.items() if k != 'step' and v}
    print(f'frodo train {args.stage}: {result["steps"]} steps in {result["seconds"]:.0f} s, final losses '
          + ', '.join(f'{k}={v:.5f}' for k, v in last.items()) + f'; wrote {where}')
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='frodo train', description=__doc__.split('\n')[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == '__main__':
    sys.exit(main())
