"""Real-capture evaluation and tuning sets: build the bags, run the graph on them, pool the scores.

    python -m frodo_datasets.eval_sets build realcapture OUT [--variants full,full100] [--scenes 0-11]
    python -m frodo_datasets.eval_sets run   realcapture OUT [--variants full] [--runner reconstruct|run]
    python -m frodo_datasets.eval_sets table realcapture OUT [--markdown]
    python -m frodo_datasets.eval_sets families realcapture OUT --variants full   # seen vs held-out designs
    python -m frodo_datasets.eval_sets stats realwalk OUT                          # how the bags see their objects

Disjoint sets of rooms (issue 9), all in the `handheld` real-capture regime (`realcapture`):
- `realcapture` (HELD OUT, for reporting only): 12 rooms, seeds 9100-9111, 3 or 4 objects each (42 in
  all: 1-2 tables and 2 chairs), shapes from the training families AND the evaluation-only families
  (`shapes.eval_families`: cantilever and tub chairs, desks, round four-leg tables), which no prior was
  trained on and nobody may tune on;
- `realcapture-tune` (for tuning): 6 rooms, seeds 8100-8105, training families only;
- `realcapture-tune2` (for tuning): 12 more rooms, seeds 8200-8211, training families only: with the first
  set 63 objects, so that a choice is not made on the 30-point swings of a few of 21 objects;
- `realcapture-tune3` (for tuning): 18 rooms, seeds 8300-8317, the training families and the extra families
  of the broader prior (`shapes.extra_families`): for the first prior `furniture` these are unseen designs,
  so the set measures what the held-out set's unseen designs ask without touching them (not so for
  `furniture_broad`, which trains on them).
Never tune on `realcapture`; report on it.

Inside-out walks (issue 27: the `realcapture` set scores recall ~98 % while real walks find a third of the
objects), in the `realwalk` regime (`realcapture.preset_kwargs('realwalk')`: the `handheld` conditions on a
walk through the middle of a room looking outwards, `scene.InsideOutPath`), 4 or 5 objects per room (1-2
tables and 3 chairs, nearly every chair pushed under a table on the side away from the camera):
- `realwalk` (HELD OUT, for reporting only): 12 rooms, seeds 9200-9211, 54 objects, held-out families only
  (`shapes.eval_families`);
- `realwalk-tune` (for tuning): 12 rooms, seeds 8400-8411, training families only;
- `realwalk-tune2` (for tuning): 12 more rooms, seeds 8500-8511, training families only: single objects and
  draws of the detector noise move realwalk-tune's pooled figures by several points, so a change is judged on
  both (108 objects);
- `realwalk-tune3` (for tuning): 40 more rooms, seeds 8600-8639, training families only: failures that one
  room in ten shows (a long table published twice) need more rooms than the first two sets hold.

Variants (`VARIANTS`) are the same rooms under different conditions: `full` (every condition of the set's
preset, `EvalSet.preset`: `handheld` or `realwalk`, 35 keyframes), `full100` (the same, 100 views), `full640`
(the same at 640x480, a Kinect's size, instead of 320x240, with the detector's pixel errors doubled), `depth`
(the same rooms and keyframes with a registered Kinect-like depth image, CONTRACT v1.1, as RGB-D captures
such as ScanNet, Redwood or TUM have), and one
condition of the `handheld` preset at a time on top of `plain` (the
project's usual regime: a room walk of 60 consecutive clean frames): `truncation` (close-range hand-held
path, 100 views, clean), `keyframes` (the same path at 35 keyframes), `occlusion` (chairs pushed under
tables, clutter on tables), `masks` (detector-like mask errors), `drift` (pose noise and drift), `landmarks`
(SLAM points only on textured surfaces, sparser and noisier), `camera` (exposure, vignetting, sensor noise,
ambient occlusion, soft shadows, specular highlights).

Bags are not committed; `build` regenerates them deterministically (same seed -> same scene and frames),
each with its `.gt.json` sidecar (true object and camera poses; never read by the graph).
`run` reconstructs every bag that has no result yet (results/<variant>/<scene>.json, so an interrupted run
keeps what it finished; the runner is recorded in the result) and scores it with the contract protocol:
`--runner reconstruct` (the default) is the offline pipeline `frodo reconstruct` (deterministic, one process,
about twice as fast), `--runner run` the live graph `frodo run` (`--rate`, `--timeout`). `table` pools them:
recall, false positives per scene, median centre error, mean CD and F1@5cm of the matched objects. `stats`
pools `frodo_datasets.capture_stats` over the built bags (keyframes in view per object, viewing-angle
spread, detections cut by a nearer object, turn and baseline between keyframes).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from frodo_datasets.realcapture import preset_kwargs
from frodo_datasets.synth import SynthConfig, sidecar_path, synthesize

CLASSES = ('dining table', 'chair', 'chair')  # cycled: 3 objects = 1 table + 2 chairs, 4 = 2 + 2
WALK_CLASSES = ('dining table', 'chair', 'chair', 'chair')  # 4 objects = 1 table + 3 chairs, 5 = 2 + 3
RUNNERS = ('reconstruct', 'run')


@dataclass(frozen=True)
class EvalSet:
    """A named set of rooms: seeds, object counts, the shape families they draw from, the classes cycled over
    the objects and the `frodo synth` preset of its `full` and `full100` variants."""

    name: str
    seeds: tuple[int, ...]
    objects: tuple[int, ...]
    family_set: str
    purpose: str
    preset: str = 'handheld'
    classes: tuple[str, ...] = CLASSES

    def scenes(self) -> list[tuple[str, int, int]]:
        """(scene name, seed, object count) per room."""
        return [(f'{self.name}-{seed}', seed, n) for seed, n in zip(self.seeds, self.objects)]


SETS: dict[str, EvalSet] = {
    'realcapture': EvalSet('realcapture', tuple(range(9100, 9112)), tuple(3 + i % 2 for i in range(12)), 'all',
                           'held-out evaluation: report only, never tune'),
    'realcapture-tune': EvalSet('realcapture-tune', tuple(range(8100, 8106)), tuple(3 + i % 2 for i in range(6)),
                                'train', 'tuning (training families only)'),
    'realcapture-tune2': EvalSet('realcapture-tune2', tuple(range(8200, 8212)), tuple(3 + i % 2 for i in range(12)),
                                 'train', 'tuning, second set (training families only)'),
    'realcapture-tune3': EvalSet('realcapture-tune3', tuple(range(8300, 8318)), tuple(3 + i % 2 for i in range(18)),
                                 'extra', 'tuning, third set (training and extra families: designs the first '
                                 'prior `furniture` has not seen)'),
    'realwalk': EvalSet('realwalk', tuple(range(9200, 9212)), tuple(4 + i % 2 for i in range(12)), 'heldout',
                        'held-out evaluation of inside-out walks (issue 27): report only, never tune',
                        preset='realwalk', classes=WALK_CLASSES),
    'realwalk-tune': EvalSet('realwalk-tune', tuple(range(8400, 8412)), tuple(4 + i % 2 for i in range(12)), 'train',
                             'tuning on inside-out walks (training families only)', preset='realwalk',
                             classes=WALK_CLASSES),
    'realwalk-tune2': EvalSet('realwalk-tune2', tuple(range(8500, 8512)), tuple(4 + i % 2 for i in range(12)),
                              'train', 'tuning on inside-out walks, second set (training families only)',
                              preset='realwalk', classes=WALK_CLASSES),
    'realwalk-tune3': EvalSet('realwalk-tune3', tuple(range(8600, 8640)), tuple(4 + i % 2 for i in range(40)),
                              'train', 'tuning on inside-out walks, third set: 40 rooms, where rarer failures show '
                              '(training families only)', preset='realwalk', classes=WALK_CLASSES),
}

_HANDHELD = preset_kwargs('handheld')
_PLAIN = dict(scene='walk', frames=60)


def _variant(**overrides) -> Callable[[SynthConfig], SynthConfig]:
    return lambda base: replace(base, **overrides)


# Per-frame drift for the 60-frame walk giving the same end-of-sequence drift as the hand-held path's
# per-second random walk over its ~115 s: per-frame std = per-second std * sqrt(115 / 60).
_WALK_DRIFT = replace(_HANDHELD['pose_noise'], drift_per_second=False,
                      drift_rot_deg=_HANDHELD['pose_noise'].drift_rot_deg * np.sqrt(115 / 60),
                      drift_trans_m=_HANDHELD['pose_noise'].drift_trans_m * np.sqrt(115 / 60))


def at_image_scale(config: SynthConfig, factor: int) -> SynthConfig:
    """The same capture with images `factor` times as wide and high (the field of view kept) and the detector's
    pixel errors (erosion/dilation, outline displacement, bleeding) scaled with them: the same relative mask
    errors on more pixels, so that a result that changes measures the method's own pixel constants."""
    if factor == 1:
        return config
    noise = config.mask_noise
    return replace(config, width=config.width * factor, height=config.height * factor,
                   mask_noise=replace(noise, morph_px=noise.morph_px * factor, boundary_px=noise.boundary_px * factor,
                                      bleed_px=noise.bleed_px * factor))


