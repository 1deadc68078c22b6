"""Multi-view shape code fusion (paper Sec. 5.2, "Multi-view Shape Code Fusion").

(i) average: the mean of the single-view codes; (ii) majority vote: the 4 nearest training codes of every
single-view code are pooled and the most frequent training shape wins, so the fused code is always a valid
shape of the training database. Ties are broken by the smaller summed distance.
"""
from __future__ import annotations

import numpy as np
import torch

ArrayLike = np.ndarray | torch.Tensor


def _np(x: ArrayLike) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def fuse_mean(codes: ArrayLike) -> np.ndarray:
    """codes (N, C) -> mean code (C,) float32."""
    codes = _np(codes).astype(np.float32)
    if codes.ndim != 2 or len(codes) == 0:
        raise ValueError(f'fuse_mean expects codes (N, C) with N >= 1, got shape {codes.shape}')
    return codes.mean(axis=0)


def vote_index(codes: ArrayLike, training_codes: ArrayLike, k: int = 4) -> int:
    """Index of the training code chosen by majority vote over the k nearest training codes of each code."""
    codes = _np(codes).astype(np.float64)
    train = _np(training_codes).astype(np.float64)
    if codes.ndim != 2 or len(codes) == 0 or train.ndim != 2 or codes.shape[1] != train.shape[1]:
        raise ValueError(f'fuse_vote expects codes (N, C) and training codes (M, C), got {codes.shape}, {train.shape}')
    k = min(k, len(train))
    d = np.linalg.norm(codes[:, None, :] - train[None, :, :], axis=-1)  # (N, M)
    nearest = np.argsort(d, axis=1)[:, :k]  # (N, k)
    votes = np.bincount(nearest.ravel(), minlength=len(train))
    summed = np.zeros(len(train))
    np.add.at(summed, nearest.ravel(), np.take_along_axis(d, nearest, axis=1).ravel())
    best = np.flatnonzero(votes == votes.max())
    return int(best[np.argmin(summed[best])])


def fuse_vote(codes: ArrayLike, training_codes: ArrayLike, k: int = 4) -> np.ndarray:
    """codes (N, C), training_codes (M, C) -> the winning training code (C,) float32."""
    return _np(training_codes)[vote_index(codes, training_codes, k)].astype(np.float32)
