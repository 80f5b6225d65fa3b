"""The detector's small numeric helpers (homographies, image sampling, the decoder's symbol count) against
independent computations: the fast paths the circles path uses must give the same numbers."""
from __future__ import annotations

import numpy as np
import pytest

from companion.detect import homography, sampling
from companion.markers.codec import GridDecoder
from companion.markers.layout import UNKNOWN, MarkerLayout


def by_hand(H: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(K, 2) grid points through one (3, 3) homography, written out: (x, y) = (H (u, v, 1))[:2] / w."""
    p = np.column_stack([uv, np.ones(len(uv))]) @ H.T
    return p[:, :2] / p[:, 2:]


def random_homographies(rng, m: int) -> np.ndarray:
    H = np.zeros((m, 3, 3))
    H[:, 0, 0], H[:, 1, 1] = rng.uniform(6, 14, m), rng.uniform(6, 14, m)
    H[:, 0, 1], H[:, 1, 0] = rng.uniform(-3, 3, m), rng.uniform(-3, 3, m)
    H[:, :2, 2] = rng.uniform(50, 300, (m, 2))
    H[:, 2, :2] = rng.uniform(-0.01, 0.01, (m, 2))
    H[:, 2, 2] = 1.0
    return H


@pytest.mark.parametrize("m", [1, 2, 4, 5, 9])
def test_batched_projection_of_few_and_many_homographies_agrees_with_the_formula(m):
    rng = np.random.default_rng(m)
    H = random_homographies(rng, m)
    shared = rng.uniform(0, 16, (30, 2))
    each = rng.uniform(0, 16, (m, 30, 2))
    np.testing.assert_allclose(homography.project(H, shared), np.stack([by_hand(h, shared) for h in H]), atol=1e-9)
    np.testing.assert_allclose(homography.project(H, each), np.stack([by_hand(h, uv) for h, uv in zip(H, each)]),
                               atol=1e-9)
    # a homography that could not be built projects to NaN, the others are untouched
    H[0] = np.nan
    projected = homography.project(H, shared)
    assert np.isnan(projected[0]).all() and np.isfinite(projected[1:]).all()


@pytest.mark.parametrize("m", [1, 3, 6])
def test_a_point_at_the_horizon_is_not_a_finite_pixel(m):
    H = np.repeat(np.array([[10.0, 0.0, 100.0], [0.0, 10.0, 100.0], [0.5, 0.0, 1.0]])[None], m, axis=0)
    uv = np.array([[-2.0, 3.0], [1.0, 1.0]])  # w = 0.5 u + 1: 0 at u = -2
    projected = homography.project(H, uv)
    assert not np.isfinite(projected[:, 0]).any()
    np.testing.assert_allclose(projected[:, 1], np.repeat(by_hand(H[0], uv[1:]), m, axis=0), atol=1e-9)


def test_determinant_and_inverse_of_three_by_three_matrices_match_numpy():
    rng = np.random.default_rng(0)
    for M in rng.normal(size=(200, 3, 3)):
        assert homography.det3(M) == pytest.approx(np.linalg.det(M), rel=1e-9, abs=1e-12)
        np.testing.assert_allclose(homography.inv3(M), np.linalg.inv(M), rtol=1e-8, atol=1e-8)


def test_affine_fit_is_the_least_squares_solution_for_any_set_of_points_even_repeated():
    rng = np.random.default_rng(1)
    grid = rng.uniform(0, 16, (7, 2))
    for k in (3, 4, 7):
        for _ in range(3):  # the same grid points again (its solver is cached) with new image points
            image = rng.uniform(0, 600, (k, 2))
            design = np.column_stack([grid[:k], np.ones(k)])
            A, *_ = np.linalg.lstsq(design, image, rcond=None)  # [x y] = [u v 1] A
            H = homography.fit_affine(grid[:k], image)
            np.testing.assert_allclose(H[:2], A.T, atol=1e-8)
            np.testing.assert_array_equal(H[2], [0.0, 0.0, 1.0])


def test_fit_errors_of_all_points_and_of_the_last_ones_match_two_separate_measurements():
    rng = np.random.default_rng(2)
    H = random_homographies(rng, 1)[0]
    grid = rng.uniform(0, 16, (9, 2))
    points = by_hand(H, grid) + rng.normal(0, 1.0, (9, 2))
    for tail in (1, 3, 9):
        both = homography.fit_errors_cells(H, grid, points, tail)
        assert both[0] == pytest.approx(homography.fit_error_cells(H, grid, points), rel=1e-12)
        assert both[1] == pytest.approx(homography.fit_error_cells(H, grid[-tail:], points[-tail:]), rel=1e-12)
    assert homography.fit_errors_cells(np.full((3, 3), np.nan), grid, points, 3) == (np.inf, np.inf)
    # a map that scales cells to 7 px squares: 7 px a cell, 0 in a flat map
    assert homography.cell_px_at(np.array([5.0, 5.0]), np.array([12.0, 5.0]), np.array([5.0, 12.0])) == 7.0
    assert np.isnan(homography.cell_px_at(np.array([5.0, 5.0]), np.array([12.0, 5.0]), np.array([19.0, 5.0])))


def test_sampling_reads_pixels_and_marks_points_off_the_image():
    image = (np.arange(20 * 30) % 251).astype(np.uint8).reshape(20, 30)
    xy = np.array([[0.0, 0.0], [29.0, 19.0], [7.0, 4.0], [29.01, 3.0], [-0.01, 3.0], [3.0, 19.5],
                   [np.nan, 2.0], [np.inf, 2.0]])
    values, inside = sampling.sample_image(image, xy)
    np.testing.assert_array_equal(inside, [True, True, True, False, False, False, False, False])
    np.testing.assert_array_equal(values[:3], [image[0, 0], image[19, 29], image[4, 7]])
    assert np.isnan(values[3:]).all()
    values, inside = sampling.sample_image(image, np.zeros((3, 0, 2)))
    assert values.shape == inside.shape == (3, 0)


@pytest.mark.parametrize("parity", [2, 4])
def test_every_cell_reads_the_mean_of_its_own_block(parity):
    """An image of 10 px blocks, one gray level per cell, read through the map cell (u, v) -> (10 u, 10 v)
    shifted by 5 px: each cell's mean is its block's level, and cells past the image are not inside."""
    n = MarkerLayout(parity=parity).n_cells
    rng = np.random.default_rng(parity)
    levels = rng.integers(0, 256, (n, n)).astype(np.uint8)
    image = np.kron(levels, np.ones((10, 10), np.uint8))[:, : 10 * n - 20]  # the last two columns cut off
    image = np.pad(image, ((5, 0), (5, 0)), mode="edge")
    H = np.array([[[10.0, 0.0, 5.0], [0.0, 10.0, 5.0], [0.0, 0.0, 1.0]]])
    cells = sampling.sample_cells(image, H, n)
    np.testing.assert_array_equal(cells.inside[0, :, : n - 2], True)
    np.testing.assert_array_equal(cells.inside[0, :, n - 2:], False)
    np.testing.assert_array_equal(cells.mean[0, :, : n - 2], levels[:, : n - 2].astype(np.float32))


def reference_symbols_touched(layout: MarkerLayout, bad: np.ndarray) -> int:
    """The fewer touched RS symbols of the row and the column code, cell by cell (docs/marker-spec.md)."""
    counts = []
    data = np.arange(layout.n_cells)[layout.data_span]
    for b in (bad, bad.T):
        touched = sum(any(b[row, col] for col in data) for row in data)
        for k in range(layout.parity):
            near, far = layout.parity_band(k, True), layout.parity_band(k, False)
            touched += any(b[near, col] for col in data) and any(b[far, col] for col in data)
        counts.append(touched)
    return min(counts)


@pytest.mark.parametrize("parity, dictionary", [(2, "6x6"), (4, "6x6"), (2, "5x5"), (4, "8x8")])
def test_symbols_touched_counts_like_the_cell_by_cell_reference(parity, dictionary):
    layout = MarkerLayout(parity=parity, dictionary=dictionary)
    decoder = GridDecoder(layout)
    rng = np.random.default_rng(parity)
    for _ in range(300):
        bad = rng.random((layout.n_cells, layout.n_cells)) < rng.uniform(0.0, 0.2)
        assert decoder.symbols_touched(bad) == reference_symbols_touched(layout, bad)


def test_the_probe_shares_are_those_of_its_own_grid():
    """Per candidate: border_black = share of the readable border cells read dark, gap_white = share of the
    readable gap-ring cells read light, dark_codeword likewise over the codeword cells; hidden cells unread."""
    layout = MarkerLayout(parity=2)
    probe = sampling.CellProbe(layout)
    border, gap, codeword = layout.border_mask, sampling.gap_ring_mask(layout), layout.codeword_mask
    rng = np.random.default_rng(5)
    image = rng.integers(0, 256, (240, 320)).astype(np.uint8)
    H = random_homographies(rng, 3) * [[[0.6], [0.6], [1.0]]]
    H[2, :2, 2] = [300.0, 200.0]  # partly off the image
    hidden = rng.random((3, layout.n_cells, layout.n_cells)) < 0.2
    reading = probe.read(image, H, hidden)
    assert (reading.grid[hidden] == UNKNOWN).all()
    for i, grid in enumerate(reading.grid):
        def share(mask, value):
            cells = grid[mask]
            readable = cells != UNKNOWN
            return np.count_nonzero(cells[readable] == value) / max(np.count_nonzero(readable), 1)
        assert reading.border_black[i] == pytest.approx(share(border, 1), abs=1e-12)
        assert reading.gap_white[i] == pytest.approx(share(gap, 0), abs=1e-12)
        assert reading.dark_codeword[i] == pytest.approx(share(codeword, 1), abs=1e-12)