VARIANTS: dict[str, Callable[[SynthConfig], SynthConfig]] = {
    'full': _variant(**_HANDHELD),
    'full100': _variant(**{**_HANDHELD, 'frames': 100}),
    'full640': lambda config: at_image_scale(_variant(**_HANDHELD)(config), 2),
    'depth': _variant(**_HANDHELD, depth=True),
    'plain': _variant(**_PLAIN),
    'truncation': _variant(scene='handheld', frames=100),
    'keyframes': _variant(scene='handheld', frames=35),
    'occlusion': _variant(**_PLAIN, tuck_chairs=_HANDHELD['tuck_chairs'], clutter=_HANDHELD['clutter']),
    'masks': _variant(**_PLAIN, mask_noise=_HANDHELD['mask_noise']),
    'drift': _variant(**_PLAIN, pose_noise=_WALK_DRIFT),
    'landmarks': _variant(**_PLAIN, slam_texture_min=_HANDHELD['slam_texture_min'],
                          slam_density=_HANDHELD['slam_density'], slam_noise_m=_HANDHELD['slam_noise_m']),
    'camera': _variant(**_PLAIN, realism=_HANDHELD['realism'],
                       capture=replace(_HANDHELD['capture'], motion_blur_s=0.0, depth_noise=False)),
}


