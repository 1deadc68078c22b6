"""The shipped prior (paper Sec. 4 joint embedding + Sec. 5.2 encoder) loads safely and decodes plausible shapes."""
import numpy as np
import pytest
import torch

from frodo_shape.prior import DEFAULT_PRIOR, PRIORS_DIR, ShapePrior, resolve_prior, shipped_priors


@pytest.fixture(scope='module')
def prior():
    torch.set_num_threads(1)
    return ShapePrior.load('furniture')


def test_shipped_priors_load_with_weights_only_and_have_a_model_card():
    assert {'furniture', 'furniture_broad'} <= set(shipped_priors()) and DEFAULT_PRIOR in shipped_priors()
    for name in shipped_priors():
        for f in ('decoder.pt', 'encoder.pt'):
            blob = torch.load(PRIORS_DIR / name / f, map_location='cpu', weights_only=True)
            assert isinstance(blob, dict)
            assert (PRIORS_DIR / name / f).stat().st_size < 5_000_000  # small enough for git
        assert (PRIORS_DIR / name / 'MODEL_CARD.md').is_file()
    with pytest.raises(FileNotFoundError, match='shipped'):
        resolve_prior('no-such-prior')


def test_broad_prior_was_trained_on_the_extra_families():
    broad = ShapePrior.load('furniture_broad')
    assert broad.code_dim == 64 and broad.class_names == ['chair', 'dining table']
    assert broad.training_codes.shape == (280, 64)
    families = {s['family'] for s in broad.training_shapes}
    assert {'shell', 'upholstered', 'spindle', 'panel_end', 'x_base', 'side', 'four_leg', 'office'} <= families
    assert not families & {'cantilever', 'tub', 'desk', 'round_four_leg'}  # evaluation-only designs


def test_prior_metadata(prior):
    assert prior.code_dim == 64
    assert prior.class_names == ['chair', 'dining table']
    assert prior.training_codes.shape == (len(prior.training_names), 64)
    assert set(prior.training_classes) == {'chair', 'dining table'}


def test_decoded_training_chair_is_closed_and_fills_the_normalised_frame(prior):
    i = prior.training_classes.index('chair')
    mesh = prior.mesh(prior.training_codes[i], resolution=48)
    assert len(mesh.faces) > 500
    half_diag = 0.5 * np.linalg.norm(mesh.extents)
    assert 0.7 < half_diag < 1.05  # training shapes have bounding-box half-diagonal 0.9
    assert mesh.bounds[1, 2] - mesh.bounds[0, 2] > 0.6  # a chair is tall in z (up)
    assert abs(mesh.volume) > 0.01 and mesh.is_watertight


def test_points_and_sdf_agree(prior):
    z = prior.training_codes[:2]
    pts = prior.decode_points(z)
    assert pts.shape == (2, 2048, 3) and float(pts.abs().max()) < 1.2
    d = prior.sdf(pts, z)  # decoded surface points lie near the SDF zero level set (joint embedding)
    assert float(d.abs().median()) < 0.05
    zz = z[0].clone().requires_grad_(True)
    prior.sdf(pts[0].detach(), zz).sum().backward()
    assert zz.grad is not None and torch.isfinite(zz.grad).all()


def test_encoder_and_retrieval(prior):
    crops = np.random.default_rng(0).integers(0, 255, (2, 128, 128, 3), dtype=np.uint8)
    masks = np.zeros((2, 128, 128), bool)
    masks[:, 30:100, 40:90] = True
    codes = prior.encode(crops, masks)
    assert codes.shape == (2, 64) and codes.dtype == np.float32 and np.isfinite(codes).all()
    assert prior.encode(crops, None).shape == (2, 64)
    nn = prior.nearest_training(prior.training_codes[3], k=4)
    assert nn[0][0] == 3 and nn[0][2] == pytest.approx(0.0, abs=1e-5) and len(nn) == 4
