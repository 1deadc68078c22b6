"""Tiny training runs of both stages (paper Eq. 1 auto-decoder, Sec. 5.2 encoder): the losses go down.

Three primitive meshes stand in for the procedural library, so these tests need neither frodo_datasets'
shape generator nor much CPU (seconds).
"""
import argparse

import numpy as np
import pytest
import torch
import trimesh
import yaml

from frodo_shape import cli_train
from frodo_shape.models import DecoderConfig, EncoderConfig, ImageEncoder, JointDecoder, ResidualBlock
from frodo_shape.prior import ShapePrior
from frodo_shape.train import (RenderSet, TrainingShape, chamfer, design_shapes, encoder_input, train_decoder,
                               train_encoder)

TINY_DECODER = {
    'seed': 0,
    'sampling': {'n_near': 1024, 'n_uniform': 256, 'n_surface': 512, 'n_dense': 5000},
    'decoder': {'sdf_width': 32, 'sdf_depth': 3, 'point_variant': 'tiny', 'num_points': 128},
    'train': {'steps': 60, 'shapes_per_batch': 3, 'sdf_points_per_shape': 256, 'surface_points': 128,
              'lr_net': 3e-3, 'lr_codes': 1e-2, 'lr_decay_every': 1000, 'checkpoint_every': 20, 'threads': 1},
}
TINY_ENCODER = {
    'seed': 0,
    'renders': {'views_per_shape': 2, 'crop_size': 64},
    'encoder': {'widths': [8, 8, 16, 16], 'blocks': [1, 1, 1, 1], 'in_channels': 4, 'input_size': 64},
    'train': {'steps': 60, 'batch_size': 6, 'lr': 1e-2, 'checkpoint_every': 20, 'threads': 1},
}


def _shapes() -> list[TrainingShape]:
    meshes = [trimesh.creation.box((1.2, 0.8, 0.5)), trimesh.creation.icosphere(2, radius=0.8),
              trimesh.creation.cylinder(0.4, 1.4, sections=16)]
    return [TrainingShape(f'prim{i}', 'chair', 'primitive', 0.5, m) for i, m in enumerate(meshes)]


def _fake_renders(n_shapes: int, size: int = 64) -> RenderSet:
    """Distinct synthetic 'renders' per shape (a disc of shape-dependent size and colour)."""
    rng = np.random.default_rng(0)
    imgs, masks, boxes, idx = [], [], [], []
    yy, xx = np.mgrid[:size, :size]
    for i in range(n_shapes):
        for _ in range(3):
            r = 8 + 6 * i
            m = (xx - size / 2) ** 2 + (yy - size / 2) ** 2 < r * r
            img = rng.integers(0, 60, (size, size, 3)).astype(np.uint8)
            img[m] = (80 * i + 40, 200 - 60 * i, 120)
            imgs.append(img), masks.append(m), boxes.append([size / 2 - r, size / 2 - r, size / 2 + r, size / 2 + r])
            idx.append(i)
    return RenderSet(np.stack(imgs), np.stack(masks), np.asarray(boxes, np.float32), np.asarray(idx))


def test_chamfer_matches_brute_force_and_is_zero_on_identical_sets():
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(2, 50, 3, generator=g), torch.rand(2, 70, 3, generator=g)
    d = torch.cdist(a, b) ** 2
    brute = d.min(2).values.mean(1) + d.min(1).values.mean(1)
    torch.testing.assert_close(chamfer(a, b), brute)
    assert float(chamfer(a, a).max()) == 0.0


def test_decoder_shapes_and_code_skip_equivalence():
    dec = JointDecoder(DecoderConfig(sdf_width=16, sdf_depth=4, point_variant='tiny', num_points=64))
    z, x = torch.randn(2, 64), torch.rand(2, 10, 3)
    assert dec.sdf(z, x).shape == (2, 10) and dec.points(z).shape == (2, 64, 3)
    lin = dec.sdf_net.layers[0].lin  # the code term computed once per shape == Linear on [xyz, code]
    ref = torch.cat([x, z[:, None].expand(-1, 10, -1)], -1) @ lin.weight.T + lin.bias
    torch.testing.assert_close(dec.sdf_net.layers[0](x, z), ref)
    enc = ImageEncoder(EncoderConfig(widths=(8, 8, 8, 8), blocks=(1, 1, 1, 1), input_size=64))
    assert enc(torch.randn(2, 4, 64, 64)).shape == (2, 64)


def test_tiny_decoder_training_reduces_losses_and_resumes(tmp_path):
    shapes = _shapes()
    out = tmp_path / 'prior'
    res = train_decoder(TINY_DECODER, out, shapes=shapes, steps=40, progress=False, device='cpu')
    h = res['history']
    assert np.mean(h['sdf'][-10:]) < 0.7 * np.mean(h['sdf'][:10])
    assert np.mean(h['chamfer'][-10:]) < 0.5 * np.mean(h['chamfer'][:10])
    res2 = train_decoder(TINY_DECODER, out, shapes=shapes, resume=True, steps=60, progress=False, device='cpu')
    assert len(res2['history']['step']) == 60 and res2['history']['step'][40] == 40
    for f in ('decoder.pt', 'config.yaml', 'shapes.yaml', 'loss_decoder.png'):
        assert (out / f).exists()
    assert yaml.safe_load((out / 'config.yaml').read_text())['decoder_training']['train']['steps'] == 60  # as run
    prior = ShapePrior.load(out)
    assert prior.training_codes.shape == (3, 64) and prior.training_names == ['prim0', 'prim1', 'prim2']
    assert prior.decode_points(prior.training_codes).shape == (3, 128, 3)


