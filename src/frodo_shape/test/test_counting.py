"""Decoder work counts (frodo_shape.counting): queries, shapes and FLOPs of known calls, with and without
gradients, and nothing counted outside the counter's block."""
import torch

from frodo_shape.counting import DecoderCounter, sdf_flops_per_query
from frodo_shape.models import DecoderConfig, JointDecoder


def tiny_decoder() -> JointDecoder:
    torch.manual_seed(0)
    config = DecoderConfig.from_dict({'code_dim': 8, 'sdf_width': 16, 'sdf_depth': 4})
    return JointDecoder(config).eval().requires_grad_(False)


def test_flops_per_query_follow_the_layer_shapes():
    decoder = tiny_decoder()
    # layers: 3->16 (code term per shape), 16->16, skip (16+3)->16, 16->16, out 16->1
    assert sdf_flops_per_query(decoder.sdf_net) == 2 * (3 * 16 + 16 * 16 + 19 * 16 + 16 * 16 + 16 * 1)


def test_queries_shapes_and_gradients_are_counted_only_inside_the_block():
    decoder = tiny_decoder()
    codes = torch.zeros(2, 8)
    decoder.sdf(codes, torch.zeros(2, 5, 3))                       # before: not counted
    counter = DecoderCounter(decoder)
    with counter:
        with torch.no_grad():
            decoder.sdf(codes, torch.zeros(2, 5, 3))               # 10 queries, forward only
        xyz = torch.zeros(1, 7, 3, requires_grad=True)
        decoder.sdf(codes[:1], xyz).sum().backward()               # 7 queries with gradients
        decoder.points(codes)                                      # 2 shapes, no gradient asked
        middle = counter.snapshot()
        decoder.points(codes[:1].clone().requires_grad_(True))     # 1 shape with gradients
    decoder.sdf(codes, torch.zeros(2, 5, 3))                       # after: not counted
    total = counter.snapshot()
    assert (total.sdf_calls, total.sdf_queries, total.sdf_queries_with_grad) == (2, 17, 7)
    assert (total.point_calls, total.point_shapes, total.point_shapes_with_grad) == (2, 3, 1)
    per_query, per_shape = counter.sdf_flops, counter.point_flops
    assert total.flops == (10 + 2 * 7) * per_query + (2 + 2 * 1) * per_shape
    assert (total - middle).point_shapes == 1 and (total - middle).sdf_queries == 0
