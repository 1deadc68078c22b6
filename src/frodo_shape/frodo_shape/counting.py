"""Work counts of the shape decoders: how many SDF queries and point-decoder shapes a piece of code asks for,
and their floating-point operations, so a stage can state how far it is from the machine's limit.

    counter = DecoderCounter(prior.decoder)
    with counter:
        ...                                   # anything that calls prior.sdf / decode_points
    counter.snapshot()                        # DecoderCounts(sdf_queries=..., flops=...)

FLOPs are counted from the layer shapes (a multiply-add = 2), forward per SDF query and per decoded shape;
a call made with gradients enabled on a differentiable input adds one backward pass of the same cost (the
gradient with respect to the layer inputs: the prior's weights are frozen, so no weight gradients).
Elementwise work (ReLU, tanh, concatenation) and the per-shape code term of the SDF layers are left out: under
1 % of the matrix products at width 256.
"""
from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import nn

from frodo_shape.models import JointDecoder, SDFDecoder, _CodeLinear


def sdf_flops_per_query(net: SDFDecoder) -> int:
    """Forward FLOPs of one SDF query: 2 x (inputs x outputs) of every layer's per-point matrix product."""
    total = 0
    for layer in [*net.layers, net.out]:
        if isinstance(layer, _CodeLinear):
            total += 2 * layer.in_features * layer.lin.weight.shape[0]
        else:
            total += 2 * layer.in_features * layer.out_features
    return total


def point_flops_per_shape(decoder: JointDecoder) -> int:
    """Forward FLOPs of decoding one code into its surface points."""
    return sum(2 * m.in_features * m.out_features for m in decoder.point_net.modules() if isinstance(m, nn.Linear))


@dataclass(frozen=True)
class DecoderCounts:
    """Totals since the counter started; subtract two snapshots for the work in between."""

    sdf_calls: int = 0
    sdf_queries: int = 0
    sdf_queries_with_grad: int = 0
    point_calls: int = 0
    point_shapes: int = 0
    point_shapes_with_grad: int = 0
    flops: float = 0.0

    def __sub__(self, other: 'DecoderCounts') -> 'DecoderCounts':
        return DecoderCounts(**{f.name: getattr(self, f.name) - getattr(other, f.name) for f in fields(self)})

    def __add__(self, other: 'DecoderCounts') -> 'DecoderCounts':
        return DecoderCounts(**{f.name: getattr(self, f.name) + getattr(other, f.name) for f in fields(self)})


def _needs_grad(*tensors: torch.Tensor) -> bool:
    return torch.is_grad_enabled() and any(isinstance(t, torch.Tensor) and t.requires_grad for t in tensors)


class DecoderCounter:
    """Counts the SDF queries and decoded shapes of `decoder` while active (a context manager; forward hooks)."""

    def __init__(self, decoder: JointDecoder):
        self.decoder = decoder
        self.sdf_flops = sdf_flops_per_query(decoder.sdf_net)
        self.point_flops = point_flops_per_shape(decoder)
        self._counts: dict[str, float] = {f.name: 0 for f in fields(DecoderCounts)}
        self._hooks: list = []

    def _on_sdf(self, module, inputs, output) -> None:
        codes, xyz = inputs
        n = int(xyz.shape[0] * xyz.shape[1]) if xyz.ndim == 3 else int(xyz.shape[0])
        grad = _needs_grad(codes, xyz)
        self._counts['sdf_calls'] += 1
        self._counts['sdf_queries'] += n
        self._counts['sdf_queries_with_grad'] += n if grad else 0
        self._counts['flops'] += n * self.sdf_flops * (2 if grad else 1)

    def _on_points(self, module, inputs, output) -> None:
        (codes,) = inputs
        n = int(codes.shape[0])
        grad = _needs_grad(codes)
        self._counts['point_calls'] += 1
        self._counts['point_shapes'] += n
        self._counts['point_shapes_with_grad'] += n if grad else 0
        self._counts['flops'] += n * self.point_flops * (2 if grad else 1)

    def snapshot(self) -> DecoderCounts:
        """The totals so far."""
        return DecoderCounts(**{k: (float(v) if k == 'flops' else int(v)) for k, v in self._counts.items()})

    def __enter__(self) -> 'DecoderCounter':
        self._hooks = [self.decoder.sdf_net.register_forward_hook(self._on_sdf),
                       self.decoder.point_net.register_forward_hook(self._on_points)]
        return self

    def __exit__(self, *exc) -> None:
        for hook in self._hooks:
            hook.remove()
        self._hooks = []