def test_tiny_encoder_training_reduces_huber_loss(tmp_path, monkeypatch):
    shapes = _shapes()
    out = tmp_path / 'prior'
    train_decoder(TINY_DECODER, out, shapes=shapes, steps=5, progress=False, device='cpu')
    monkeypatch.setattr('frodo_shape.train.render_set', lambda *a, **k: _fake_renders(len(shapes)))
    res = train_encoder(TINY_ENCODER, out, shapes=shapes, progress=False, device='cpu', steps=70)
    h = res['history']['huber']
    assert np.mean(h[-10:]) < 0.6 * np.mean(h[:10])
    prior = ShapePrior.load(out)
    rs = _fake_renders(len(shapes))
    codes = prior.encode(rs.images[:3], rs.masks[:3])
    assert codes.shape == (3, 64) and codes.dtype == np.float32
    meta = yaml.safe_load((out / 'config.yaml').read_text())
    assert meta['encoder']['input_size'] == 64 and 'decoder' in meta
    assert meta['encoder_training']['train']['steps'] == 70 and TINY_ENCODER['train']['steps'] != 70  # as run


def test_residual_block_computes_torchvision_basic_block_with_the_same_parameters():
    """The encoder's own block has torchvision BasicBlock's parameter names and output (both modes of BN)."""
    from torchvision.models.resnet import BasicBlock
    torch.manual_seed(0)
    down = torch.nn.Sequential(torch.nn.Conv2d(8, 16, 1, stride=2, bias=False), torch.nn.BatchNorm2d(16))
    ours = ResidualBlock(8, 16, stride=2, downsample=down)
    theirs = BasicBlock(8, 16, stride=2, downsample=torch.nn.Sequential(
        torch.nn.Conv2d(8, 16, 1, stride=2, bias=False), torch.nn.BatchNorm2d(16)))
    with torch.no_grad():                                  # non-trivial BN statistics and affine parameters
        for module in ours.modules():
            if isinstance(module, torch.nn.BatchNorm2d):
                module.running_mean.uniform_(-0.5, 0.5)
                module.running_var.uniform_(0.5, 2.0)
                module.weight.uniform_(0.5, 1.5)
                module.bias.uniform_(-0.2, 0.2)
    assert list(ours.state_dict()) == list(theirs.state_dict())
    theirs.load_state_dict(ours.state_dict())
    x = torch.randn(2, 8, 12, 12)
    for train in (False, True):
        ours.train(train), theirs.train(train)
        assert torch.allclose(ours(x), theirs(x), atol=1e-6)
    same = ResidualBlock(16, 16)
    assert same(torch.randn(1, 16, 6, 6)).shape == (1, 16, 6, 6)


def test_encoder_input_scaling():
    crops = np.full((1, 8, 8, 3), 255, np.uint8)
    x = encoder_input(crops, None, 16, 4)
    assert x.shape == (1, 4, 16, 16) and float(x.min()) == 1.0


def test_cli_parses_both_stages(tmp_path):
    parser = argparse.ArgumentParser()
    cli_train.add_arguments(parser)
    a = parser.parse_args(['decoder', '--out', str(tmp_path), '--steps', '3', '--meshes', 'm', '--class', 'chair'])
    assert (a.stage, a.steps, a.class_name, a.resume) == ('decoder', 3, 'chair', False)
    a = parser.parse_args(['encoder', '--prior', str(tmp_path), '--resume'])
    assert a.stage == 'encoder' and a.resume and a.config == 'furniture_encoder'
    assert cli_train.run(parser.parse_args(['decoder', '--out', str(tmp_path), '--config', 'nope'])) == 2
    with pytest.raises(SystemExit):
        parser.parse_args(['decoder'])


def test_decoder_trains_on_a_folder_of_user_meshes_via_the_cli(tmp_path):
    meshes = tmp_path / 'my_stools'
    meshes.mkdir()
    for shape in _shapes():
        shape.mesh.export(meshes / f'{shape.name}.obj')
    cfg = tmp_path / 'tiny.yaml'
    cfg.write_text(yaml.safe_dump(TINY_DECODER))
    out = tmp_path / 'prior'
    assert cli_train.main(['decoder', '--config', str(cfg), '--out', str(out), '--steps', '3', '--quiet',
                           '--meshes', str(meshes), '--class', 'chair', '--device', 'cpu']) == 0
    prior = ShapePrior.load(out)
    assert sorted(prior.training_classes) == ['chair'] * 3 and len(prior.training_names) == 3
    assert all(s['seed'] is None for s in prior.training_shapes)
    assert cli_train.main(['decoder', '--config', str(cfg), '--out', str(out), '--meshes', str(meshes)]) == 2


def test_design_shapes_are_the_evaluation_only_families() -> None:
    from frodo_datasets.shapes import eval_families, extra_families, families
    shapes = design_shapes(['chair', 'dining table'], 2, seed=11)
    for c in ('chair', 'dining table'):
        got = [s.family for s in shapes if s.class_name == c]
        assert sorted(got) == sorted(eval_families(c) * 2)
        assert not set(got) & set(families(c) + extra_families(c))
    assert all(abs(np.linalg.norm(s.mesh.extents) / 2 - 0.9) < 1e-6 and s.seed is not None for s in shapes)
    assert [s.name for s in design_shapes(['chair'], 2, seed=11)] == [s.name for s in shapes if s.class_name == 'chair']
