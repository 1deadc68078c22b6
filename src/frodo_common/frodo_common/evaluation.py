"""The CONTRACT.md evaluation protocol (used by `frodo eval` and the acceptance tests).

1. Predicted and ground-truth objects of the same class are matched one-to-one by the Hungarian method on
   the distance between mesh centroids (area-weighted surface centroids); a pair farther apart than
   `gate` (0.5 m) is no match.
2. Per matched pair `n_samples` (10,000) points are sampled uniformly on each surface (seeded).
3. Accuracy distance = mean distance from predicted samples to the nearest ground-truth sample; completion
   distance = the reverse; CD (cm) = (accuracy + completion) / 2 * 100.
4. ACC@5cm = % of predicted samples within `threshold` (5 cm) of the ground-truth samples, COMP@5cm = % of
   ground-truth samples within 5 cm of the predicted ones, F1@5cm = their harmonic mean.
5. Per object, per class and overall (means over matched pairs); recall = matched / ground-truth objects;
   unmatched predictions are false positives. Unmatched ground truth does not enter the distance means.

Inputs are lists of `EvalObject(id, class_name, mesh in the world frame)`; loaders read a `frodo run --out`
directory (`objects.json` + `meshes/<id>_<class>.ply`), a bag's `/ground_truth/objects`, or a folder of
meshes named `<id>_<class>.<ext>`.
"""
from __future__ import annotations

import json
import os
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import trimesh
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

MATCH_GATE_M = 0.5
N_SAMPLES = 10_000
THRESHOLD_M = 0.05
MESH_SUFFIXES = ('.ply', '.obj', '.off', '.stl', '.glb')


class EvaluationError(ValueError):
    """Predictions or ground truth cannot be loaded."""


@dataclass
class EvalObject:
    """One object to evaluate: id, class name, triangle mesh in the world frame."""

    id: int
    class_name: str
    mesh: trimesh.Trimesh

    @property
    def centroid(self) -> np.ndarray:
        """Area-weighted surface centroid (3,)."""
        return np.asarray(self.mesh.centroid, dtype=np.float64)


@dataclass
class PairMetrics:
    """Scores of one matched (prediction, ground truth) pair; distances in metres except cd_cm, scores in %."""

    pred_id: int
    gt_id: int
    class_name: str
    centroid_distance_m: float
    accuracy_m: float
    completion_m: float
    cd_cm: float
    acc: float
    comp: float
    f1: float


@dataclass
class Summary:
    """Aggregate over a class or over everything: counts, recall (%), false positives, and the means of
    the pair metrics over matched pairs (None when nothing matched)."""

    n_gt: int
    n_pred: int
    n_matched: int
    recall: float
    false_positives: int
    cd_cm: float | None
    accuracy_m: float | None
    completion_m: float | None
    acc: float | None
    comp: float | None
    f1: float | None


@dataclass
class EvaluationResult:
    """Everything the protocol reports."""

    pairs: list[PairMetrics]
    per_class: dict[str, Summary]
    overall: Summary
    unmatched_gt: list[int]
    unmatched_pred: list[int]
    settings: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """JSON-ready dict."""
        return {'settings': self.settings, 'overall': asdict(self.overall),
                'per_class': {k: asdict(v) for k, v in self.per_class.items()},
                'pairs': [asdict(p) for p in self.pairs],
                'unmatched_gt': self.unmatched_gt, 'unmatched_pred': self.unmatched_pred}

    def table(self) -> str:
        """Readable plain-text report: one row per matched pair, per class and overall."""
        def num(v, fmt):
            return '-' if v is None else format(v, fmt)
        head = f'{"pred":>5} {"gt":>5}  {"class":<14} {"dist m":>7} {"CD cm":>7} {"ACC%":>6} {"COMP%":>6} {"F1%":>6}'
        lines = [head, '-' * len(head)]
        for p in self.pairs:
            lines.append(f'{p.pred_id:>5} {p.gt_id:>5}  {p.class_name[:14]:<14} {p.centroid_distance_m:>7.3f} '
                         f'{p.cd_cm:>7.2f} {p.acc:>6.1f} {p.comp:>6.1f} {p.f1:>6.1f}')
        if not self.pairs:
            lines.append('(no matched pairs)')
        lines.append('')
        head = (f'{"class":<14} {"GT":>4} {"pred":>5} {"match":>5} {"recall%":>8} {"FP":>4} '
                f'{"CD cm":>7} {"ACC%":>6} {"COMP%":>6} {"F1%":>6}')
        lines += [head, '-' * len(head)]
        for name, s in [*sorted(self.per_class.items()), ('overall', self.overall)]:
            lines.append(f'{name[:14]:<14} {s.n_gt:>4} {s.n_pred:>5} {s.n_matched:>5} {s.recall:>8.1f} '
                         f'{s.false_positives:>4} {num(s.cd_cm, "7.2f"):>7} {num(s.acc, "6.1f"):>6} '
                         f'{num(s.comp, "6.1f"):>6} {num(s.f1, "6.1f"):>6}')
        if self.unmatched_gt:
            lines.append(f'missed ground truth ids: {self.unmatched_gt}')
        if self.unmatched_pred:
            lines.append(f'false positive prediction ids: {self.unmatched_pred}')
        return '\n'.join(lines)


