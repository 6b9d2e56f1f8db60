"""Which frames to match: neighbours in video order plus loop-closure pairs from retrieval.

Retrieval needs no vocabulary tree: visual words are learnt by k-means on the session's own
SIFT descriptors, each frame becomes a VLAD vector (intra- and power-normalised), and each
frame is paired with its most similar frames outside the sequential window. Revisits of the
same wall area hours of video apart thus get matched, which ties the model together.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from cystomap.sfm.config import SfmConfig

log = logging.getLogger(__name__)

Pair = tuple[int, int]


def sequential_pairs(n: int, overlap: int) -> set[Pair]:
    """Each frame with its ``overlap`` successors (indices into the video-ordered list)."""
    return {(i, j) for i in range(n) for j in range(i + 1, min(n, i + overlap + 1))}


def kmeans(data: np.ndarray, k: int, rng: np.random.Generator, iterations: int = 15) -> np.ndarray:
    """Plain Lloyd k-means with k-means++ seeding; returns the k x d centres."""
    n = len(data)
    k = min(k, n)
    centres = np.empty((k, data.shape[1]), dtype=np.float32)
    centres[0] = data[rng.integers(n)]
    d2 = ((data - centres[0]) ** 2).sum(1)
    for c in range(1, k):
        total = float(d2.sum())
        idx = int(rng.choice(n, p=d2 / total)) if total > 0 else int(rng.integers(n))
        centres[c] = data[idx]
        d2 = np.minimum(d2, ((data - centres[c]) ** 2).sum(1))
    for _ in range(iterations):
        assign = _nearest(data, centres)
        sums = _sum_by(assign, data, k)
        counts = np.bincount(assign, minlength=k).astype(np.float32)
        empty = counts == 0
        centres = np.where(empty[:, None], centres, sums / np.maximum(counts, 1)[:, None])
    return centres


def _sum_by(assign: np.ndarray, data: np.ndarray, k: int) -> np.ndarray:
    """Row sums of ``data`` per label (k x d)."""
    out = np.zeros((k, data.shape[1]), dtype=np.float32)
    if not len(assign):
        return out
    order = np.argsort(assign, kind="stable")
    labels, starts = np.unique(assign[order], return_index=True)
    out[labels] = np.add.reduceat(data[order], starts, axis=0)
    return out


def _nearest(data: np.ndarray, centres: np.ndarray) -> np.ndarray:
    d = (centres**2).sum(1)[None, :] - 2.0 * data @ centres.T
    return np.argmin(d, axis=1)


def vlad(descriptors: Sequence[np.ndarray], cfg: SfmConfig) -> np.ndarray:
    """One L2-normalised VLAD row per frame from its SIFT descriptors (uint8, N x 128)."""
    rng = np.random.default_rng(cfg.seed)
    normed = [_normalise(d) for d in descriptors]
    sample = [d[rng.choice(len(d), min(len(d), cfg.retrieval_train_per_image), replace=False)]
              for d in normed if len(d)]
    if not sample:
        return np.zeros((len(descriptors), 1), dtype=np.float32)
    train = np.concatenate(sample)
    centres = kmeans(train, cfg.retrieval_words, rng)
    k, dim = centres.shape
    out = np.zeros((len(normed), k * dim), dtype=np.float32)
    for i, d in enumerate(normed):
        if not len(d):
            continue
        assign = _nearest(d, centres)
        acc = _sum_by(assign, d - centres[assign], k)
        norms = np.linalg.norm(acc, axis=1, keepdims=True)
        acc = np.divide(acc, norms, out=np.zeros_like(acc), where=norms > 0)
        v = acc.ravel()
        v = np.sign(v) * np.sqrt(np.abs(v))
        n = np.linalg.norm(v)
        out[i] = v / n if n > 0 else v
    return out


def _normalise(desc: np.ndarray) -> np.ndarray:
    d = np.asarray(desc, dtype=np.float32)
    if not len(d):
        return d.reshape(0, 128)
    n = np.linalg.norm(d, axis=1, keepdims=True)
    return d / np.maximum(n, 1e-6)


def retrieval_pairs(descriptors: Sequence[np.ndarray], cfg: SfmConfig) -> set[Pair]:
    """Each frame with its ``retrieval_neighbors`` most similar frames outside its sequential
    window; the neighbours of one frame are also that far apart from each other, so they are
    distinct revisits rather than consecutive frames of one."""
    n = len(descriptors)
    k = cfg.retrieval_neighbors
    if k <= 0 or n < 3:
        return set()
    gap = cfg.retrieval_min_gap or max(cfg.sequential_overlap, 2)
    v = vlad(descriptors, cfg)
    sim = v @ v.T
    pairs: set[Pair] = set()
    for i in range(n):
        chosen: list[int] = []
        for j in np.argsort(-sim[i], kind="stable").tolist():
            if len(chosen) == k:
                break
            if abs(i - j) <= gap or any(abs(j - c) <= gap for c in chosen):
                continue
            chosen.append(j)
            pairs.add((min(i, j), max(i, j)))
    return pairs


def extension_pairs(
    verified: dict[Pair, int], n: int, gap: int, next_gap: int, min_inliers: int, every: int = 1
) -> set[Pair]:
    """Pairs (i, i + next_gap), for i a multiple of ``every``, whose pair (i, i + gap) has
    at least ``min_inliers`` verified matches."""
    return {
        (i, i + next_gap)
        for i in range(0, n - next_gap, every)
        if verified.get((i, i + gap), 0) >= min_inliers
    }


def gap_schedule(start: int, max_gap: int) -> list[tuple[int, int]]:
    """(gap, every) after the first ``start`` gaps: powers of two up to ``max_gap``; gap g
    (beyond 4) only for frames that are multiples of g / 2, which are the candidate
    keyframes for a keyframe stride of g / 2 or g / 4."""
    out = []
    g = 1
    while g * 2 <= max_gap:
        g *= 2
        if g > start:
            out.append((g, 1 if g <= 4 else g // 2))
    return out


def read_descriptors(database: Path, names: list[str]) -> list[np.ndarray]:
    import pycolmap

    db = pycolmap.Database.open(str(database))
    try:
        by_name = {im.name: im.image_id for im in db.read_all_images()}
        return [
            np.asarray(db.read_descriptors(by_name[name]).data) if name in by_name
            else np.zeros((0, 128), np.uint8)
            for name in names
        ]
    finally:
        db.close()


def loop_pairs(
    database: Path, names: list[str], frames: list[int], cfg: SfmConfig
) -> set[Pair]:
    """Retrieval pairs among ``frames`` (indices into ``names``, e.g. the keyframes)."""
    if cfg.retrieval_neighbors <= 0 or len(frames) < 3:
        return set()
    descs = read_descriptors(database, [names[i] for i in frames])
    sub = retrieval_pairs(descs, cfg)
    return {(frames[a], frames[b]) for a, b in sub}
