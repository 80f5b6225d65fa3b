"""Detector stage: decode sampled grids into dictionary markers, never guessing.

Two decoders, tried in order, over a batch of M sampled (N, N) grids:

1. **Bounded-distance decoding of the whole codeword** (vectorised). The 84
   codeword cells (data and both RS parity copies; 132 for p = 4) of the 50
   markers under 4 rotations form a code of 200 words whose minimum distance
   is 22 (38 for p = 4), far more than the 14 of the 6 x 6 data alone,
   because the RS parity spreads every data difference over many cells. A
   grid is accepted as the nearest word when (a) its distance d1 over the
   known cells is at most t(k), the largest radius at which a grid of k
   random known cells would land within t of any of the 200 words with
   probability below ``false_accept_bound``, and (b) the runner-up is at
   least ``min_gap`` further away. Scattered damage (a blob over the data,
   noise) is corrected here; this is where the per-code algebraic decoder is
   weak: each of the two RS(8, 6) codes corrects a single symbol, so a blob
   over two rows *and* two columns defeats both.
2. **Algebraic RS decoding** (``MarkerLayout.decode``, the lead's decoder)
   for damage concentrated in whole symbols (a strip over one data column
   and one parity copy), accepted only when the marker it returns is also the
   unique nearest word of step 1.

An undecodable grid is rejected: that is the detector's false-positive guard.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from math import comb

import numpy as np

from companion.markers.layout import UNKNOWN, DecodeResult, MarkerLayout

DEFAULT_FALSE_ACCEPT_BOUND = 1e-12


@dataclass(frozen=True)
class Ranking:
    """Nearest dictionary words of M grids (over the known codeword cells).

    best, second: (M,) indices into the (rotation, marker) word table.
    d1, d2: (M,) distances to them; known: (M,) known codeword cells.
    """

    best: np.ndarray
    second: np.ndarray
    d1: np.ndarray
    d2: np.ndarray
    known: np.ndarray


class GridDecoder:
    """Decodes sampled grids of one marker layout.

    false_accept_bound: per-grid probability that a grid of random cells is
        accepted by the bounded-distance decoder.
    min_gap: the runner-up word must be at least this many cells further.
    algebraic: also try the per-code RS decoder on grids the first step rejects.
    """

    def __init__(self, layout: MarkerLayout, false_accept_bound: float = DEFAULT_FALSE_ACCEPT_BOUND,
                 min_gap: int = 6, algebraic: bool = True):
        self.layout = layout
        self.false_accept_bound = false_accept_bound
        self.min_gap = min_gap
        self.algebraic = algebraic
        self._mask = layout.codeword_mask
        n_markers = len(layout.all_cells)
        # word w = rotation * n_markers + marker: the marker as it appears in a grid
        # that np.rot90(grid, rotation) turns upright
        self._words = np.concatenate([np.rot90(layout.all_cells, -k, axes=(1, 2))[:, self._mask]
                                      for k in range(4)]).astype(np.float32)
        self._n_markers = n_markers

    @cached_property
    def min_distance(self) -> int:
        """Minimum Hamming distance between any two words (markers x rotations)."""
        w = self._words
        d = w.sum(1)[:, None] + w.sum(1)[None, :] - 2 * w @ w.T
        np.fill_diagonal(d, np.inf)
        return int(d.min())

    @cached_property
    def radius_by_known(self) -> np.ndarray:
        """(K + 1,) int: the acceptance radius t(k) for k known cells (-1: never accept).

        t(k) is the largest t with  W * sum_{i <= t} C(k, i) / 2^k <= bound
        (W words, each cell a fair coin), capped below half the minimum
        distance so that an accepted word is always the unique nearest.
        """
        n_words = len(self._words)
        cap = (self.min_distance - 1) // 2 - 2
        radius = np.full(self._words.shape[1] + 1, -1)
        for k in range(len(radius)):
            total = 0
            for t in range(0, cap + 1):
                total += comb(k, t)
                if n_words * total / 2.0 ** k > self.false_accept_bound:
                    break
                radius[k] = t
        return radius

    def rank(self, grids: np.ndarray) -> Ranking:
        """Distances of M grids (M, N, N) int8 to every word, reduced to the two nearest."""
        obs = grids[:, self._mask]
        known = (obs != UNKNOWN).astype(np.float32)
        black = (obs == 1).astype(np.float32)
        # Hamming distance over known cells: sum(o) + sum(known * w) - 2 o . w
        d = black.sum(1)[:, None] + known @ self._words.T - 2 * black @ self._words.T
        order = np.argsort(d, axis=1, kind="stable")[:, :2]
        rows = np.arange(len(d))
        return Ranking(order[:, 0], order[:, 1], d[rows, order[:, 0]].round().astype(int),
                       d[rows, order[:, 1]].round().astype(int), known.sum(1).astype(int))

    def plausible(self, grids: np.ndarray, max_fraction: float = 0.3) -> np.ndarray:
        """(M,) bool: grids (read roughly, e.g. one sample per cell) within ``max_fraction`` of their
        known codeword cells of some word; a cheap screen before careful sampling and decoding."""
        grids = self._as_grids(grids)
        if len(grids) == 0:
            return np.zeros(0, bool)
        ranking = self.rank(grids)
        return (ranking.known > 0) & (ranking.d1 <= max_fraction * ranking.known)

    def decode(self, grids: np.ndarray) -> list[DecodeResult | None]:
        """Decode M sampled grids (M, N, N) int8 (1 black, 0 white, -1 unknown), each on its own."""
        grids = self._as_grids(grids)
        if len(grids) == 0:
            return []
        ranking = self.rank(grids)
        accepted = self._accepted(ranking)
        return [self._result(grid, *self._nearest(ranking, i)) if accepted[i] else self._algebraic(grid, ranking, i)
                for i, grid in enumerate(grids)]

    def decode_groups(self, grids: np.ndarray, groups: np.ndarray) -> dict[int, DecodeResult]:
        """Decode candidates each read one or more ways (e.g. with more or fewer erasures).

        grids: (G, N, N) int8, groups: (G,) the candidate of each reading, in
        order of preference. The bounded-distance step runs on every reading at
        once before the (slower) algebraic step on any; per candidate the first
        reading that decodes wins. Returns {candidate: result} for those decoded.
        """
        grids = self._as_grids(grids)
        groups = np.asarray(groups)
        if len(grids) == 0:
            return {}
        ranking = self.rank(grids)
        accepted = self._accepted(ranking)
        results: dict[int, DecodeResult] = {}
        for i in np.flatnonzero(accepted):
            if int(groups[i]) not in results:
                results[int(groups[i])] = self._result(grids[i], *self._nearest(ranking, i))
        for i, grid in enumerate(grids):
            if int(groups[i]) not in results:
                result = self._algebraic(grid, ranking, i)
                if result is not None:
                    results[int(groups[i])] = result
        return results

    def _as_grids(self, grids: np.ndarray) -> np.ndarray:
        return np.asarray(grids, dtype=np.int8).reshape(-1, self.layout.n_cells, self.layout.n_cells)

    def _accepted(self, ranking: Ranking) -> np.ndarray:
        radius = self.radius_by_known[ranking.known]
        return (ranking.d1 <= radius) & (ranking.d2 >= ranking.d1 + self.min_gap)

    def _nearest(self, ranking: Ranking, i: int) -> tuple[int, int]:
        """(marker id, rotation) of grid i's nearest word."""
        rotation, marker_id = divmod(int(ranking.best[i]), self._n_markers)
        return marker_id, rotation

    def _worth_algebraic(self, ranking: Ranking, i: int) -> bool:
        """Skip grids the RS decoder's own check would reject: its result must be the unique
        nearest word, and the layout rejects more than ``max_mismatch_fraction`` of the known
        cells disagreeing (d1 is a lower bound on that count)."""
        return bool(ranking.d2[i] > ranking.d1[i]
                    and ranking.d1[i] <= self.layout.max_mismatch_fraction * ranking.known[i])

    def _algebraic(self, grid: np.ndarray, ranking: Ranking, i: int) -> DecodeResult | None:
        """The lead's RS decoder, accepted only if it returns grid i's unique nearest word.

        Only that word's rotation is tried: any other answer would be refused.
        """
        if not (self.algebraic and self._worth_algebraic(ranking, i)):
            return None
        marker_id, rotation = self._nearest(ranking, i)
        result = self.layout.decode(grid, rotations=(rotation,))
        if result is None or result.id != marker_id:
            return None
        return self._result(grid, marker_id, rotation)

    def _result(self, grid: np.ndarray, marker_id: int, rotation: int) -> DecodeResult:
        upright = np.rot90(grid, rotation)
        expected = self.layout.all_cells[marker_id].astype(np.int8)
        mask = self._mask
        known = upright != UNKNOWN
        wrong = known & (upright != expected)
        agree = known & (upright == expected)
        return DecodeResult(
            id=marker_id,
            symbol=self.layout.dictionary.symbol_of(marker_id),
            rotation=rotation,
            corrected=self.symbols_touched(~agree),
            erased_cells=int(np.count_nonzero(mask & ~known)),
            mismatched_cells=int(np.count_nonzero(mask & wrong)),
            quality=float(np.count_nonzero(mask & agree) / np.count_nonzero(mask)),
        )

    def symbols_touched(self, bad: np.ndarray) -> int:
        """RS symbols that needed correction or erasure recovery, the fewer of the two codes.

        bad: (N, N) bool over the upright grid, True for a wrong or unknown cell.
        A data symbol is touched if any of its cells is bad; a parity symbol if
        both of its copies are (one intact copy is enough).
        """
        lay = self.layout
        n, p, size = lay.data_size, lay.parity, lay.n_cells
        r0 = lay.inner_origin + 1
        span = slice(r0, r0 + n)
        counts = []
        for b in (bad, bad.T):  # row code, then column code (columns as rows)
            data = int(np.count_nonzero(b[span, span].any(axis=1)))
            # parity symbol k: near copy at row p - 1 - k, far copy at row N - p + k
            parity = sum(bool(b[p - 1 - k, span].any() and b[size - p + k, span].any()) for k in range(p))
            counts.append(data + parity)
        return min(counts)
