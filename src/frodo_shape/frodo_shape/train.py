"""Training of the joint shape embedding (paper Sec. 4, Eq. 1) and of the image encoder (Sec. 5.2).

Stage 1, auto-decoder (DeepSDF-style, codes are free parameters in an `nn.Embedding`):
    L = λ1 · CD(Gs(z), X_gt) + λ2 · |clamp(Gd(z, x), δ) − clamp(d_gt, δ)| + ||z||² / σ²,  δ = 0.1,
with Adam (separate learning rates for the networks and the codes, step decay).
Stage 2, encoder: a ResNet-style CNN regresses the learnt codes from renders of the training shapes with
random viewpoints, materials, lighting, backgrounds and perturbed crop boxes (Huber loss).

Both stages: YAML configs (`frodo_shape/configs/*.yaml`), deterministic seeds (every step draws from a
generator seeded by (seed, step), so a resumed run continues exactly), resumable checkpoints, tqdm
progress, loss-curve PNGs, cuda when available. Data: the procedural library of `frodo_datasets.shapes`
or the user's own meshes (`load_user_meshes`: ShapeNet layout or a plain folder).

Output folder = a prior folder (`prior.py` loads it): decoder.pt, encoder.pt, config.yaml, shapes.yaml,
loss_*.png, plus checkpoints/ and cache/ (not needed to use the prior).
"""
from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh
import yaml
from tqdm import tqdm

from frodo_shape.augment import CropAugmentation, augment_crop
from frodo_shape.models import DecoderConfig, EncoderConfig, ImageEncoder, JointDecoder
from frodo_shape.sdf_data import SamplingConfig, cached_samples

CONFIG_DIR = Path(__file__).parent / 'configs'


# ---------------------------------------------------------------- configuration and data
def load_config(path_or_name: str | Path) -> dict:
    """A YAML training config: a path, or the name of a file in frodo_shape/configs (with or without .yaml)."""
    p = Path(path_or_name)
    if not p.exists():
        cand = CONFIG_DIR / (p.name if p.suffix else p.name + '.yaml')
        if not cand.exists():
            known = sorted(f.stem for f in CONFIG_DIR.glob('*.yaml'))
            raise FileNotFoundError(f'config {path_or_name!r} not found (not a file, not one of {known})')
        p = cand
    with open(p) as f:
        return yaml.safe_load(f) or {}


def choose_device(name: str = 'auto') -> torch.device:
    """'auto' -> cuda if available else cpu; otherwise the named device."""
    if name in (None, 'auto'):
        return torch.device('cuda' if torch.cuda.is_available() else 'cpu')
    return torch.device(name)


@dataclass
class TrainingShape:
    """A training shape: normalised-frame mesh, its scale (metres per normalised unit) and provenance."""

    name: str
    class_name: str
    family: str
    scale: float
    mesh: trimesh.Trimesh
    seed: int | None = None  # procedural shapes: `frodo_datasets.shapes.generate(class_name, seed, family)`


def to_training_shapes(records) -> list[TrainingShape]:
    """`frodo_datasets.shapes.ShapeRecord`s (metric, canonical frame) as normalised `TrainingShape`s."""
    from frodo_datasets.shapes import normalise
    out = []
    for r in records:
        mesh, scale = normalise(r.mesh)
        seed = getattr(r, 'seed', None)  # user meshes carry seed -1
        out.append(TrainingShape(r.name, r.class_name, str(getattr(r, 'family', '') or ''), float(scale), mesh,
                                 None if seed is None or int(seed) < 0 else int(seed)))
    return out


def library_shapes(classes: list[str], count: int, seed: int, extra: bool = False) -> list[TrainingShape]:
    """`count` procedural shapes per class from `frodo_datasets.shapes.library` (with its extra families when
    `extra`)."""
    from frodo_datasets.shapes import library
    return to_training_shapes([r for c in classes for r in library(c, count, seed=seed, extra=extra)])


def design_shapes(classes: list[str], count: int, seed: int) -> list[TrainingShape]:
    """`count` shapes of every held-out design (`frodo_datasets.shapes.eval_families`) of each class: designs no
    prior is trained on (generator seeds drawn from `seed`)."""
    from frodo_datasets.shapes import eval_families, procedural_record
    seeds = np.random.default_rng(seed).choice(2**31, size=count, replace=False) if count else []
    return to_training_shapes([procedural_record(c, int(k), f)
                               for c in classes for f in eval_families(c) for k in seeds])


