"""`frodo report`: every evaluation set through the offline pipeline, one generated results page.

    frodo report                                  # all sets -> docs/results.md (+ docs/results/*.png)
    frodo report --sets demo,heldout-walks        # some sets; the page keeps only what was asked
    frodo report --limit 2                        # at most 2 bags per set (a quick look)

Each bag is reconstructed with `frodo_bringup.pipeline.reconstruct` (what `frodo reconstruct` runs) and scored
with the contract protocol (`frodo_common.evaluation`). Results go to WORK/<commit>/results/<set>/<scene>.json,
so an interrupted report resumes where it stopped and a second report on the same commit only re-renders;
uncommitted changes to tracked files get their own key (`<commit>-dirty-<hash of the diff>`). `commit=KEY`
(`frodo report --commit KEY`) renders or resumes the results stored under another key, e.g. after a commit
that changed only documents. The page states the command, the commit the results were computed at, the machine
and its load, so a figure can be traced and regenerated.

The sets (`REPORT_SETS`):
- `demo`: the two bundled bags (`bags/demo_walk.mcap`, `bags/demo_orbit.mcap`), training shape families;
- `heldout-walks`: synthetic room walks (`frodo synth --scene walk --families heldout`, 4 objects, seeds
  7301-7304) of shape families no prior was trained on;
- `realcapture`: the held-out real-capture set (`frodo_datasets.eval_sets`, `realcapture`, variant `full`:
  12 rooms, 35 keyframes of a hand-held path with every real-capture condition);
- `realwalk`: the held-out inside-out walks (`frodo_datasets.eval_sets`, `realwalk`, variant `full`: 12 rooms,
  35 keyframes of a walk through the middle of a room looking outwards, held-out designs; issue 27);
- `realwalk-depth`: the same walks with a registered depth image (variant `depth`);
- `public-real`: bags built from public real furniture models and real camera paths
  (`scripts/build_real_bags.sh` -> `data/real/build/*.mcap`); left out, with the build command on the page,
  when they have not been built.
"""
from __future__ import annotations

import hashlib
import json
import os
import platform
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from frodo_common.host import cpu_model, git_commit, memory_gb

DEFAULT_PAGE = Path('docs/results.md')
DEFAULT_WORK = Path('out/report')
HELDOUT_WALK_SEEDS = (7301, 7302, 7303, 7304)
PUBLIC_REAL_DIR = Path('data/real/build')


@dataclass(frozen=True)
class ReportSet:
    """A named group of bags with ground truth: `bags(work_dir)` returns them, building what is missing;
    an empty list means the set is not available here, and `missing` says how to make it."""

    name: str
    title: str
    description: str
    bags: Callable[[Path], list[Path]]
    missing: str = ''


def _demo_bags(_: Path) -> list[Path]:
    return [p for p in (Path('bags/demo_walk.mcap'), Path('bags/demo_orbit.mcap')) if p.is_file()]


def _heldout_walks(work: Path) -> list[Path]:
    from frodo_datasets.synth import SynthConfig, synthesize
    paths = []
    for seed in HELDOUT_WALK_SEEDS:
        path = work / 'bags' / 'heldout-walks' / f'walk-{seed}.mcap'
        if not path.is_file():
            path.parent.mkdir(parents=True, exist_ok=True)
            partial = path.with_name(path.stem + '.partial.mcap')
            synthesize(SynthConfig(scene='walk', objects=4, seed=seed, family_set='heldout'), partial)
            partial.with_name(partial.name.replace('.mcap', '.gt.json')).rename(path.with_suffix('.gt.json'))
            partial.rename(path)
        paths.append(path)
    return paths


def _realcapture(work: Path) -> list[Path]:
    from frodo_datasets import eval_sets
    return eval_sets.build(eval_sets.SETS['realcapture'], work / 'realcapture', ['full'])


def _realwalk(work: Path, variant: str = 'full') -> list[Path]:
    from frodo_datasets import eval_sets
    return eval_sets.build(eval_sets.SETS['realwalk'], work / 'realwalk', [variant])


def _public_real(_: Path) -> list[Path]:
    # the bags of scripts/build_real_bags.sh (aws_<scene>_fr1xyz_<views>.mcap); the TUM real-frame bags of
    # scripts/build_tum_bags.sh share the folder and are measured by `frodo_datasets.annotate measure`
    return sorted(PUBLIC_REAL_DIR.glob('aws_*.mcap'))