# variant -> (frames (None: the preset's), image scale, registered depth) on the set's preset
PRESET_VARIANTS = {'full': (None, 1, False), 'full100': (100, 1, False), 'full640': (None, 2, False),
                   'depth': (None, 1, True)}


def scene_config(eval_set: EvalSet, seed: int, objects: int, variant: str) -> SynthConfig:
    """SynthConfig of one room of `eval_set` under `variant` (`full`, `full100`, `full640`, `depth`: the set's
    preset)."""
    base = SynthConfig(objects=objects, classes=eval_set.classes, seed=seed, family_set=eval_set.family_set)
    if variant in PRESET_VARIANTS:
        frames, scale, depth = PRESET_VARIANTS[variant]
        config = replace(base, **{**preset_kwargs(eval_set.preset), **({'frames': frames} if frames else {}),
                                  'depth': depth})
        return at_image_scale(config, scale)
    return VARIANTS[variant](base)


def _select(items: list, spec: str | None) -> list:
    """Items picked by a spec like '0-3,7' (indices), or all."""
    if not spec:
        return items
    picked = []
    for part in spec.split(','):
        lo, _, hi = part.partition('-')
        picked += list(range(int(lo), int(hi or lo) + 1))
    return [items[i] for i in picked if 0 <= i < len(items)]


def bag_path(out: Path, variant: str, scene: str) -> Path:
    return out / 'bags' / variant / f'{scene}.mcap'


def build(eval_set: EvalSet, out: Path, variants: list[str], scenes: str | None = None) -> list[Path]:
    """Write the bags (skipping those already there); returns their paths."""
    paths = []
    for variant in variants:
        for scene, seed, n in _select(eval_set.scenes(), scenes):
            path = bag_path(out, variant, scene)
            if not path.is_file():
                path.parent.mkdir(parents=True, exist_ok=True)
                started = time.monotonic()
                tmp = path.with_suffix('.partial.mcap')
                result = synthesize(scene_config(eval_set, seed, n, variant), tmp)
                sidecar_path(tmp).rename(sidecar_path(path))  # true poses: e.g. bench_dense --code oracle
                tmp.rename(path)
                print(f'{path}: {len(result.scene.objects)} objects ('
                      + ', '.join(f'{o.class_name}/{o.family}' for o in result.scene.objects)
                      + f'), {time.monotonic() - started:.0f} s', flush=True)
            paths.append(path)
    return paths


def _frodo() -> list[str]:
    exe = Path(sys.executable).with_name('frodo')
    return [str(exe)] if exe.is_file() else [shutil.which('frodo') or 'frodo']