def user_shapes(root: str | Path, class_name: str | None, up_axis: str = 'y', front_axis: str = '-z',
                target_height: float | None = None) -> list[TrainingShape]:
    """The user's meshes (ShapeNet layout or a plain folder) via `frodo_datasets.shapes.load_user_meshes`.

    target_height: metres to rescale each mesh's height to (ShapeNet models are not metric); None keeps units.
    """
    from frodo_datasets.shapes import load_user_meshes
    records = load_user_meshes(root, class_name=class_name, up_axis=up_axis, front_axis=front_axis,
                               target_height=target_height)
    if not records:
        raise FileNotFoundError(f'no meshes found under {root} (expected ShapeNet <synset>/<id>/models/model_normalized.obj '
                                'or a folder of .obj/.ply/.stl/.off/.glb files)')
    return to_training_shapes(records)


def training_shapes(config: dict, meshes: str | None = None, class_name: str | None = None) -> list[TrainingShape]:
    """The shapes a decoder config trains on (`data:` section), or the user's meshes when `meshes` is given."""
    data = config.get('data', {})
    if meshes:
        return user_shapes(meshes, class_name, data.get('up_axis', 'y'), data.get('front_axis', '-z'),
                           data.get('target_height'))
    return library_shapes(list(data.get('classes', ['chair', 'dining table'])), int(data.get('shapes_per_class', 100)),
                          int(data.get('library_seed', 0)), bool(data.get('extra_families', False)))


class SampleBank:
    """SDF samples of all shapes as tensors: points (M, S, 3), sdf (M, S), surface (M, N, 3)."""

    def __init__(self, shapes: list[TrainingShape], sampling: SamplingConfig, cache_dir: Path | None,
                 progress: bool = True):
        pts, sdf, surf = [], [], []
        for i, s in enumerate(tqdm(shapes, desc='SDF samples', disable=not progress)):
            smp = cached_samples(s.mesh, sampling, cache_dir, seed=i)
            pts.append(smp.points), sdf.append(smp.sdf), surf.append(smp.surface)
        self.points = torch.from_numpy(np.stack(pts))
        self.sdf = torch.from_numpy(np.stack(sdf))
        self.surface = torch.from_numpy(np.stack(surf))

    def batch(self, idx: torch.Tensor, n_sdf: int, n_surface: int, gen: torch.Generator):
        """Random subsets for shapes idx (B,): xyz (B, n_sdf, 3), sdf (B, n_sdf), surface (B, n_surface, 3)."""
        B, S, N = len(idx), self.points.shape[1], self.surface.shape[1]
        si = torch.randint(0, S, (B, n_sdf), generator=gen)
        ni = torch.randint(0, N, (B, n_surface), generator=gen)
        rows = idx[:, None]
        return self.points[rows, si], self.sdf[rows, si], self.surface[rows, ni]