REPORT_SETS: dict[str, ReportSet] = {s.name: s for s in (
    ReportSet('demo', 'Demo bags', 'The two bundled bags (`bags/`): a room walk past 4 objects and an orbit '
              'around one, shape families the prior was trained on, exact masks and poses.', _demo_bags,
              missing='the bundled bags are missing from bags/ (see bags/README.md)'),
    ReportSet('heldout-walks', 'Synthetic walks, held-out designs',
              'Synthetic room walks (`frodo synth --scene walk --families heldout --objects 4`, seeds '
              f'{HELDOUT_WALK_SEEDS[0]}-{HELDOUT_WALK_SEEDS[-1]}): chair and table designs no prior was trained '
              'on, 60 frames, light mask and pose noise.', _heldout_walks),
    ReportSet('realcapture', 'Real-capture conditions, held out',
              'The held-out real-capture set (`python -m frodo_datasets.eval_sets build realcapture`, variant '
              '`full`): 12 synthetic rooms, 35 keyframes of a hand-held path with motion blur, exposure, sensor '
              'noise, detector-like masks, pose drift, sparse textured landmarks, tucked chairs and clutter.',
              _realcapture),
    ReportSet('realwalk', 'Inside-out walks, held out',
              'The held-out inside-out walks (`python -m frodo_datasets.eval_sets build realwalk`, variant `full`): '
              '12 synthetic rooms with furniture along the walls, 35 keyframes of a walk through the middle looking '
              'outwards (rotation-dominated, narrow baseline: each object seen from one side in a few keyframes), '
              'chairs behind tables, held-out designs, and the real-capture conditions of `realcapture`.',
              _realwalk),
    ReportSet('realwalk-depth', 'Inside-out walks with depth, held out',
              'The same held-out walks with a registered Kinect-like depth image (variant `depth`), as RGB-D '
              'captures (ScanNet, Redwood, TUM) have: the same rooms and keyframes, other draws of the noise.',
              lambda work: _realwalk(work, 'depth')),
    ReportSet('public-real', 'Public real furniture on real camera paths',
              'Real furniture models in their real arrangement rendered along a real hand-held trajectory '
              '(TUM fr1/xyz); provenance in data/real/README.md.', _public_real,
              missing='not built here: run `scripts/build_real_bags.sh` (clones two public repositories) and '
                      'report again'),
)}


