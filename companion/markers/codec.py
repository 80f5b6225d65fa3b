"""Decode sampled grids into dictionary markers, never guessing: the RS marker's one decoder.

Two steps, tried in order, over a batch of M sampled (N, N) grids
(1 black, 0 white, -1 unknown):

1. **Bounded-distance decoding of the whole codeword** (vectorised). The 84
   codeword cells (data and both RS parity copies; 132 for p = 4) of the 50
   markers under 4 rotations form a code of 200 words whose minimum distance
   is 22 (38 for p = 4), far more than the 14 of the 6 x 6 data alone,
   because the RS parity spreads every data difference over many cells. A
   grid is accepted as the nearest word when (a) its distance d1 over the
   known cells is at most t(k), the largest radius at which a grid of k
   random known cells would land within t of any of the 200 words with
   probability below ``false_accept_probability``, and (b) the runner-up is at
   least ``min_gap_cells`` further away. Scattered damage (a blob over the data,
   noise) is corrected here; this is where the per-code algebraic decoder is
   weak: each of the two RS(8, 6) codes corrects a single symbol, so a blob
   over two rows *and* two columns defeats both.
2. **Algebraic RS decoding** (``GridDecoder.decode_algebraic``) for damage
   concentrated in whole symbols (a strip over one data column and one
   parity copy): the row code and the column code are RS-decoded with unknown
   cells as erasures, each with the two parity copies merged and with each
   copy alone; a result counts only if its data is exactly a dictionary
   marker whose full codeword the known cells agree with (at most
   ``max_mismatch_fraction`` of them disagree). In the batch decoder it is
   accepted only when that marker is also the unique nearest word of step 1.

An undecodable grid is rejected: that is the detector's false-positive guard.
``reedsolo`` keeps module state while decoding: one decoder per thread.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from math import comb

import numpy as np
import reedsolo

from companion.markers.layout import UNKNOWN, MarkerLayout, bits_to_symbols, symbols_to_bits
from companion.params import require


@dataclass(frozen=True)
class DecoderParams:
    """Acceptance rules of the decoder.

    false_accept_probability: per grid, the chance that random cells are
        accepted by the bounded-distance step (it sets the radius t(k)).
    min_gap_cells: the runner-up word must be at least this many cells further.
    max_mismatch_fraction: the algebraic step's marker is refused when more
        than this share of the known codeword cells disagree with it.
    screen_max_mismatch_fraction: ``plausible``: a rough reading (one sample
        per cell) within this share of its known cells of some word.
    algebraic: also try the algebraic RS step on grids the first step rejects.
    """

    false_accept_probability: float = 1e-12
    min_gap_cells: int = 6
    max_mismatch_fraction: float = 0.25
    screen_max_mismatch_fraction: float = 0.3
    algebraic: bool = True

    def __post_init__(self):
        require(0.0 < self.false_accept_probability < 1e-3, "false_accept_probability", "in (0, 1e-3)",
                self.false_accept_probability)
        require(self.min_gap_cells >= 1, "min_gap_cells", ">= 1", self.min_gap_cells)
        require(0.0 <= self.max_mismatch_fraction < 0.5, "max_mismatch_fraction", "in [0, 0.5)",
                self.max_mismatch_fraction)
        require(0.0 <= self.screen_max_mismatch_fraction < 0.5, "screen_max_mismatch_fraction", "in [0, 0.5)",
                self.screen_max_mismatch_fraction)


@dataclass(frozen=True)
class DecodeResult:
    """A grid that decoded to a dictionary marker.

    rotation: k such that ``np.rot90(grid, k)`` is the upright marker
        (the marker appears rotated k x 90 deg clockwise in the grid).
    corrected: RS symbols that needed correction or erasure recovery (the
        fewer of the row and the column code's; see ``symbols_touched``).
    erased_cells: codeword cells (data and parity) that were unknown.
    mismatched_cells: known codeword cells that disagree with the marker.
    quality: fraction of codeword cells that are known and agree.
    """

    id: int
    symbol: str
    rotation: int
    corrected: int
    erased_cells: int
    mismatched_cells: int
    quality: float


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
    """Decodes sampled grids of one marker layout. Not thread-safe (``reedsolo``): one per thread."""

    def __init__(self, layout: MarkerLayout, params: DecoderParams | None = None):
        self.layout = layout
        self.params = params or DecoderParams()
        self._mask = layout.codeword_mask
        n_markers = len(layout.all_cells)
        # word w = rotation * n_markers + marker: the marker as it appears in a grid
        # that np.rot90(grid, rotation) turns upright
        self._words = np.concatenate([np.rot90(layout.all_cells, -k, axes=(1, 2))[:, self._mask]
                                      for k in range(4)]).astype(np.float32)
        self._words_t = np.ascontiguousarray(self._words.T)
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
                if n_words * total / 2.0 ** k > self.params.false_accept_probability:
                    break
                radius[k] = t
        return radius

    # ------------------------------------------------------------ batched decoding

    def rank(self, grids: np.ndarray) -> Ranking:
        """Distances of M grids (M, N, N) int8 to every word, reduced to the two nearest."""
        obs = grids[:, self._mask]
        known = (obs != UNKNOWN).astype(np.float32)
        black = (obs == 1).astype(np.float32)
        # Hamming distance over known cells: sum(o) + sum(known * w) - 2 o . w (one product: exact in float32)
        d = (known - 2 * black) @ self._words_t + black.sum(1)[:, None]
        order = np.argsort(d, axis=1, kind="stable")[:, :2]
        rows = np.arange(len(d))
        return Ranking(order[:, 0], order[:, 1], d[rows, order[:, 0]].round().astype(int),
                       d[rows, order[:, 1]].round().astype(int), known.sum(1).astype(int))

    def plausible(self, grids: np.ndarray) -> np.ndarray:
        """(M,) bool: grids (read roughly, e.g. one sample per cell) within ``screen_max_mismatch_fraction``
        of their known codeword cells of some word; a cheap screen before careful sampling and decoding."""
        grids = self._as_grids(grids)
        if len(grids) == 0:
            return np.zeros(0, bool)
        ranking = self.rank(grids)
        return (ranking.known > 0) & (ranking.d1 <= self.params.screen_max_mismatch_fraction * ranking.known)

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
        return (ranking.d1 <= radius) & (ranking.d2 >= ranking.d1 + self.params.min_gap_cells)

    def _nearest(self, ranking: Ranking, i: int) -> tuple[int, int]:
        """(marker id, rotation) of grid i's nearest word."""
        rotation, marker_id = divmod(int(ranking.best[i]), self._n_markers)
        return marker_id, rotation

    def _worth_algebraic(self, ranking: Ranking, i: int) -> bool:
        """Skip grids the algebraic step's own check would reject: its result must be the unique
        nearest word, and it rejects more than ``max_mismatch_fraction`` of the known cells
        disagreeing (d1 is a lower bound on that count)."""
        return bool(ranking.d2[i] > ranking.d1[i]
                    and ranking.d1[i] <= self.params.max_mismatch_fraction * ranking.known[i])

    def _algebraic(self, grid: np.ndarray, ranking: Ranking, i: int) -> DecodeResult | None:
        """The algebraic step, accepted only if it returns grid i's unique nearest word.

        Only that word's rotation is tried: any other answer would be refused.
        """
        if not (self.params.algebraic and self._worth_algebraic(ranking, i)):
            return None
        marker_id, rotation = self._nearest(ranking, i)
        if self._algebraic_upright(np.rot90(grid, rotation)) != marker_id:
            return None
        return self._result(grid, marker_id, rotation)

    # ------------------------------------------------------------ algebraic RS decoding

    def decode_algebraic(self, grid: np.ndarray, rotations: tuple[int, ...] = (0, 1, 2, 3)) -> DecodeResult | None:
        """Decode one sampled (N, N) int8 grid with the algebraic RS step alone, trying ``rotations``.

        Returns the marker only if a Reed-Solomon code recovers data that is
        exactly a dictionary marker and the known cells agree with that
        marker's full codeword, in exactly one marker over the rotations;
        otherwise None. Never a guess.
        """
        grid = np.asarray(grid, dtype=np.int8)
        found = [(marker_id, k) for k in rotations
                 if (marker_id := self._algebraic_upright(np.rot90(grid, k))) is not None]
        if len({marker_id for marker_id, _ in found}) != 1:
            return None
        return self._result(grid, *found[0])

    def _algebraic_upright(self, upright: np.ndarray) -> int | None:
        """The one marker the RS codes recover from an upright grid and its known cells confirm, or None."""
        candidates = dict.fromkeys(marker_id for data_bits in self._rs_candidates(upright)
                                   if (marker_id := self._dictionary_id(data_bits)) is not None)
        accepted = [marker_id for marker_id in candidates if self._agrees(upright, marker_id)]
        return accepted[0] if len(accepted) == 1 else None

    def _rs_candidates(self, upright: np.ndarray):
        """Yield (n, n) data bits decoded by the row code and by the column code.

        Each code is tried with the two parity copies merged and with each copy
        alone: an occluder over one side band turns that copy into errors, and
        the other copy alone then still decodes.
        """
        span = self.layout.data_span
        data = upright[span, span]
        for along_rows in (True, False):
            symbols_bits = data if along_rows else data.T
            near, far = self._parity_copies(upright, along_rows)
            for parity_bits in (merge_copies(near, far), near, far):
                symbols = self._rs_decode(np.concatenate([symbols_bits, parity_bits]))
                if symbols is not None:
                    bits = symbols_to_bits(symbols, self.layout.data_size)
                    yield bits if along_rows else bits.T

    def _parity_copies(self, upright: np.ndarray, along_rows: bool) -> tuple[np.ndarray, np.ndarray]:
        """The two (p, n) int8 copies of the row code's (or column code's) parity bits."""
        lay = self.layout
        copies = []
        for near in (True, False):
            index = [lay.parity_band(k, near) for k in range(lay.parity)]
            copies.append(upright[index, lay.data_span] if along_rows else upright[lay.data_span, index].T)
        return copies[0], copies[1]

    def _rs_decode(self, codeword_bits: np.ndarray) -> np.ndarray | None:
        """(n + p, n) bits with unknowns -> (n,) data symbols, or None if undecodable."""
        lay = self.layout
        erasures = np.flatnonzero((codeword_bits == UNKNOWN).any(axis=1))
        if len(erasures) > lay.parity:
            return None
        received = bits_to_symbols(np.where(codeword_bits == UNKNOWN, 0, codeword_bits))
        try:
            _, full, _ = lay.rs_codec.decode(bytearray(received.tolist()), erase_pos=erasures.tolist())
        except reedsolo.ReedSolomonError:
            return None
        full = np.array(full, dtype=np.int64)
        if lay.parity_of(full[:lay.data_size]).tolist() != full[lay.data_size:].tolist():
            return None  # reedsolo returned something that is not a codeword
        return full[:lay.data_size]

    def _dictionary_id(self, data_bits: np.ndarray) -> int | None:
        matches = np.flatnonzero((self.layout.dictionary.bits == data_bits).all(axis=(1, 2)))
        return int(matches[0]) if len(matches) else None

    def _agrees(self, upright: np.ndarray, marker_id: int) -> bool:
        """At most ``max_mismatch_fraction`` of the known codeword cells disagree with the marker's codeword."""
        cells = upright[self._mask]
        known = cells != UNKNOWN
        mismatched = int(np.count_nonzero(known & (cells != self.layout.all_cells[marker_id][self._mask])))
        return mismatched <= self.params.max_mismatch_fraction * np.count_nonzero(known)

    # ------------------------------------------------------------ the result

    def _result(self, grid: np.ndarray, marker_id: int, rotation: int) -> DecodeResult:
        """The DecodeResult of a grid read as marker ``marker_id`` at ``rotation`` (the only place one is built)."""
        upright_index, cells, mask = self._result_tables
        upright = np.ravel(grid)[upright_index[rotation]]  # np.rot90(grid, rotation), flattened
        known = upright != UNKNOWN
        agree = known & (upright == cells[marker_id])
        return DecodeResult(
            id=marker_id,
            symbol=self.layout.dictionary.symbol_of(marker_id),
            rotation=rotation,
            corrected=self.symbols_touched(~agree.reshape(grid.shape)),
            erased_cells=int(np.count_nonzero(mask & ~known)),
            mismatched_cells=int(np.count_nonzero(mask & known & ~agree)),
            quality=float(np.count_nonzero(mask & agree) / np.count_nonzero(mask)),
        )

    @cached_property
    def _result_tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(4, N * N) flat index of np.rot90(grid, k) in the grid, (markers, N * N) int8 cells of each marker,
        (N * N,) the codeword mask, all flattened."""
        n = self.layout.n_cells
        index = np.arange(n * n).reshape(n, n)
        return (np.stack([np.rot90(index, k).ravel() for k in range(4)]),
                self.layout.all_cells.reshape(len(self.layout.all_cells), -1).astype(np.int8), self._mask.ravel())

    def symbols_touched(self, bad: np.ndarray) -> int:
        """RS symbols that needed correction or erasure recovery, the fewer of the two codes.

        bad: (N, N) bool over the upright grid, True for a wrong or unknown cell.
        A data symbol is touched if any of its cells is bad; a parity symbol if
        both of its copies are (one intact copy is enough).
        """
        touched = bad.ravel()[self._symbol_cells].any(axis=-1)  # (2, n + 2p): row code, column code
        n, p = self.layout.data_size, self.layout.parity
        counts = (np.count_nonzero(touched[:, :n], axis=1)
                  + np.count_nonzero(touched[:, n:n + p] & touched[:, n + p:], axis=1))
        return int(counts.min())

    @cached_property
    def _symbol_cells(self) -> np.ndarray:
        """(2, n + 2p, n) flat grid indices of the cells of each symbol: the row code's (data rows, then each
        parity symbol's near copy, then its far copy), then the column code's, the same along columns."""
        lay = self.layout
        n_cells, span = lay.n_cells, lay.data_span
        rows = ([np.arange(n_cells)[span][i] for i in range(lay.data_size)]
                + [lay.parity_band(k, True) for k in range(lay.parity)]
                + [lay.parity_band(k, False) for k in range(lay.parity)])
        along = np.arange(n_cells)[span]
        by_rows = np.array([row * n_cells + along for row in rows])
        by_columns = np.array([along * n_cells + column for column in rows])
        return np.stack([by_rows, by_columns])


def merge_copies(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Bitwise merge of two copies: a bit known in either; copies that disagree -> unknown."""
    merged = np.where(a == UNKNOWN, b, a)
    merged[(a != UNKNOWN) & (b != UNKNOWN) & (a != b)] = UNKNOWN
    return merged
