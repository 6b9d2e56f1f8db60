"""Changes that share one accepted cluster but are separate objects at their half maxima.

A region is measured on its full-width-at-half-maximum outline (:mod:`cystomap.compare.changes`).
When one cluster holds two changes joined by a broad, significant ridge (two lesions inside
one patch of photometric residue: the saddle between them is itself a change, so
:func:`cystomap.compare.null.split_at_saddles` keeps them together), the pixels above half the
cluster's peak fall apart into blobs, and measuring them as one outline puts the centroid
between the lesions and loses the weaker one. A blob is its own change when, at half of *its
own* peak, it is still not connected to a stronger blob: it is a separate object by the
same half-maximum rule the outline is measured with (no new constant). Blobs that do connect
at that level are parts of one change (the lobes of a heterogeneous lesion: the valley
between them stays above half their height), and so are blobs that meet across a strip of
unseen wall at that level (what joins the pieces of one change there:
:func:`cystomap.compare.changes._join_pieces`). A region is split only into pieces that would
each be reported on their own.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from cystomap.compare.morphology import label_wrapped


def separate_half_maxima(sig: np.ndarray, lab: np.ndarray, n: int, peak_percentile: float,
                         grow: Callable[[np.ndarray], np.ndarray] | None = None,
                         stands: Callable[[list[np.ndarray], np.ndarray], list[bool]] | None = None,
                         ) -> tuple[np.ndarray, int]:
    """``lab`` (regions 1 … ``n`` on the grid of ``sig``) with every region whose half-maximum
    blobs are separate objects split into one region per object (the region's pixels go to
    the object they flow to: watershed of the significance); (labels, count).

    ``grow(mask)``: ``mask`` grown across what still joins one change (a strip of unseen wall:
    the pieces :func:`cystomap.compare.changes._join_pieces` joins there); blobs that touch
    once grown are not separate. ``stands(pieces, labels)``: whether each piece (flat pixels;
    ``labels``: the grid's labels with each piece as a new region of its own) would be reported
    on its own (a change by the pair's null that passes the checks); a region is split only
    into pieces that all would (a faint lesion in fragments, each too weak alone, or a lesion
    whose valley leaves a sliver at the edge of the compared wall, stays whole)."""
    from skimage.segmentation import watershed

    out = lab.copy()
    count = n
    flat_sig = sig.ravel()
    for r in range(1, n + 1):
        m = lab == r
        if not m.any():
            continue
        peak = float(np.percentile(sig[m], peak_percentile))
        blobs, k = label_wrapped(m & (sig >= 0.5 * peak))
        if k < 2:
            continue
        idx = [np.flatnonzero(blobs.ravel() == i) for i in range(1, k + 1)]
        tops = [float(flat_sig[p].max()) for p in idx]
        summits = [int(p[np.argmax(flat_sig[p])]) for p in idx]
        order = np.argsort(tops)[::-1]
        objects = [int(order[0])]
        for j in order[1:]:
            level = m & (sig >= 0.5 * tops[j])
            flat = label_wrapped(level if grow is None else grow(level))[0].ravel()
            mine = flat[summits[j]]  # > 0: the summit is above half of itself
            if any(flat[summits[o]] == mine for o in objects):
                continue  # joined to a stronger blob at half its own height: one change
            objects.append(int(j))
        # flooded over the grown region, so that parts of it joined across unseen wall go
        # to the object they belong to; while a piece would not be reported on its own, the
        # weakest such object is given back (the weakest of all when only the strongest
        # blob's piece fails)
        flood = m if grow is None else grow(m) | m
        while len(objects) > 1:
            markers = np.zeros(lab.shape, np.int32)
            for i, o in enumerate(objects, start=1):
                markers.ravel()[idx[o]] = i
            ws = watershed(-sig, markers, mask=flood, connectivity=2)
            ws[~m] = 0
            pieces = [np.flatnonzero(ws.ravel() == i) for i in range(1, len(objects) + 1)]
            trial = out.copy()
            for i, p in enumerate(pieces):
                trial.ravel()[p] = count + 1 + i
            ok = [True] * len(pieces) if stands is None else stands(pieces, trial)
            weak = [i for i, good in enumerate(ok) if not good]
            if not weak:
                for p in pieces[1:]:
                    count += 1
                    out.ravel()[p] = count
                break
            objects.pop(weak[-1] if weak[-1] > 0 else len(objects) - 1)
    return out, count


__all__ = ["separate_half_maxima"]
