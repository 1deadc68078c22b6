"""`frodo bench`: measure decoder and bag throughput, optimiser seconds per iteration against views,
association latency against objects in view and the demo run end to end; write OUT/bench.json + plots."""
from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

from frodo_bringup.bench import ALL_SECTIONS, DEMO_BAG, SECTIONS, markdown_page, run_all, summary


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of `frodo bench`."""
    parser.add_argument('--out', default='out/bench', metavar='DIR',
                        help='output directory: bench.json, optimiser.png, association.png, diagnostics.png, '
                             'soak/soak.json + soak.png (default: %(default)s)')
    parser.add_argument('--bag', default=str(DEMO_BAG), metavar='BAG',
                        help='contract bag of the bag_read, end_to_end, soak and optim_workers sections, relative to '
                             'the working directory like the bench/ scripts (default: %(default)s, as frodo demo)')
    parser.add_argument('--quick', action='store_true',
                        help='fewer views, objects, frames and repeats (a few minutes on 2 CPUs)')
    parser.add_argument('--only', nargs='+', choices=ALL_SECTIONS, metavar='SECTION',
                        help=f'run only these sections ({", ".join(ALL_SECTIONS)}); default: all but soak and optim_workers')
    parser.add_argument('--soak-frames', type=int, default=10_000, metavar='N',
                        help='frames of the soak run (demo bag repeated; default: %(default)s)')
    parser.add_argument('--soak-rate', type=float, default=2.0, metavar='X',
                        help='playback rate of the soak run, times real time (default: %(default)s)')
    parser.add_argument('--page', type=Path, default=None, metavar='FILE',
                        help='also write the figures as a markdown page, its plots in a folder named after it '
                             '(the README links docs/performance.md, made with --page docs/performance.md)')
    parser.add_argument('--device', default='auto', help="torch device: 'auto' (cuda if available), 'cpu', 'cuda'")
    parser.add_argument('--threads', type=int, default=0, metavar='N',
                        help='torch CPU threads (default: torch\'s own choice)')


def run(args: argparse.Namespace) -> int:
    """Run the benchmarks; 0 when every section ran, 1 when one failed (its error is in the JSON), 2 on bad options."""
    import torch
    device = args.device
    if device == 'auto':
        device = 'cuda' if torch.cuda.is_available() else 'cpu'
    if device.startswith('cuda') and not torch.cuda.is_available():
        print('frodo bench: error: --device cuda but no CUDA device is available', file=sys.stderr)
        return 2
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    out = Path(args.out)
    if args.soak_frames < 1 or args.soak_rate <= 0:
        print('frodo bench: error: --soak-frames must be >= 1 and --soak-rate > 0', file=sys.stderr)
        return 2
    doc = run_all(out, args.quick, device, list(args.only or SECTIONS),
                  log=lambda text: print(f'frodo bench: {text}', file=sys.stderr, flush=True),
                  soak_frames=args.soak_frames, soak_rate=args.soak_rate, bag=args.bag)
    (out / 'bench.json').write_text(json.dumps(doc, indent=2) + '\n')
    print(summary(doc))
    print(f'written: {out / "bench.json"}' + ''.join(f', {out / p}' for p in doc['plots']))
    if args.page is not None:
        from frodo_bringup.report import commit_key
        doc['machine']['commit_key'] = commit_key()
        figures = args.page.parent / args.page.stem
        figures.mkdir(parents=True, exist_ok=True)
        for plot in doc['plots']:
            if plot.endswith('.png'):
                shutil.copyfile(out / plot, figures / Path(plot).name)
        doc['plots'] = [Path(p).name for p in doc['plots']]
        args.page.write_text(markdown_page(doc, figures.name))
        print(f'written: {args.page}')
    return 1 if any(isinstance(v, dict) and 'error' in v for v in doc.values()) else 0