def commit_key(repo: Path = Path('.')) -> str:
    """Short commit of the checkout; with uncommitted changes to tracked files `<commit>-dirty-<hash of the
    diff>`, so the same edits reuse their results and other edits do not; 'unknown' outside git."""
    head = git_commit(repo)
    if not head:
        return 'unknown'
    try:
        diff = subprocess.run(['git', 'diff', 'HEAD'], cwd=repo, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return 'unknown'
    return f'{head}-dirty-{hashlib.sha1(diff).hexdigest()[:8]}' if diff else head


def machine() -> dict:
    """What the figures were measured on: CPU model, cores, memory, torch and its threads, GPU."""
    import torch
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else 'none'
    return {'cpu': cpu_model(), 'cores': os.cpu_count(), 'memory_gb': round(memory_gb(), 1),
            'python': platform.python_version(), 'torch': torch.__version__, 'torch_threads': torch.get_num_threads(),
            'gpu': gpu}


def run_bag(bag: Path, out_dir: Path, params: Sequence[str | os.PathLike]) -> dict:
    """Reconstruct one bag, write its outputs and picture under out_dir, score it; the result dict (contract
    scores + 'run': wall seconds, phase seconds, objects per final stage, machine load)."""
    from frodo_bringup.pipeline import PipelineConfig, reconstruct
    from frodo_bringup.result_figure import draw_result
    from frodo_common.evaluation import evaluate, load_ground_truth, load_predictions

    load_before = os.getloadavg()[0]
    started = time.perf_counter()
    result = reconstruct(bag, PipelineConfig.from_params_files(params))
    seconds = time.perf_counter() - started
    result.write(out_dir)
    pred, gt = load_predictions(out_dir), load_ground_truth(bag)
    report = evaluate(pred, gt)
    draw_result(pred, gt, report, out_dir / 'result.png', title=bag.name)
    scores = report.to_dict()
    stages: dict[str, int] = {}
    for estimate in result.estimates.values():
        stages[estimate.stage] = stages.get(estimate.stage, 0) + 1
    scores['run'] = {'bag': str(bag), 'seconds': seconds, 'phases': result.seconds, 'frames': result.frames,
                     'stages': stages, 'load_before': load_before, 'load_after': os.getloadavg()[0],
                     'problems': len(result.problems), 'machine': machine()}
    return scores


def collect(report_set: ReportSet, work: Path, params: Sequence[str | os.PathLike], limit: int | None,
            log: Callable[[str], None]) -> list[tuple[str, dict]]:
    """(scene, result) of every bag of the set, running those without a stored result."""
    bags = report_set.bags(work)
    if limit is not None:
        bags = bags[:limit]
    results = []
    for i, bag in enumerate(bags):
        scene = bag.stem
        stored = work / 'results' / report_set.name / f'{scene}.json'
        if stored.is_file():
            log(f'{report_set.name} [{i + 1}/{len(bags)}] {scene}: stored result reused')
        else:
            log(f'{report_set.name} [{i + 1}/{len(bags)}] {scene}: reconstructing ...')
            try:
                result = run_bag(bag, work / 'runs' / report_set.name / scene, params)
            except Exception as err:  # noqa: BLE001 - one failing bag is reported on the page, the rest still run
                log(f'{report_set.name} {scene}: failed: {type(err).__name__}: {err}')
                result = {'error': f'{type(err).__name__}: {err}', 'run': {'bag': str(bag)}}
            stored.parent.mkdir(parents=True, exist_ok=True)
            stored.write_text(json.dumps(result, indent=1) + '\n')
            log(f'{report_set.name} {scene}: {summary_line(result)}')
        results.append((scene, json.loads(stored.read_text())))
    return results


def summary_line(result: dict) -> str:
    if 'error' in result:
        return f'error: {result["error"]}'
    o = result['overall']
    return (f'{o["n_matched"]}/{o["n_gt"]} found, {o["false_positives"]} FP, CD {_num(o["cd_cm"], ".2f")} cm, '
            f'F1@5cm {_num(o["f1"], ".1f")}, {result["run"]["seconds"]:.0f} s')


def _num(value, spec: str) -> str:
    return '-' if value is None or (isinstance(value, float) and not np.isfinite(value)) else format(value, spec)


def _stages(stages: dict[str, int]) -> str:
    return ', '.join(f'{n} {stage}' for stage, n in sorted(stages.items())) or '-'


def set_section(report_set: ReportSet, results: list[tuple[str, dict]], picture: str | None) -> list[str]:
    """Markdown of one set: what it is, one row per bag, the pooled row, a picture."""
    from frodo_datasets.eval_sets import pool
    lines = [f'## {report_set.title} (`{report_set.name}`)', '', report_set.description, '']
    if not results:
        return lines + [f'No bags: {report_set.missing or "the set gave no bags"}.', '']
    head = ['bag', 'objects', 'found', 'FP', 'median centre cm', 'mean CD cm', 'mean F1@5cm', 'mean COMP@5cm',
            'final stages', 'seconds', 'load']
    lines += ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    scored = []
    for scene, r in results:
        if 'error' in r:
            lines.append(f'| {scene} | - | - | - | - | - | - | - | failed: {r["error"][:80]} | - | - |')
            continue
        scored.append(r)
        s = pool([r])
        run = r['run']
        lines.append(f'| {scene} | {s["objects"]} | {s["found"]} | {r["overall"]["false_positives"]} | '
                     f'{_num(s["median_centre_cm"], ".1f")} | {_num(s["mean_cd_cm"], ".2f")} | '
                     f'{_num(s["mean_f1"], ".1f")} | {_num(s["mean_comp"], ".1f")} | {_stages(run["stages"])} | '
                     f'{run["seconds"]:.0f} | '
                     f'{run["load_before"]:.1f} |')
    if scored:
        s = pool(scored)
        seconds = sum(r['run']['seconds'] for r in scored)
        stages: dict[str, int] = {}
        for r in scored:
            for stage, n in r['run']['stages'].items():
                stages[stage] = stages.get(stage, 0) + n
        lines.append(f'| **all {s["scenes"]}** | {s["objects"]} | {s["found"]} ({s["recall"]:.1f} %) | '
                     f'{s["fp_per_scene"]:.2f}/bag | {_num(s["median_centre_cm"], ".1f")} | '
                     f'{_num(s["mean_cd_cm"], ".2f")} | {_num(s["mean_f1"], ".1f")} | {_num(s["mean_comp"], ".1f")} | '
                     f'{_stages(stages)} | '
                     f'{seconds:.0f} | |')
    lines.append('')
    if picture:
        lines += [f'![{report_set.name}: {results[0][0]}]({picture})', '',
                  f'*{results[0][0]}: reconstruction (colour) against ground truth (grey), top and front views.*', '']
    return lines


def summary_rows(sections: list[tuple[ReportSet, list[tuple[str, dict]]]]) -> list[str]:
    """One row per set: recall, FP per bag, median centre error, mean CD and F1 of matched objects."""
    from frodo_datasets.eval_sets import pool
    head = ['set', 'bags', 'objects', 'recall %', 'FP/bag', 'median centre cm', 'mean CD cm', 'mean F1@5cm',
            'mean COMP@5cm', 'F1 (misses = 0)', 'seconds/bag']
    lines = ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    for report_set, results in sections:
        scored = [r for _, r in results if 'error' not in r]
        if not scored:
            lines.append(f'| {report_set.name} | 0 | - | - | - | - | - | - | - | - | - |')
            continue
        s = pool(scored)
        per_bag = sum(r['run']['seconds'] for r in scored) / len(scored)
        lines.append(f'| {report_set.name} | {s["scenes"]} | {s["objects"]} | {s["recall"]:.1f} | '
                     f'{s["fp_per_scene"]:.2f} | {_num(s["median_centre_cm"], ".1f")} | '
                     f'{_num(s["mean_cd_cm"], ".2f")} | {_num(s["mean_f1"], ".1f")} | '
                     f'{_num(s["mean_comp"], ".1f")} | {_num(s["mean_f1_all"], ".1f")} | {per_bag:.0f} |')
    return lines


def render(sections: list[tuple[ReportSet, list[tuple[str, dict]]]], pictures: dict[str, str], command: str,
           commit: str, host: dict, date: str, params: Sequence[str | os.PathLike] = (),
           checkout: str | None = None) -> str:
    """The results page."""
    parameters = ('the default parameters' if not params else
                  'the default parameters overridden by ' + ', '.join(f'`{p}`' for p in params))
    lines = ['# Results', '',
             f'Generated by `{command}` on {date} from results computed at commit `{commit}`'
             + (f' (page rendered at `{checkout}`)' if checkout and checkout != commit else '')
             + '. Do not edit by hand: run the command again.',
             '',
             f'Machine: {host["cpu"]}, {host["cores"]} cores, {host["memory_gb"]} GB, GPU: {host["gpu"]}; '
             f'Python {host["python"]}, torch {host["torch"]} ({host["torch_threads"]} threads). '
             '"load" is the machine\'s 1-minute load average when the bag started: seconds measured at a load '
             'above the core count are slower than the machine can do.', '',
             f'Each bag is reconstructed offline (`frodo reconstruct BAG --out DIR`, {parameters}) and '
             'scored with the evaluation protocol of CONTRACT.md: predicted and ground-truth objects of one class '
             'are matched one-to-one (Hungarian method on the distance between mesh centroids, no match beyond '
             '0.5 m); "centre" is that distance; CD (cm) is the mean of the two directed mean distances between '
             '10,000 surface samples of each mesh, F1@5cm the harmonic mean of accuracy and completion at 5 cm '
             '(%), COMP@5cm the completion alone (the share of the ground-truth surface within 5 cm of the '
             'estimate: low where an object\'s unseen side is wrong), all averaged over matched objects; "F1 '
             '(misses = 0)" counts every missed object as 0. "final stages" counts objects by the last optimiser '
             'stage that gave their estimate (fused < sparse < dense).', '',
             '## Summary', '', *summary_rows(sections), '']
    for report_set, results in sections:
        lines += set_section(report_set, results, pictures.get(report_set.name))
    return '\n'.join(lines).rstrip() + '\n'


def report(set_names: Sequence[str], page: Path = DEFAULT_PAGE, work: Path = DEFAULT_WORK,
           params: Sequence[str | os.PathLike] = (), limit: int | None = None,
           command: str = 'frodo report', log: Callable[[str], None] = print, commit: str | None = None) -> list[str]:
    """Run (or reuse) every named set and write the page plus one picture per set beside it; returns the bags
    that failed ('set/scene: error'), which the page lists too. commit: the key results are stored under
    (default: `commit_key()` of the checkout)."""
    unknown = [n for n in set_names if n not in REPORT_SETS]
    if unknown:
        raise ValueError(f'unknown set(s) {", ".join(unknown)}; known: {", ".join(REPORT_SETS)}')
    checkout = commit_key()
    commit = commit or checkout
    work_dir = work / (commit if commit != 'unknown' else time.strftime('unknown-%Y%m%dT%H%M%S'))
    figures = page.parent / page.stem
    sections, pictures = [], {}
    for name in set_names:
        report_set = REPORT_SETS[name]
        results = collect(report_set, work_dir, params, limit, log)
        sections.append((report_set, results))
        first = next((scene for scene, r in results if 'error' not in r), None)
        source = work_dir / 'runs' / name / first / 'result.png' if first else None
        if source is not None and source.is_file():
            figures.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source, figures / f'{name}.png')
            pictures[name] = f'{figures.name}/{name}.png'
    page.parent.mkdir(parents=True, exist_ok=True)
    measured_on = [r['run']['machine'] for _, results in sections for _, r in results if 'machine' in r.get('run', {})]
    page.write_text(render(sections, pictures, command, commit, measured_on[0] if measured_on else machine(),
                           time.strftime('%Y-%m-%d'), params, checkout))
    log(f'wrote {page} (results under {work_dir})')
    return [f'{s.name}/{scene}: {r["error"]}' for s, results in sections for scene, r in results if 'error' in r]
