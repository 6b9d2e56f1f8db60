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
between them stays above half their height), and so are blobs in parts of the region that
only its joining across unseen wall or of fragments made one (no valley lies between them).
"""

from __future__ import annotations

import numpy as np

from cystomap.compare.morphology import label_wrapped


def separate_half_maxima(sig: np.ndarray, lab: np.ndarray, n: int, peak_percentile: float,
                         ) -> tuple[np.ndarray, int]:
    """``lab`` (regions 1 … ``n`` on the grid of ``sig``) with every region whose half-maximum
    blobs are separate objects split into one region per object (the region's pixels go to
    the object they flow to: watershed of the significance); (labels, count)."""
    from skimage.segmentation import watershed

    out = lab.copy()
    count = n
    for r in range(1, n + 1):
        m = lab == r
        if not m.any():
            continue
        peak = float(np.percentile(sig[m], peak_percentile))
        blobs, k = label_wrapped(m & (sig >= 0.5 * peak))
        if k < 2:
            continue
        idx = [np.flatnonzero(blobs.ravel() == i) for i in range(1, k + 1)]
        flat_sig = sig.ravel()
        tops = [float(flat_sig[p].max()) for p in idx]
        summits = [int(p[np.argmax(flat_sig[p])]) for p in idx]
        # pieces the region joined across unseen wall (or as fragments) are not in one
        # connected part of it: a valley can only separate blobs of the same part
        parts = label_wrapped(m)[0].ravel()
        order = np.argsort(tops)[::-1]
        objects = [int(order[0])]
        for j in order[1:]:
            rivals = [o for o in objects if parts[summits[o]] == parts[summits[j]]]
            if not rivals:
                continue
            flat = label_wrapped(m & (sig >= 0.5 * tops[j]))[0].ravel()
            mine = flat[summits[j]]  # > 0: the summit is above half of itself
            if any((flat[idx[o]] == mine).any() for o in rivals):
                continue  # joined to a stronger blob at half its own height: one change
            objects.append(int(j))
        if len(objects) < 2:
            continue
        markers = np.zeros(lab.shape, np.int32)
        for i, o in enumerate(objects, start=1):
            markers.ravel()[idx[o]] = i
        ws = watershed(-sig, markers, mask=m, connectivity=2)
        for i in range(2, len(objects) + 1):
            count += 1
            out[ws == i] = count
    return out, count


__all__ = ["separate_half_maxima"]