# ---------------------------------------------------------------- metrics
def sample_surface(mesh: trimesh.Trimesh, n: int = N_SAMPLES, seed: int = 0) -> np.ndarray:
    """`n` points (n, 3) uniformly distributed over the surface area of `mesh` (deterministic per seed)."""
    if len(mesh.faces) == 0 or mesh.area <= 0:
        raise EvaluationError('cannot sample an empty mesh')
    points, _ = trimesh.sample.sample_surface(mesh, int(n), seed=int(seed))
    return np.asarray(points, dtype=np.float64)


def point_metrics(pred_points: np.ndarray, gt_points: np.ndarray,
                  threshold: float = THRESHOLD_M) -> tuple[float, float, float, float, float, float]:
    """(accuracy m, completion m, CD cm, ACC %, COMP %, F1 %) of two point sets (N, 3), (M, 3)."""
    d_acc, _ = cKDTree(gt_points).query(pred_points)
    d_comp, _ = cKDTree(pred_points).query(gt_points)
    accuracy, completion = float(d_acc.mean()), float(d_comp.mean())
    acc = 100.0 * float(np.mean(d_acc <= threshold))
    comp = 100.0 * float(np.mean(d_comp <= threshold))
    f1 = 2 * acc * comp / (acc + comp) if acc + comp > 0 else 0.0
    return accuracy, completion, 100.0 * (accuracy + completion) / 2, acc, comp, f1


def match(pred: Sequence[EvalObject], gt: Sequence[EvalObject], gate: float = MATCH_GATE_M) -> list[tuple[int, int]]:
    """One-to-one matches (index into pred, index into gt): Hungarian on centroid distance within each class,
    pairs farther than `gate` metres dropped. Infeasible pairs cost more than all feasible ones together, so
    the number of matches is maximised first and the total distance second."""
    out: list[tuple[int, int]] = []
    for name in sorted({o.class_name for o in pred} & {o.class_name for o in gt}):
        pi = [i for i, o in enumerate(pred) if o.class_name == name]
        gi = [j for j, o in enumerate(gt) if o.class_name == name]
        cost = np.linalg.norm(np.array([pred[i].centroid for i in pi])[:, None, :]
                              - np.array([gt[j].centroid for j in gi])[None, :, :], axis=2)
        feasible = cost <= gate
        big = gate * (min(len(pi), len(gi)) + 1) + 1.0
        rows, cols = linear_sum_assignment(np.where(feasible, cost, big))
        out += [(pi[r], gi[c]) for r, c in zip(rows, cols) if feasible[r, c]]
    return sorted(out)


def _summary(pairs: list[PairMetrics], n_gt: int, n_pred: int) -> Summary:
    def mean(attr: str) -> float | None:
        return float(np.mean([getattr(p, attr) for p in pairs])) if pairs else None
    return Summary(n_gt=n_gt, n_pred=n_pred, n_matched=len(pairs),
                   recall=100.0 * len(pairs) / n_gt if n_gt else 0.0, false_positives=n_pred - len(pairs),
                   cd_cm=mean('cd_cm'), accuracy_m=mean('accuracy_m'), completion_m=mean('completion_m'),
                   acc=mean('acc'), comp=mean('comp'), f1=mean('f1'))


def evaluate(pred: Sequence[EvalObject], gt: Sequence[EvalObject], n_samples: int = N_SAMPLES,
             threshold: float = THRESHOLD_M, gate: float = MATCH_GATE_M, seed: int = 0) -> EvaluationResult:
    """Run the protocol on predicted and ground-truth objects (world-frame meshes)."""
    for objs, what in ((pred, 'prediction'), (gt, 'ground truth')):
        ids = [o.id for o in objs]
        if len(set(ids)) != len(ids):
            raise EvaluationError(f'{what} object ids are not unique: {sorted(ids)}')
    pairs = []
    for i, j in match(pred, gt, gate):
        p, g = pred[i], gt[j]
        metrics = point_metrics(sample_surface(p.mesh, n_samples, seed), sample_surface(g.mesh, n_samples, seed),
                                threshold)
        pairs.append(PairMetrics(p.id, g.id, g.class_name, float(np.linalg.norm(p.centroid - g.centroid)), *metrics))
    pairs.sort(key=lambda p: (p.class_name, p.gt_id))
    classes = sorted({o.class_name for o in gt} | {o.class_name for o in pred})
    per_class = {c: _summary([p for p in pairs if p.class_name == c], sum(o.class_name == c for o in gt),
                             sum(o.class_name == c for o in pred)) for c in classes}
    matched_pred, matched_gt = {p.pred_id for p in pairs}, {p.gt_id for p in pairs}
    return EvaluationResult(
        pairs=pairs, per_class=per_class, overall=_summary(pairs, len(gt), len(pred)),
        unmatched_gt=sorted(o.id for o in gt if o.id not in matched_gt),
        unmatched_pred=sorted(o.id for o in pred if o.id not in matched_pred),
        settings={'n_samples': n_samples, 'threshold_m': threshold, 'gate_m': gate, 'seed': seed})


