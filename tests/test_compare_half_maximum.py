"""Regions split where their half maxima are separate objects
(:func:`cystomap.compare.half_maximum.separate_half_maxima`)."""

from __future__ import annotations

import numpy as np

from cystomap.compare.half_maximum import separate_half_maxima


def _blob(shape: tuple[int, int], r: float, c: float, sigma: float) -> np.ndarray:
    rows, cols = np.mgrid[:shape[0], :shape[1]]
    return np.exp(-((rows - r) ** 2 + (cols - c) ** 2) / (2 * sigma ** 2))


def test_two_peaks_apart_at_their_own_half_maxima_are_split() -> None:
    """A peak of 100 and one of 60 on a plateau of 20: at 30 (half the weaker peak) they are
    not connected, so they are two changes; each pixel goes to the peak it flows to."""
    shape = (60, 120)
    sig = 20 + 80 * _blob(shape, 30, 30, 5) + 40 * _blob(shape, 30, 90, 4)
    lab = np.ones(shape, np.int32)
    out, n = separate_half_maxima(sig, lab, 1, 99.0)
    assert n == 2
    assert out[30, 30] != out[30, 90]
    assert set(np.unique(out)) == {1, 2}


def test_lobes_joined_above_half_their_height_stay_one() -> None:
    """Two lobes of one lesion (100 and 80, 20 px apart) whose valley (44.6) stays above half
    of the weaker lobe: one change, though the valley is below half the region's peak (its
    half-maximum blobs fall apart); 22 px apart the valley (33.5) is below half of both:
    two changes."""
    shape = (60, 120)
    for gap, changes in ((20, 1), (22, 2)):
        sig = 100 * _blob(shape, 30, 50, 6) + 80 * _blob(shape, 30, 50 + gap, 6)
        lab = (sig > 10).astype(np.int32)  # the cluster above a candidate level
        out, n = separate_half_maxima(sig, lab, 1, 99.0)
        assert n == changes
        assert (out[lab > 0] > 0).all() and (out[lab == 0] == 0).all()


def test_seam_wrapping_blob_is_one_object() -> None:
    """A peak across the atlas seam (half in the first columns, half in the last) and a weaker
    one elsewhere: two changes, the seam's halves one of them."""
    shape = (40, 200)
    sig = 10 + 90 * (_blob(shape, 20, 0, 4) + _blob(shape, 20, 200, 4)) + 50 * _blob(shape, 20, 100, 4)
    lab = np.ones(shape, np.int32)
    out, n = separate_half_maxima(sig, lab, 1, 99.0)
    assert n == 2
    assert out[20, 0] == out[20, 199] != out[20, 100]


def test_pieces_too_weak_alone_or_joined_across_unseen_wall_stay_one() -> None:
    """The two peaks of the first test stay one region when the weaker one's piece would not
    be reported on its own (a faint lesion in fragments), or when the wall between them is grown
    over (a strip of unseen wall between two halves of one lesion)."""
    shape = (60, 120)
    sig = 20 + 80 * _blob(shape, 30, 30, 5) + 40 * _blob(shape, 30, 90, 4)
    lab = np.ones(shape, np.int32)
    strong = sig.ravel() >= 90
    _, n = separate_half_maxima(sig, lab, 1, 99.0,
                                stands=lambda pieces, _: [bool(strong[p].any()) for p in pieces])
    assert n == 1
    _, n = separate_half_maxima(sig, lab, 1, 99.0, grow=lambda m: m | (sig > 0))
    assert n == 1
    _, n = separate_half_maxima(sig, lab, 1, 99.0, grow=lambda m: m,
                                stands=lambda pieces, _: [True] * len(pieces))
    assert n == 2
