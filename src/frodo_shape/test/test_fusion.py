"""Multi-view code fusion (paper Sec. 5.2): mean and majority vote over the 4 nearest training codes."""
import numpy as np
import pytest
import torch

from frodo_shape.fusion import fuse_mean, fuse_vote, vote_index


def test_mean_of_codes():
    codes = np.array([[0.0, 1.0], [2.0, 3.0]])
    np.testing.assert_allclose(fuse_mean(codes), [1.0, 2.0])
    np.testing.assert_allclose(fuse_mean(torch.tensor(codes)), [1.0, 2.0])
    with pytest.raises(ValueError):
        fuse_mean(np.zeros((0, 2)))


def test_vote_returns_the_training_shape_most_views_agree_on():
    # Training shapes on a line: the 4 nearest of a view of shape 7 are 7 and its neighbours 5, 6, 8 or 9;
    # ties between equally voted shapes go to the smaller summed distance.
    rng = np.random.default_rng(0)
    train = np.zeros((20, 8))
    train[:, 0] = np.arange(20)
    views = np.concatenate([train[7] + 0.05 * rng.normal(size=(5, 8)),   # five noisy views of shape 7
                            train[15] + 0.05 * rng.normal(size=(2, 8))])  # two outlier views
    assert vote_index(views, train, k=4) == 7
    np.testing.assert_array_equal(fuse_vote(views, train), train[7].astype(np.float32))


def test_vote_is_a_training_code_unlike_the_mean():
    train = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 5.0]])
    views = np.array([[1.0, 0.1], [-1.0, 0.1]])
    assert fuse_vote(views, train, k=1).tolist() in train.tolist()
    np.testing.assert_allclose(fuse_mean(views), [0.0, 0.1])