def score(pred_dir: Path, bag: Path) -> dict:
    """Contract-protocol scores of one run (frodo_common.evaluation), as a JSON-ready dict."""
    from frodo_common.evaluation import evaluate, load_ground_truth, load_predictions

    gt = load_ground_truth(bag)
    pred = load_predictions(pred_dir)
    return evaluate(pred, gt).to_dict()


def runner_command(runner: str, bag: Path, pred_dir: Path, params: list[str] | None = None, rate: float = 1.0,
                   timeout: float = 300.0) -> list[str]:
    """The command line that reconstructs `bag` into `pred_dir`: `frodo reconstruct` (runner 'reconstruct', the
    offline pipeline; rate and timeout do not apply) or `frodo run` (runner 'run', the live graph)."""
    if runner == 'reconstruct':
        command = [*_frodo(), 'reconstruct', str(bag), '--out', str(pred_dir), '--quiet']
    elif runner == 'run':
        command = [*_frodo(), 'run', str(bag), '--out', str(pred_dir), '--rate', str(rate), '--no-progress',
                   '--timeout', str(timeout)]
    else:
        raise ValueError(f'runner must be one of {RUNNERS}, got {runner!r}')
    for p in params or []:
        command += ['--params', p]
    return command


def run(eval_set: EvalSet, out: Path, variants: list[str], scenes: str | None = None, rate: float = 1.0,
        params: list[str] | None = None, timeout: float = 300.0, code: Path | None = None,
        runner: str = 'reconstruct') -> None:
    """Reconstruction + scoring of every built bag without a result yet; writes results/<variant>/<scene>.json.

    runner: 'reconstruct' (`frodo reconstruct`, the offline pipeline: deterministic, about twice as fast; the
    default) or 'run' (`frodo run`, the live graph, with `rate` and `timeout`); see `runner_command`.
    code: run from this source tree (its src/frodo_* packages first on PYTHONPATH, e.g. a `git archive` of
    the commit to measure) instead of the installed packages.
    """
    if runner not in RUNNERS:
        raise ValueError(f'runner must be one of {RUNNERS}, got {runner!r}')
    env = os.environ.copy()
    if code is not None:
        packages = sorted(str(p) for p in (Path(code) / 'src').glob('frodo_*') if p.is_dir())
        if not packages:
            raise FileNotFoundError(f'no src/frodo_* packages under {code}')
        env['PYTHONPATH'] = os.pathsep.join(packages + [env.get('PYTHONPATH', '')]).rstrip(os.pathsep)
    for variant in variants:
        for scene, _, _ in _select(eval_set.scenes(), scenes):
            bag = bag_path(out, variant, scene)
            result_path = out / 'results' / variant / f'{scene}.json'
            if result_path.is_file() or not bag.is_file():
                continue
            pred_dir = out / 'runs' / variant / scene
            command = runner_command(runner, bag, pred_dir, params, rate, timeout)
            started = time.monotonic()
            proc = subprocess.run(command, capture_output=True, text=True, env=env)
            seconds = time.monotonic() - started
            if pred_dir.is_dir():
                (pred_dir / f'frodo_{runner}.log').write_text(proc.stdout + proc.stderr)
            if not (pred_dir / 'objects.json').is_file():
                print(f'{scene} [{variant}]: frodo {runner} wrote no outputs (exit {proc.returncode}):\n'
                      f'{(proc.stdout + proc.stderr)[-2000:]}', file=sys.stderr, flush=True)
                continue
            # frodo run not done in time (exit 3) or nodes stopped by force (exit 1): the outputs written so far
            # are what a user would get; scored, and the exit code is kept with the result.
            report = score(pred_dir, bag)
            report['run'] = {'runner': runner, 'exit_code': proc.returncode, 'seconds': seconds,
                             **({'rate': rate} if runner == 'run' else {}),
                             'code': str(code) if code is not None else 'installed'}
            result_path.parent.mkdir(parents=True, exist_ok=True)
            result_path.write_text(json.dumps(report, indent=1) + '\n')
            o = report['overall']
            print(f'{scene} [{variant}]: {o["n_matched"]}/{o["n_gt"]} found, {o["false_positives"]} FP, '
                  f'F1 {o["f1"] if o["f1"] is not None else float("nan"):.1f}, {seconds:.0f} s, '
                  f'exit {proc.returncode}', flush=True)


