"""Networks of the joint shape embedding (paper Sec. 4 and supplement "Network Architecture and Training").

- `SDFDecoder` Gd(z, x): DeepSDF-style MLP on [code, xyz] with a latent skip connection at the middle layer,
  tanh output, optional weight norm. The code's contribution to the first and the skip layer is computed
  once per shape and broadcast over its query points (same function as concatenating, far fewer FLOPs).
- `PointDecoder` Gs(z): PSGN-style fully connected decoder to 2048 surface points. The paper's branch is
  FC 512-1024-2048-2048x3 (~15 M parameters); `POINT_DECODER_VARIANTS` names smaller CPU variants.
- `JointDecoder`: both branches on one 64-D code.
- `ImageEncoder`: a ResNet-style CNN (`ResidualBlock`s, reduced width) regressing a code from a
  128x128 crop, optionally with the instance mask as a 4th channel (paper Sec. 5.2).

All networks work in the normalised object frame (docs/ARCHITECTURE.md): z up, front +x, bounding-box
half-diagonal 0.9.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Sequence

import torch
from torch import nn

# Hidden widths of the point branch (output layer 2048x3 follows). 'paper' is the supplement's branch.
POINT_DECODER_VARIANTS: dict[str, tuple[int, ...]] = {
    'tiny': (256,),
    'small': (256, 256),
    'medium': (256, 512),
    'paper': (512, 1024, 2048),
}


@dataclass
class DecoderConfig:
    """Size of the joint decoder. `sdf_depth` hidden layers of `sdf_width`; skip input at layer depth // 2."""

    code_dim: int = 64
    sdf_width: int = 256
    sdf_depth: int = 5
    weight_norm: bool = False
    point_variant: str = 'small'
    num_points: int = 2048

    @classmethod
    def from_dict(cls, d: dict | None) -> 'DecoderConfig':
        return cls(**(d or {}))

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class EncoderConfig:
    """Size of the image encoder: stage widths of four ResNet stages, `blocks` `ResidualBlock`s per stage."""

    code_dim: int = 64
    widths: Sequence[int] = field(default_factory=lambda: (24, 48, 96, 192))
    blocks: Sequence[int] = field(default_factory=lambda: (2, 2, 2, 2))
    in_channels: int = 4
    input_size: int = 128

    @classmethod
    def from_dict(cls, d: dict | None) -> 'EncoderConfig':
        return cls(**(d or {}))

    def to_dict(self) -> dict:
        d = asdict(self)
        d['widths'], d['blocks'] = list(self.widths), list(self.blocks)
        return d


class _CodeLinear(nn.Module):
    """Linear layer on [features, code] computed as W_f f + (W_c z + b) with the code term once per shape."""

    def __init__(self, in_features: int, code_dim: int, out_features: int, weight_norm: bool):
        super().__init__()
        self.in_features = in_features
        lin = nn.Linear(in_features + code_dim, out_features)
        self.lin = nn.utils.parametrizations.weight_norm(lin) if weight_norm else lin

    def forward(self, feats: torch.Tensor, codes: torch.Tensor) -> torch.Tensor:
        """feats (B, P, F), codes (B, C) -> (B, P, out)."""
        w = self.lin.weight
        code_term = codes @ w[:, self.in_features:].T + self.lin.bias  # (B, out)
        return feats @ w[:, :self.in_features].T + code_term[:, None, :]


class SDFDecoder(nn.Module):
    """DeepSDF decoder Gd: (codes (B, C), xyz (B, P, 3)) -> signed distance (B, P), negative inside."""

    def __init__(self, code_dim: int = 64, width: int = 256, depth: int = 5, weight_norm: bool = False):
        super().__init__()
        if depth < 2:
            raise ValueError(f'sdf depth must be >= 2, got {depth}')
        self.skip_at = depth // 2
        wn = (lambda m: nn.utils.parametrizations.weight_norm(m)) if weight_norm else (lambda m: m)
        layers: list[nn.Module] = []
        for i in range(depth):
            if i == 0:
                layers.append(_CodeLinear(3, code_dim, width, weight_norm))
            elif i == self.skip_at:
                layers.append(_CodeLinear(width + 3, code_dim, width, weight_norm))
            else:
                layers.append(wn(nn.Linear(width, width)))
        self.layers = nn.ModuleList(layers)
        self.out = nn.Linear(width, 1)

    def forward(self, codes: torch.Tensor, xyz: torch.Tensor) -> torch.Tensor:
        """codes (B, C), xyz (B, P, 3) -> sdf (B, P)."""
        h = xyz
        for i, layer in enumerate(self.layers):
            if i == 0:
                h = layer(xyz, codes)
            elif i == self.skip_at:
                h = layer(torch.cat([h, xyz], dim=-1), codes)
            else:
                h = layer(h)
            h = torch.relu(h)
        return torch.tanh(self.out(h)).squeeze(-1)


