"""A trained shape prior: joint decoder (paper Sec. 4), training codes, image encoder (Sec. 5.2).

A prior is a folder (`frodo_shape/priors/<name>/` for shipped ones, or any folder written by
`frodo train decoder/encoder`): decoder.pt ({'state_dict': float16 weights, 'training_codes': (M, C)}),
encoder.pt (float16 state dict, optional), config.yaml, shapes.yaml (training shape names, classes, scales).
Everything is loaded with `torch.load(..., weights_only=True)`.

Coordinates are in the normalised object frame (docs/ARCHITECTURE.md); `shapes.yaml` scales map a training
shape back to metres.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import trimesh
import yaml

from frodo_shape.meshing import marching_cubes, sdf_grid
from frodo_shape.models import DecoderConfig, EncoderConfig, ImageEncoder, JointDecoder

PRIORS_DIR = Path(__file__).parent / 'priors'
# The prior shape_node and optim_node load unless told otherwise (both must use the same one: codes are only
# meaningful to the decoder they were trained with). Chosen on the tuning rooms; see its MODEL_CARD.md, "Decision".
DEFAULT_PRIOR = 'furniture_broad'


def shipped_priors() -> list[str]:
    """Names of the priors shipped in frodo_shape/priors."""
    return sorted(p.name for p in PRIORS_DIR.iterdir() if (p / 'decoder.pt').exists()) if PRIORS_DIR.exists() else []


def resolve_prior(name_or_dir: str | Path) -> Path:
    """A prior folder from a shipped name or a path; raises FileNotFoundError naming the shipped priors."""
    p = Path(name_or_dir)
    if (p / 'decoder.pt').exists():
        return p
    shipped = PRIORS_DIR / str(name_or_dir)
    if (shipped / 'decoder.pt').exists():
        return shipped
    raise FileNotFoundError(f'no shape prior {str(name_or_dir)!r}: not a folder with decoder.pt and not a shipped '
                            f'prior (shipped: {shipped_priors()}); train one with `frodo train decoder`')


class ShapePrior:
    """Joint decoder + encoder + training codes of one prior, ready for inference on `device`."""

    def __init__(self, path: Path, decoder: JointDecoder, training_codes: torch.Tensor, meta: dict,
                 shapes: list[dict], encoder: ImageEncoder | None, device: torch.device):
        self.path = path
        self.decoder = decoder
        self.encoder = encoder
        self.device = device
        self.meta = meta
        self.training_codes = training_codes
        self.training_shapes: list[dict] = shapes  # shapes.yaml rows: name, class, family, scale, seed
        self.training_names: list[str] = [s['name'] for s in shapes]
        self.training_classes: list[str] = [s['class'] for s in shapes]
        self.training_scales = np.array([float(s.get('scale', 1.0)) for s in shapes])
        self.class_names: list[str] = list(meta.get('class_names', sorted(set(self.training_classes))))
        self.code_dim: int = int(training_codes.shape[1])

    @classmethod
    def load(cls, name_or_dir: str | Path, device: str | torch.device = 'cpu') -> 'ShapePrior':
        """Load a shipped prior by name ('furniture') or a prior folder. device: 'cpu', 'cuda' or 'auto'."""
        path = resolve_prior(name_or_dir)
        if str(device) == 'auto':
            device = 'cuda' if torch.cuda.is_available() else 'cpu'
        dev = torch.device(device)
        meta = yaml.safe_load((path / 'config.yaml').read_text())
        shapes = yaml.safe_load((path / 'shapes.yaml').read_text()) or []
        blob = torch.load(path / 'decoder.pt', map_location='cpu', weights_only=True)
        decoder = JointDecoder(DecoderConfig.from_dict(meta['decoder']))
        decoder.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in blob['state_dict'].items()})
        decoder.to(dev).eval().requires_grad_(False)
        encoder = None
        if (path / 'encoder.pt').exists() and 'encoder' in meta:
            encoder = ImageEncoder(EncoderConfig.from_dict(meta['encoder']))
            sd = torch.load(path / 'encoder.pt', map_location='cpu', weights_only=True)
            encoder.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in sd.items()})
            encoder.to(dev).eval().requires_grad_(False)
        codes = blob['training_codes'].float().to(dev)
        if len(shapes) != len(codes):
            raise ValueError(f'{path}: shapes.yaml lists {len(shapes)} shapes but decoder.pt has {len(codes)} codes')
        return cls(path, decoder, codes, meta, shapes, encoder, dev)

    # ------------------------------------------------------------ encoder
    def encode(self, crops: np.ndarray, masks: np.ndarray | None = None, batch_size: int = 64) -> np.ndarray:
        """Codes (N, C) float32 from crops (N, H, W, 3) uint8 RGB and instance masks (N, H, W) bool or None.

        Crops should be square windows around the detection box (`frodo_shape.crops.square_crop`, margin 0.1,
        what the encoder was trained on); they are resized to the encoder input size here.
        """
        from frodo_shape.train import encoder_input
        if self.encoder is None:
            raise RuntimeError(f'prior {self.path} has no encoder.pt; train one with `frodo train encoder --prior {self.path}`')
        crops = np.asarray(crops)
        if crops.ndim != 4 or crops.shape[-1] != 3 or crops.dtype != np.uint8:
            raise ValueError(f'crops must be (N, H, W, 3) uint8 RGB, got {crops.shape} {crops.dtype}')
        if masks is not None and np.asarray(masks).shape != crops.shape[:3]:
            raise ValueError(f'masks must be (N, H, W) = {crops.shape[:3]}, got {np.asarray(masks).shape}')
        c = self.encoder.config
        out = []
        with torch.no_grad():
            for s in range(0, len(crops), batch_size):
                m = None if masks is None else np.asarray(masks[s:s + batch_size], dtype=bool)
                x = encoder_input(crops[s:s + batch_size], m, c.input_size, c.in_channels).to(self.device)
                out.append(self.encoder(x).float().cpu().numpy())
        return np.concatenate(out) if out else np.zeros((0, self.code_dim), np.float32)

    # ------------------------------------------------------------ decoders
    def _codes(self, codes) -> torch.Tensor:
        z = torch.as_tensor(codes, dtype=torch.float32, device=self.device)
        return z[None] if z.ndim == 1 else z

    def decode_points(self, codes) -> torch.Tensor:
        """Surface points (N, 2048, 3) (normalised frame) of codes (N, C) or (C,); differentiable in the codes."""
        return self.decoder.points(self._codes(codes))

    def sdf(self, points, codes) -> torch.Tensor:
        """Signed distances, differentiable in points and codes.

        points (N, P, 3) with codes (N, C) -> (N, P); points (P, 3) with a code (C,) or (1, C) -> (P,).
        """
        pts = torch.as_tensor(points, dtype=torch.float32, device=self.device)
        z = self._codes(codes)
        if pts.ndim == 2:
            return self.decoder.sdf(z[:1], pts[None])[0]
        return self.decoder.sdf(z, pts)

    def sdf_numpy(self, points: np.ndarray, code, chunk: int = 65536) -> np.ndarray:
        """SDF (P,) float32 of points (P, 3) for one code (C,), evaluated in chunks without gradients."""
        z = self._codes(code)[:1]
        out = []
        with torch.no_grad():
            for s in range(0, len(points), chunk):
                p = torch.as_tensor(points[s:s + chunk], dtype=torch.float32, device=self.device)
                out.append(self.decoder.sdf(z, p[None])[0].cpu().numpy())
        return np.concatenate(out) if out else np.zeros(0, np.float32)

    def mesh(self, code, resolution: int = 64) -> trimesh.Trimesh:
        """Marching-cubes mesh of the zero level set of code (C,) in the normalised frame ([-1, 1]^3 grid).

        Coarse-to-fine evaluation (`meshing.sdf_grid`); an empty mesh when the code has no surface.
        """
        code = np.asarray(code.detach().cpu() if isinstance(code, torch.Tensor) else code, dtype=np.float32).reshape(-1)
        grid = sdf_grid(lambda p: self.sdf_numpy(p, code), resolution)
        return marching_cubes(grid)

    # ------------------------------------------------------------ latent space
    def nearest_training(self, code, k: int = 4) -> list[tuple[int, str, float]]:
        """CAD retrieval: the k training shapes nearest to code (C,) in code space, as (index, name, distance)."""
        z = self._codes(code)[0]
        d = torch.linalg.norm(self.training_codes - z, dim=1)
        k = min(k, len(d))
        vals, idx = torch.topk(d, k, largest=False)
        return [(int(i), self.training_names[int(i)], float(v)) for i, v in zip(idx, vals)]

    def fit_sdf(self, points: np.ndarray, sdf: np.ndarray, steps: int = 300, lr: float = 5e-3, batch: int = 4096,
                delta: float = 0.1, code_reg: float = 1e-4, init=None, seed: int = 0) -> np.ndarray:
        """Auto-decoder inference: the code (C,) minimising the clamped L1 SDF loss (+ code prior) on samples.

        points (S, 3), sdf (S,) in the normalised frame; init: starting code (default: mean training code).
        """
        gen = torch.Generator().manual_seed(seed)
        pts = torch.as_tensor(points, dtype=torch.float32)
        gt = torch.as_tensor(sdf, dtype=torch.float32)
        z0 = self.training_codes.mean(0) if init is None else self._codes(init)[0]
        z = z0.detach().clone().to(self.device).requires_grad_(True)
        opt = torch.optim.Adam([z], lr=lr)
        sched = torch.optim.lr_scheduler.StepLR(opt, step_size=max(1, steps // 2), gamma=0.2)
        for _ in range(steps):
            i = torch.randint(0, len(pts), (min(batch, len(pts)),), generator=gen)
            pred = self.decoder.sdf(z[None], pts[i][None].to(self.device))[0]
            loss = (pred.clamp(-delta, delta) - gt[i].to(self.device).clamp(-delta, delta)).abs().mean() \
                + code_reg * z.pow(2).sum()
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
        return z.detach().cpu().numpy().astype(np.float32)