def _live(report: dict) -> bool:
    """The result came from `frodo run` (exit codes 1 and 3 mean a forced stop and a timeout only there)."""
    return 'run' in report and report['run'].get('runner', 'run') == 'run'


def pool(reports: list[dict]) -> dict:
    """Pooled scores of several runs: recall %, false positives per scene, median centre error (cm),
    mean CD (cm), F1@5cm and COMP@5cm (%, completion: of the ground-truth surface, how much lies within 5 cm
    of the estimate) over matched objects, and F1 with every missed object counted as 0."""
    pairs = [p for r in reports for p in r['pairs']]
    comp = [p['comp'] for p in pairs if p.get('comp') is not None]
    n_gt = sum(r['overall']['n_gt'] for r in reports)
    fp = sum(r['overall']['false_positives'] for r in reports)
    f1 = [p['f1'] for p in pairs]
    return {
        'scenes': len(reports), 'objects': n_gt, 'found': len(pairs),
        'timed_out': sum(_live(r) and r['run'].get('exit_code', 0) == 3 for r in reports),
        'forced_stop': sum(_live(r) and r['run'].get('exit_code', 0) == 1 for r in reports),
        'recall': 100.0 * len(pairs) / n_gt if n_gt else 0.0,
        'fp_per_scene': fp / len(reports) if reports else 0.0,
        'median_centre_cm': 100.0 * float(np.median([p['centroid_distance_m'] for p in pairs])) if pairs else None,
        'mean_cd_cm': float(np.mean([p['cd_cm'] for p in pairs])) if pairs else None,
        'mean_f1': float(np.mean(f1)) if f1 else None,
        'mean_comp': float(np.mean(comp)) if comp else None,
        'mean_f1_all': float(np.sum(f1) / n_gt) if n_gt else None,
    }