def chamfer(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Symmetric chamfer distance of paper Eq. 2 (squared distances): a (B, N, 3), b (B, M, 3) -> (B,).

    Nearest neighbours are found without autograd; the loss is then rebuilt from the matched pairs, which
    has the same value and gradient as differentiating through the min but avoids a (B, N, M) backward.
    """
    with torch.no_grad():
        d = torch.cdist(a, b)
        ia, ib = d.argmin(dim=2), d.argmin(dim=1)
    pa = torch.gather(b, 1, ia[..., None].expand(-1, -1, 3))
    pb = torch.gather(a, 1, ib[..., None].expand(-1, -1, 3))
    return (a - pa).pow(2).sum(-1).mean(1) + (b - pb).pow(2).sum(-1).mean(1)


def _step_generator(seed: int, step: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed * 1_000_003 + step)


def _save_atomic(obj, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix('.tmp')
    torch.save(obj, tmp)
    tmp.replace(path)


def _half_state(module: torch.nn.Module) -> dict:
    return {k: (v.half() if v.is_floating_point() else v).clone() for k, v in module.state_dict().items()}


def plot_losses(history: dict[str, list[float]], path: Path, title: str) -> None:
    """Loss curves (log scale) of a history {'step': [...], name: [...]} to a PNG."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 4))
    steps = np.asarray(history['step'])
    for k, v in history.items():
        if k == 'step' or not len(v):
            continue
        v = np.asarray(v, dtype=np.float64)
        w = max(1, len(v) // 50)
        smooth = np.convolve(v, np.ones(w) / w, mode='valid')
        ax.plot(steps[w - 1:], smooth, label=k)
    ax.set_yscale('log')
    ax.set_xlabel('step')
    ax.set_ylabel('loss')
    ax.set_title(title)
    ax.grid(True, which='both', alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------- stage 1: joint auto-decoder
def _training_setup(config: dict, steps: int | None, device: str | None):
    """Seed torch and set its threads from a training config; returns (config as run, its train section, seed,
    steps, device). The config as run carries a `steps` override, so the prior's config.yaml says what was run."""
    total_steps = int(steps if steps is not None else config.get('train', {}).get('steps', 3000))
    config = copy.deepcopy(config)
    tc = config.setdefault('train', {})
    tc['steps'] = total_steps
    seed = int(config.get('seed', 0))
    torch.manual_seed(seed)
    torch.set_num_threads(int(tc.get('threads', 2)))
    return config, tc, seed, total_steps, choose_device(device)


def train_decoder(config: dict, out_dir: str | Path, shapes: list[TrainingShape] | None = None,
                  resume: bool = False, steps: int | None = None, device: str = 'auto', progress: bool = True,
                  meshes: str | None = None, class_name: str | None = None) -> dict:
    """Train the joint decoder and the training codes; writes the decoder half of a prior to `out_dir`.

    shapes: training shapes (default: from the config / `meshes`). Returns {'history', 'seconds', 'steps'}.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    config, tc, seed, total_steps, dev = _training_setup(config, steps, device)
    if shapes is None:
        shapes = training_shapes(config, meshes, class_name)
    sampling = SamplingConfig.from_dict(config.get('sampling'))
    cache = out / 'cache' / 'sdf' if config.get('cache_dir') is None else Path(config['cache_dir'])
    bank = SampleBank(shapes, sampling, cache, progress)

    dcfg = DecoderConfig.from_dict(config.get('decoder'))
    decoder = JointDecoder(dcfg).to(dev)
    codes = torch.nn.Embedding(len(shapes), dcfg.code_dim).to(dev)
    torch.nn.init.normal_(codes.weight, 0.0, float(tc.get('code_init_std', 1.0)) / math.sqrt(dcfg.code_dim))
    opt = torch.optim.Adam([{'params': decoder.parameters(), 'lr': float(tc.get('lr_net', 1e-3))},
                            {'params': codes.parameters(), 'lr': float(tc.get('lr_codes', 1e-2))}])
    base_lrs = [g['lr'] for g in opt.param_groups]
    history: dict[str, list[float]] = {'step': [], 'total': [], 'sdf': [], 'chamfer': [], 'reg': []}
    start = 0
    ckpt_path = out / 'checkpoints' / 'decoder.pt'
    if resume and ckpt_path.exists():
        ck = torch.load(ckpt_path, map_location=dev, weights_only=True)
        decoder.load_state_dict(ck['decoder'])
        codes.load_state_dict(ck['codes'])
        opt.load_state_dict(ck['optim'])
        history, start = ck['history'], int(ck['step'])
    elif resume:
        print(f'--resume: no checkpoint at {ckpt_path}; starting from scratch')

    B = min(int(tc.get('shapes_per_batch', 16)), len(shapes))
    n_sdf, n_surf = int(tc.get('sdf_points_per_shape', 2048)), int(tc.get('surface_points', 2048))
    n_cd = min(B, int(tc.get('chamfer_shapes', B)))  # shapes of the batch that get the chamfer term
    delta, lam_cd, lam_sdf = float(tc.get('delta', 0.1)), float(tc.get('lambda_chamfer', 1.0)), float(tc.get('lambda_sdf', 1.0))
    code_reg = float(tc.get('code_reg', 1e-4))
    decay, decay_every = float(tc.get('lr_decay', 0.5)), int(tc.get('lr_decay_every', 1000))
    every = int(tc.get('checkpoint_every', 200))
    t0 = time.time()

    def checkpoint(step: int) -> None:
        _save_atomic({'decoder': decoder.state_dict(), 'codes': codes.state_dict(), 'optim': opt.state_dict(),
                      'step': step, 'history': history}, ckpt_path)

    bar = tqdm(range(start, total_steps), desc='decoder', disable=not progress, initial=start, total=total_steps)
    for step in bar:
        for g, lr in zip(opt.param_groups, base_lrs):
            g['lr'] = lr * decay ** (step // decay_every)
        gen = _step_generator(seed, step)
        idx = torch.randperm(len(shapes), generator=gen)[:B]
        xyz, sdf_gt, surf = (t.to(dev) for t in bank.batch(idx, n_sdf, n_surf, gen))
        z = codes(idx.to(dev))
        l_sdf = (decoder.sdf(z, xyz).clamp(-delta, delta) - sdf_gt.clamp(-delta, delta)).abs().mean()
        l_cd = chamfer(decoder.points(z[:n_cd]), surf[:n_cd]).mean() if lam_cd > 0 else torch.zeros((), device=dev)
        l_reg = z.pow(2).sum(1).mean()
        loss = lam_sdf * l_sdf + lam_cd * l_cd + code_reg * l_reg
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        for k, v in (('step', step), ('total', loss.item()), ('sdf', l_sdf.item()), ('chamfer', l_cd.item()),
                     ('reg', code_reg * l_reg.item())):
            history[k].append(v)
        bar.set_postfix(sdf=f'{l_sdf.item():.4f}', cd=f'{l_cd.item():.5f}')
        if (step + 1) % every == 0:
            checkpoint(step + 1)
    seconds = time.time() - t0
    checkpoint(total_steps)

    export_decoder(out, decoder, codes.weight.detach(), shapes, config, dcfg, sampling)
    if history['step']:
        plot_losses({k: v for k, v in history.items() if k != 'total'}, out / 'loss_decoder.png',
                    f'joint auto-decoder ({len(shapes)} shapes)')
    return {'history': history, 'seconds': seconds, 'steps': total_steps}


def export_decoder(out: Path, decoder: JointDecoder, codes: torch.Tensor, shapes: list[TrainingShape], config: dict,
                   dcfg: DecoderConfig, sampling: SamplingConfig) -> None:
    """Write decoder.pt (float16 weights, float32 training codes), config.yaml and shapes.yaml to `out`."""
    torch.save({'state_dict': _half_state(decoder), 'training_codes': codes.float().cpu().clone()}, out / 'decoder.pt')
    classes = sorted({s.class_name for s in shapes})
    meta = {'name': out.name, 'code_dim': dcfg.code_dim, 'class_names': classes, 'decoder': dcfg.to_dict(),
            'sampling': {k: (list(v) if isinstance(v, tuple) else v) for k, v in sampling.__dict__.items()},
            'decoder_training': copy.deepcopy(config)}
    old = out / 'config.yaml'
    if old.exists():  # keep an encoder section written earlier
        prev = yaml.safe_load(old.read_text()) or {}
        meta.update({k: v for k, v in prev.items() if k.startswith('encoder')})
    old.write_text(yaml.safe_dump(meta, sort_keys=False))
    (out / 'shapes.yaml').write_text(yaml.safe_dump(
        [{'name': s.name, 'class': s.class_name, 'family': s.family, 'scale': round(s.scale, 6), 'seed': s.seed}
         for s in shapes],
        sort_keys=False))


# ---------------------------------------------------------------- stage 2: encoder on renders
@dataclass
class RenderSet:
    """Context crops of rendered training views.

    images (V, S, S, 3) uint8, masks (V, S, S) bool, boxes (V, 4) float32 (x0, y0, x1, y1) object box in crop
    pixels, shape_index (V,) int64 into the training shapes.
    """

    images: np.ndarray
    masks: np.ndarray
    boxes: np.ndarray
    shape_index: np.ndarray


def _background(rng: np.random.Generator, size: int) -> np.ndarray:
    """Random background image (size, size, 3) uint8: plain, gradient or smooth noise."""
    kind = rng.integers(3)
    c1, c2 = rng.uniform(0, 1, 3), rng.uniform(0, 1, 3)
    if kind == 0:
        img = np.broadcast_to(c1, (size, size, 3))
    elif kind == 1:
        t = np.linspace(0, 1, size)[:, None, None] * np.ones((1, size, 1))
        img = c1 + t * (c2 - c1)
    else:
        low = rng.uniform(0, 1, (int(rng.integers(3, 9)),) * 2 + (3,))
        img = torch.nn.functional.interpolate(torch.from_numpy(low).permute(2, 0, 1)[None], size=(size, size),
                                              mode='bicubic', align_corners=False)[0].permute(1, 2, 0).numpy()
    return (np.clip(img, 0, 1) * 255).astype(np.uint8)


def render_scene(shape: TrainingShape, rng: np.random.Generator, render_size: int = 192,
                 distance: tuple[float, float] = (1.3, 4.5)):
    """Render one random view of `shape` at metric scale, on a random floor, before a random wall/backdrop.

    Random yaw, camera `distance` m away (default 1.3-4.5; a range starting nearer than 1.3 m is kept beyond
    1.1 x the shape's bounding radius) at height 0.9-1.9 m above the floor, focal length chosen so the object spans 60-150 px (a near
    camera thus has a wide field of view: strong perspective, as at handheld range), random materials
    (`Material.random`), light direction/intensity, ambient.
    Returns (rgb (S, S, 3) uint8, mask (S, S) bool, box (4,) x0, y0, x1, y1) or None when (almost) invisible.
    """
    from frodo_common.geometry import look_at
    from frodo_datasets.render import Light, Material, RenderObject, Renderer

    metric = shape.mesh.copy()
    metric.apply_scale(shape.scale)
    metric.apply_transform(trimesh.transformations.rotation_matrix(rng.uniform(0, 2 * np.pi), (0, 0, 1)))
    z_floor = metric.bounds[0, 2]
    radius = 0.9 * shape.scale
    objects = [RenderObject(metric, Material.random(rng), label=1)]
    if rng.uniform() < 0.85:
        floor = trimesh.creation.box((12, 12, 0.02))
        floor.apply_translation((0, 0, z_floor - 0.01))
        objects.append(RenderObject(floor, Material.random(rng), label=0))
    if rng.uniform() < 0.5:
        wall = trimesh.creation.box((0.05, 12, 6))
        wall.apply_translation((-(radius + rng.uniform(0.3, 2.0)), 0, z_floor + 3))
        wall.apply_transform(trimesh.transformations.rotation_matrix(rng.uniform(0, 2 * np.pi), (0, 0, 1)))
        objects.append(RenderObject(wall, Material.random(rng), label=0))
    # a near range keeps the camera outside the object; ranges from 1.3 m are drawn as the shipped encoder's were
    near = max(distance[0], 1.1 * radius) if distance[0] < 1.3 else distance[0]
    dist = rng.uniform(near, max(distance[1], near))
    cam_h, az = rng.uniform(0.9, 1.9), rng.uniform(0, 2 * np.pi)
    eye = np.array([dist * np.cos(az), dist * np.sin(az), z_floor + cam_h])
    target = rng.normal(scale=0.1 * radius, size=3)
    f = rng.uniform(60, 150) * np.linalg.norm(eye - target) / (2 * radius)
    c = (render_size - 1) / 2
    K = np.array([[f, 0, c], [0, f, c], [0, 0, 1.0]])
    light = Light(direction=(rng.uniform(-1, 1), rng.uniform(-1, 1), -rng.uniform(0.5, 1.5)),
                  intensity=float(rng.uniform(0.4, 0.9)))
    res = Renderer(objects).render(K, look_at(eye, target), render_size, render_size, light=light,
                                   ambient=float(rng.uniform(0.2, 0.55)), shadows=True,
                                   background=_background(rng, render_size))
    mask = res.labels == 1
    if mask.sum() < 50:
        return None
    ys, xs = np.nonzero(mask)
    return res.rgb, mask, np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], dtype=np.float64)


def render_view(shape: TrainingShape, rng: np.random.Generator, crop_size: int = 160, context: float = 1.6,
                distance: tuple[float, float] = (1.3, 4.5)):
    """`render_scene` cut to a square context window of `context` x the box's longer side, resized to crop_size.

    Returns (image (crop_size, crop_size, 3) uint8, mask (crop_size, crop_size) bool, box (4,) float32 in crop
    pixels) or None.
    """
    from frodo_shape.crops import square_crop
    scene = render_scene(shape, rng, distance=distance)
    if scene is None:
        return None
    rgb, mask, box = scene
    crop, crop_mask = square_crop(rgb, mask, box, crop_size, (context - 1) / 2)
    s = crop_size / (max(box[2] - box[0], box[3] - box[1], 2.0) * context)
    cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
    box_c = np.array([(box[0] - cx) * s, (box[1] - cy) * s, (box[2] - cx) * s, (box[3] - cy) * s]) + crop_size / 2
    return crop, crop_mask, box_c.astype(np.float32)


def render_set(shapes: list[TrainingShape], views_per_shape: int, seed: int, cache_path: Path | None = None,
               progress: bool = True, crop_size: int = 160, distance: tuple[float, float] = (1.3, 4.5)) -> RenderSet:
    """`views_per_shape` random views of every shape, cameras `distance` m away (cached as npz at `cache_path`)."""
    if cache_path is not None and cache_path.exists():
        with np.load(cache_path) as f:
            return RenderSet(f['images'], f['masks'], f['boxes'], f['shape_index'])
    imgs, masks, boxes, index = [], [], [], []
    for i, shape in enumerate(tqdm(shapes, desc='renders', disable=not progress)):
        rng = np.random.default_rng([seed, i])
        n = 0
        while n < views_per_shape:
            v = render_view(shape, rng, crop_size=crop_size, distance=distance)
            if v is None:
                continue
            imgs.append(v[0]), masks.append(v[1]), boxes.append(v[2]), index.append(i)
            n += 1
    rs = RenderSet(np.stack(imgs), np.stack(masks), np.stack(boxes), np.asarray(index, dtype=np.int64))
    if cache_path is not None:
        cache_path.parent.mkdir(parents=True, exist_ok=True)
        tmp = cache_path.with_suffix('.tmp.npz')
        np.savez(tmp, images=rs.images, masks=rs.masks, boxes=rs.boxes, shape_index=rs.shape_index)
        tmp.replace(cache_path)
    return rs


def encoder_input(crops: np.ndarray, masks: np.ndarray | None, size: int, in_channels: int) -> torch.Tensor:
    """Network input (N, in_channels, size, size) float32 from crops (N, H, W, 3) uint8 and masks (N, H, W) bool.

    RGB is scaled to [-1, 1]; the mask channel (4th) is ±1 (all +1 when `masks` is None). Non-square or
    differently sized crops are resized to `size` (crops should be square: `crops.square_crop`).
    """
    x = torch.from_numpy(np.ascontiguousarray(crops)).permute(0, 3, 1, 2).float() / 127.5 - 1.0
    if in_channels == 4:
        m = torch.ones(x.shape[0], 1, *x.shape[2:]) if masks is None else \
            torch.from_numpy(np.ascontiguousarray(masks)).float()[:, None] * 2 - 1
        x = torch.cat([x, m], dim=1)
    if x.shape[-2:] != (size, size):
        x = torch.nn.functional.interpolate(x, size=(size, size), mode='bilinear', align_corners=False)
    return x


def train_encoder(config: dict, prior_dir: str | Path, out_dir: str | Path | None = None,
                  shapes: list[TrainingShape] | None = None, resume: bool = False, steps: int | None = None,
                  device: str = 'auto', progress: bool = True, meshes: str | None = None,
                  class_name: str | None = None) -> dict:
    """Train the image encoder on renders of the prior's training shapes, regressing their codes (Huber loss).

    prior_dir: a folder with decoder.pt/shapes.yaml from `train_decoder`; out_dir: where encoder.pt goes
    (default: prior_dir). shapes: the training shapes in the prior's order (default: re-created from the
    prior's decoder config / `meshes`). Returns {'history', 'seconds', 'steps'}.
    """
    prior_dir = Path(prior_dir)
    out = Path(out_dir) if out_dir is not None else prior_dir
    out.mkdir(parents=True, exist_ok=True)
    config, tc, seed, total_steps, dev = _training_setup(config, steps, device)
    meta = yaml.safe_load((prior_dir / 'config.yaml').read_text())
    names = [s['name'] for s in yaml.safe_load((prior_dir / 'shapes.yaml').read_text())]
    codes = torch.load(prior_dir / 'decoder.pt', map_location='cpu', weights_only=True)['training_codes'].float()
    if shapes is None:
        shapes = training_shapes(meta['decoder_training'], meshes, class_name)
    if [s.name for s in shapes] != names:
        raise ValueError(f'the shapes given do not match the prior {prior_dir} (shapes.yaml lists {len(names)} shapes); '
                         'pass the same --meshes/--class used for `frodo train decoder`')
    rc = config.get('renders', {})
    distance = tuple(float(d) for d in rc.get('distance', (1.3, 4.5)))
    near = '' if distance == (1.3, 4.5) else f'_d{distance[0]:g}-{distance[1]:g}'
    cache = out / 'cache' / f"renders_v{rc.get('views_per_shape', 24)}_s{seed}_n{len(shapes)}{near}.npz"
    rs = render_set(shapes, int(rc.get('views_per_shape', 24)), seed, cache, progress, int(rc.get('crop_size', 160)),
                    distance)
    aug = CropAugmentation.from_dict(config.get('augment'))

    ecfg = EncoderConfig.from_dict(config.get('encoder'))
    ecfg.code_dim = codes.shape[1]
    encoder = ImageEncoder(ecfg)
    encoder.code_mean.copy_(codes.mean(0))
    encoder.code_std.copy_(codes.std(0).clamp_min(1e-6))
    encoder.to(dev)
    lr = float(tc.get('lr', 1e-3))
    opt = torch.optim.AdamW(encoder.parameters(), lr=lr, weight_decay=float(tc.get('weight_decay', 1e-4)))
    power = float(tc.get('lr_power', 0.9))
    history: dict[str, list[float]] = {'step': [], 'huber': []}
    start = 0
    ckpt_path = out / 'checkpoints' / 'encoder.pt'
    if resume and ckpt_path.exists():
        ck = torch.load(ckpt_path, map_location=dev, weights_only=True)
        encoder.load_state_dict(ck['encoder'])
        opt.load_state_dict(ck['optim'])
        history, start = ck['history'], int(ck['step'])
    elif resume:
        print(f'--resume: no checkpoint at {ckpt_path}; starting from scratch')
    B = int(tc.get('batch_size', 32))
    huber_delta = float(tc.get('huber_delta', 1.0))
    p_no_mask = float(tc.get('p_no_mask', 0.05))
    every = int(tc.get('checkpoint_every', 200))
    target_all = (codes - encoder.code_mean.cpu()) / encoder.code_std.cpu()
    t0 = time.time()

    def checkpoint(step: int) -> None:
        _save_atomic({'encoder': encoder.state_dict(), 'optim': opt.state_dict(), 'step': step, 'history': history},
                     ckpt_path)

    encoder.train()
    bar = tqdm(range(start, total_steps), desc='encoder', disable=not progress, initial=start, total=total_steps)
    for step in bar:
        for g in opt.param_groups:
            g['lr'] = lr * (1 - step / total_steps) ** power
        rng = np.random.default_rng([seed, step])
        views = rng.integers(0, len(rs.images), B)
        crops, masks = zip(*(augment_crop(rs.images[v], rs.masks[v], rs.boxes[v], rng, ecfg.input_size, aug=aug)
                             for v in views))
        masks = np.stack(masks)
        x = encoder_input(np.stack(crops), masks, ecfg.input_size, ecfg.in_channels)
        if ecfg.in_channels == 4:
            drop = torch.from_numpy(rng.uniform(size=B) < p_no_mask)
            x[drop, 3] = 1.0
        target = target_all[torch.from_numpy(rs.shape_index[views])].to(dev)
        loss = torch.nn.functional.huber_loss(encoder.forward_normalised(x.to(dev)), target, delta=huber_delta)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        history['step'].append(step)
        history['huber'].append(loss.item())
        bar.set_postfix(huber=f'{loss.item():.4f}')
        if (step + 1) % every == 0:
            checkpoint(step + 1)
    seconds = time.time() - t0
    checkpoint(total_steps)
    encoder.eval()
    torch.save(_half_state(encoder), out / 'encoder.pt')
    meta_path = out / 'config.yaml'
    meta = yaml.safe_load(meta_path.read_text()) if meta_path.exists() else meta
    meta['encoder'] = ecfg.to_dict()
    meta['encoder_training'] = copy.deepcopy(config)
    meta_path.write_text(yaml.safe_dump(meta, sort_keys=False))
    if history['step']:
        plot_losses(history, out / 'loss_encoder.png', f'encoder ({len(rs.images)} renders of {len(shapes)} shapes)')
    return {'history': history, 'seconds': seconds, 'steps': total_steps}