# ---------------------------------------------------------------- loaders
def load_mesh(path: str | os.PathLike) -> trimesh.Trimesh:
    """A triangle mesh from a file (scenes are concatenated); raises EvaluationError when unreadable or empty."""
    try:
        mesh = trimesh.load(str(path), force='mesh', process=False)
    except Exception as err:  # noqa: BLE001 - trimesh raises many types for broken files
        raise EvaluationError(f'cannot read mesh {path}: {err}') from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise EvaluationError(f'mesh {path} has no triangles')
    return mesh


def load_predictions(out_dir: str | os.PathLike) -> list[EvalObject]:
    """Objects of a `frodo run --out DIR` directory: `DIR/objects.json` records (`id`, `class`, `mesh` path
    relative to DIR; without `mesh`, `meshes/<id>_<class>.ply` is tried). Records without a mesh file are
    skipped (they cannot be scored); a missing `objects.json` raises EvaluationError."""
    out_dir = Path(out_dir)
    path = out_dir / 'objects.json'
    if not path.is_file():
        raise EvaluationError(f'{path} not found (expected the output directory of `frodo run --out`)')
    try:
        doc = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise EvaluationError(f'{path} is not valid JSON: {err}') from None
    records = doc['objects'] if isinstance(doc, dict) and 'objects' in doc else doc
    if isinstance(records, dict):  # {id: record}
        records = [{'id': int(k), **v} for k, v in records.items()]
    objects = []
    for r in records:
        object_id, class_name = int(r['id']), str(r['class'])
        rel = r.get('mesh') or f'meshes/{object_id}_{_file_class(class_name)}.ply'
        mesh_path = out_dir / rel
        if not mesh_path.is_file():
            continue
        objects.append(EvalObject(object_id, class_name, load_mesh(mesh_path)))
    return objects


def _file_class(class_name: str) -> str:
    return re.sub(r'[^A-Za-z0-9]+', '_', class_name).strip('_')


def load_mesh_folder(folder: str | os.PathLike) -> list[EvalObject]:
    """Meshes named `<id>_<class>.<ext>` (class words joined by `_`, e.g. `3_dining_table.ply`)."""
    objects = []
    for path in sorted(Path(folder).iterdir()):
        m = re.fullmatch(r'(\d+)_(.+)', path.stem)
        if path.suffix.lower() in MESH_SUFFIXES and m:
            objects.append(EvalObject(int(m.group(1)), m.group(2).replace('_', ' '), load_mesh(path)))
    if not objects:
        raise EvaluationError(f'no meshes named <id>_<class>.<ext> ({", ".join(MESH_SUFFIXES)}) in {folder}')
    return objects


def load_ground_truth_bag(path: str | os.PathLike, topic: str = '/ground_truth/objects') -> list[EvalObject]:
    """Ground truth from a bag's MarkerArray topic: TRIANGLE_LIST markers, ns = class, id = object id,
    ADD/DELETE/DELETEALL applied in order over all messages."""
    from visualization_msgs.msg import Marker

    from frodo_common.bag import BagReader
    from frodo_common.conversions import marker_to_mesh

    markers: dict[int, Marker] = {}
    for message in BagReader(path).messages([topic]):
        for marker in message.decode().markers:
            if marker.action == Marker.DELETEALL:
                markers.clear()
            elif marker.action == Marker.DELETE:
                markers.pop(marker.id, None)
            elif marker.type == Marker.TRIANGLE_LIST:
                markers[marker.id] = marker
    if not markers:
        raise EvaluationError(f'{path} has no TRIANGLE_LIST markers on {topic}')
    objects = []
    for object_id, marker in sorted(markers.items()):
        vertices, faces = marker_to_mesh(marker)
        mesh = trimesh.Trimesh(vertices, faces, process=False)
        mesh.merge_vertices()
        objects.append(EvalObject(int(object_id), marker.ns, mesh))
    return objects


def load_ground_truth(path: str | os.PathLike) -> list[EvalObject]:
    """Ground truth from a bag (`.mcap`), an output-style directory (`objects.json`), or a mesh folder."""
    path = Path(path)
    if path.is_file():
        return load_ground_truth_bag(path)
    if (path / 'objects.json').is_file():
        return load_predictions(path)
    if path.is_dir():
        return load_mesh_folder(path / 'meshes' if (path / 'meshes').is_dir() else path)
    raise EvaluationError(f'ground truth {path} not found (a .mcap bag, or a folder of <id>_<class>.ply meshes)')