def table(eval_set: EvalSet, out: Path, variants: list[str], markdown: bool = False,
          scenes: str | None = None) -> str:
    """Pooled table, one row per variant with results (partial sets say how many scenes they cover);
    `scenes` (e.g. '0-3') restricts it to those rooms, to compare variants on the same rooms."""
    def fmt(v, spec):
        return '-' if v is None else format(v, spec)
    names = {name for name, _, _ in _select(eval_set.scenes(), scenes)}
    rows = []
    for variant in variants:
        files = sorted((out / 'results' / variant).glob(f'{eval_set.name}-*.json'))
        files = [f for f in files if f.stem in names]
        if not files:
            continue
        s = pool([json.loads(f.read_text()) for f in files])
        rows.append((variant, s))
    head = ['variant', 'scenes', 'timed out', 'objects', 'recall %', 'FP/scene', 'median centre cm', 'mean CD cm', 'mean F1@5cm',
            'F1 (misses = 0)']
    lines = []
    for variant, s in rows:
        lines.append([variant, str(s['scenes']), str(s['timed_out']), str(s['objects']), fmt(s['recall'], '.1f'), fmt(s['fp_per_scene'], '.2f'),
                      fmt(s['median_centre_cm'], '.1f'), fmt(s['mean_cd_cm'], '.2f'), fmt(s['mean_f1'], '.1f'),
                      fmt(s['mean_f1_all'], '.1f')])
    if markdown:
        return '\n'.join(['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
                         + ['| ' + ' | '.join(r) + ' |' for r in lines])
    widths = [max(len(h), *(len(r[i]) for r in lines)) if lines else len(h) for i, h in enumerate(head)]
    return '\n'.join('  '.join(c.rjust(w) for c, w in zip(r, widths)) for r in [head, *lines])


def family_table(eval_set: EvalSet, out: Path, variant: str) -> str:
    """Recall, mean F1@5cm and CD of one variant's results split by class and by family kind: training, extra
    (the broader prior's, unseen by the default one) or held-out (the room's objects are recomposed from the
    seeds; nothing is rendered)."""
    from frodo_datasets.scene import SCENE_LAYOUT, compose_scene
    from frodo_datasets.shapes import eval_families, extra_families

    groups: dict[tuple[str, str], list] = {}
    for scene, seed, n in eval_set.scenes():
        path = out / 'results' / variant / f'{scene}.json'
        if not path.is_file():
            continue
        pairs = {p['gt_id']: p for p in json.loads(path.read_text())['pairs']}
        config = scene_config(eval_set, seed, n, variant)
        room = compose_scene(config.objects, config.classes, seed=config.seed, family_set=config.family_set,
                             layout=SCENE_LAYOUT.get(config.scene, config.scene))
        for o in room.objects:
            kind = ('held-out' if o.family in eval_families(o.class_name)
                    else 'extra' if o.family in extra_families(o.class_name) else 'training')
            groups.setdefault((o.class_name, kind), []).append(pairs.get(o.id))
    lines = ['| class | families | objects | recall % | mean F1@5cm | mean CD cm |', '|---|---|---|---|---|---|']
    for (class_name, kind), found in sorted(groups.items()):
        matched = [p for p in found if p is not None]
        f1 = f'{np.mean([p["f1"] for p in matched]):.1f}' if matched else '-'
        cd = f'{np.mean([p["cd_cm"] for p in matched]):.2f}' if matched else '-'
        lines.append(f'| {class_name} | {kind} | {len(found)} | {100 * len(matched) / len(found):.1f} | {f1} | {cd} |')
    return '\n'.join(lines)


def stats_table(eval_set: EvalSet, out: Path, variants: list[str], scenes: str | None = None) -> str:
    """Markdown table of `capture_stats.pool_statistics` over the set's built bags, one row per variant
    (`<set> <variant>`; variants without bags are left out)."""
    from frodo_datasets import capture_stats

    rows = []
    for variant in variants:
        bags = [bag_path(out, variant, scene) for scene, _, _ in _select(eval_set.scenes(), scenes)]
        bags = [b for b in bags if b.is_file()]
        if bags:
            pooled = capture_stats.pool_statistics([capture_stats.bag_statistics(b) for b in bags])
            rows.append(capture_stats.markdown_row(f'`{eval_set.name}` {variant}', pooled))
    return '\n'.join(capture_stats.table_header() + rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m frodo_datasets.eval_sets', description=__doc__.splitlines()[0])
    parser.add_argument('command', choices=('build', 'run', 'table', 'families', 'stats', 'list'))
    parser.add_argument('set', choices=tuple(SETS))
    parser.add_argument('out', type=Path, nargs='?', default=Path('out/eval_sets'))
    parser.add_argument('--variants', default='full', help=f'comma-separated, from: {", ".join(VARIANTS)} (or "all")')
    parser.add_argument('--scenes', default=None, help="room indices, e.g. '0-3,7' (default: all)")
    parser.add_argument('--runner', choices=RUNNERS, default='reconstruct',
                        help='run: reconstruct (`frodo reconstruct`, offline, deterministic, about twice as fast; '
                             'default) or run (`frodo run`, the live graph)')
    parser.add_argument('--rate', type=float, default=1.0, help='--runner run: playback rate of frodo run (default 1; '
                        '0 drops frames on a loaded machine)')
    parser.add_argument('--params', action='append', default=[], help='parameter YAML or preset (repeatable)')
    parser.add_argument('--timeout', type=float, default=300.0,
                        help='--runner run: frodo run --timeout, seconds to wait for the graph after the bag '
                             '(default 300)')
    parser.add_argument('--code', type=Path, default=None,
                        help='source tree to run the method from (e.g. `git archive HEAD src | tar -x -C DIR`)')
    parser.add_argument('--markdown', action='store_true', help='table as Markdown')
    args = parser.parse_args(argv)
    eval_set = SETS[args.set]
    variants = list(VARIANTS) if args.variants == 'all' else [v.strip() for v in args.variants.split(',') if v.strip()]
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown:
        parser.error(f'unknown variants {unknown}; known: {", ".join(VARIANTS)}')
    if args.command == 'list':
        for scene, seed, n in eval_set.scenes():
            print(f'{scene}: seed {seed}, {n} objects, families {eval_set.family_set}, preset {eval_set.preset}')
        print(f'purpose: {eval_set.purpose}')
    elif args.command == 'build':
        build(eval_set, args.out, variants, args.scenes)
    elif args.command == 'run':
        run(eval_set, args.out, variants, args.scenes, args.rate, args.params, args.timeout, args.code, args.runner)
    elif args.command == 'stats':
        print(stats_table(eval_set, args.out, variants, args.scenes))
    elif args.command == 'families':
        for variant in variants:
            print(f'{variant}:\n{family_table(eval_set, args.out, variant)}')
    else:
        print(table(eval_set, args.out, variants, args.markdown, args.scenes))
    return 0


if __name__ == '__main__':
    sys.exit(main())