class PointDecoder(nn.Module):
    """PSGN-style point decoder Gs: codes (B, C) -> surface points (B, num_points, 3)."""

    def __init__(self, code_dim: int = 64, hidden: Sequence[int] = (256, 256), num_points: int = 2048):
        super().__init__()
        dims = [code_dim, *hidden]
        layers: list[nn.Module] = []
        for a, b in zip(dims[:-1], dims[1:]):
            layers += [nn.Linear(a, b), nn.ReLU()]
        layers.append(nn.Linear(dims[-1], num_points * 3))
        self.net = nn.Sequential(*layers)
        self.num_points = num_points

    def forward(self, codes: torch.Tensor) -> torch.Tensor:
        return self.net(codes).view(codes.shape[0], self.num_points, 3)


class JointDecoder(nn.Module):
    """Joint embedding decoder: one code, two decoders (paper Eq. 1)."""

    def __init__(self, config: DecoderConfig | None = None):
        super().__init__()
        self.config = config or DecoderConfig()
        c = self.config
        if c.point_variant not in POINT_DECODER_VARIANTS:
            raise ValueError(f'unknown point decoder variant {c.point_variant!r}; known: {sorted(POINT_DECODER_VARIANTS)}')
        self.sdf_net = SDFDecoder(c.code_dim, c.sdf_width, c.sdf_depth, c.weight_norm)
        self.point_net = PointDecoder(c.code_dim, POINT_DECODER_VARIANTS[c.point_variant], c.num_points)

    def sdf(self, codes: torch.Tensor, xyz: torch.Tensor) -> torch.Tensor:
        """codes (B, C), xyz (B, P, 3) -> (B, P)."""
        return self.sdf_net(codes, xyz)

    def points(self, codes: torch.Tensor) -> torch.Tensor:
        """codes (B, C) -> (B, num_points, 3)."""
        return self.point_net(codes)


class ResidualBlock(nn.Module):
    """The two-convolution residual block of ResNet-18/34 (He et al. 2016): 3x3 conv (stride) + BN + ReLU, 3x3 conv
    + BN, plus the input (through `downsample` where the shape changes), ReLU. Its parameter names are those of
    torchvision's `BasicBlock`, so encoders saved with either load into the other; defined here so that loading
    the shape models does not import torchvision (about 1 s, with torch._dynamo, in every process that starts)."""

    def __init__(self, in_channels: int, channels: int, stride: int = 1, downsample: nn.Module | None = None):
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, channels, 3, stride=stride, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(channels)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(channels)
        self.downsample = downsample

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.bn2(self.conv2(self.relu(self.bn1(self.conv1(x)))))
        return self.relu(out + (x if self.downsample is None else self.downsample(x)))


class ImageEncoder(nn.Module):
    """ResNet-style encoder: images (B, in_channels, S, S) float, normalised -> codes (B, code_dim).

    Input: RGB in [-1, 1] plus (in_channels = 4) the instance mask as ±1 (`train.encoder_input`). Stem conv7x7/2 + maxpool, four stages of `ResidualBlock`s (strides 1, 2, 2, 2), global average pool, FC.
    """

    def __init__(self, config: EncoderConfig | None = None):
        super().__init__()
        self.config = config or EncoderConfig()
        c = self.config
        w0 = c.widths[0]
        self.stem = nn.Sequential(
            nn.Conv2d(c.in_channels, w0, 7, stride=2, padding=3, bias=False), nn.BatchNorm2d(w0), nn.ReLU(inplace=True),
            nn.MaxPool2d(3, stride=2, padding=1))
        stages = []
        in_ch = w0
        for i, (w, n) in enumerate(zip(c.widths, c.blocks)):
            stride = 1 if i == 0 else 2
            blocks = []
            for j in range(n):
                s = stride if j == 0 else 1
                down = None
                if s != 1 or in_ch != w:
                    down = nn.Sequential(nn.Conv2d(in_ch, w, 1, stride=s, bias=False), nn.BatchNorm2d(w))
                blocks.append(ResidualBlock(in_ch, w, stride=s, downsample=down))
                in_ch = w
            stages.append(nn.Sequential(*blocks))
        self.stages = nn.Sequential(*stages)
        self.head = nn.Linear(in_ch, c.code_dim)
        # Per-dimension statistics of the training codes: the head regresses standardised codes.
        self.register_buffer('code_mean', torch.zeros(c.code_dim))
        self.register_buffer('code_std', torch.ones(c.code_dim))

    def forward_normalised(self, images: torch.Tensor) -> torch.Tensor:
        """images (B, in_channels, S, S) -> standardised codes (B, code_dim)."""
        h = self.stages(self.stem(images))
        return self.head(torch.flatten(nn.functional.adaptive_avg_pool2d(h, 1), 1))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """images (B, in_channels, S, S) -> codes (B, code_dim)."""
        return self.forward_normalised(images) * self.code_std + self.code_mean


def count_parameters(module: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
