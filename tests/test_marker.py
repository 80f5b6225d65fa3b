"""The RS marker layout and codec: round trips, erasure and error recovery, no wrong ids."""
import itertools

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from companion.markers.codec import DecoderParams, GridDecoder
from companion.markers.layout import UNKNOWN, MarkerLayout, MarkerLayoutError, marker_image
from companion.params import ParamsError

LAYOUTS = {p: MarkerLayout(p) for p in (2, 4)}
DECODERS = {p: GridDecoder(layout) for p, layout in LAYOUTS.items()}
IDS = range(50)


def grid_of(layout, marker_id, rotation=0):
    """The sampled grid of an upright marker seen rotated `rotation` x 90 deg clockwise."""
    return np.rot90(layout.cells(marker_id).astype(np.int8), -rotation).copy()


def data_rows(layout):
    return [layout.data_origin + i for i in range(layout.data_size)]


@pytest.mark.parametrize("parity, cells", [(2, 14), (4, 18)])
def test_grid_sizes(parity, cells):
    layout = LAYOUTS[parity]
    assert layout.n_cells == cells
    assert layout.codeword_mask.sum() == 36 + 4 * parity * 6
    assert len(layout.circles) == 12


def test_unsupported_parity_is_an_error():
    with pytest.raises(MarkerLayoutError, match="parity"):
        MarkerLayout(3)


@pytest.mark.parametrize("parity", [2, 4])
def test_circles_sit_in_white_corners_clear_of_every_cell(parity):
    """Every circle, with a quarter-cell margin, lies in cells that are always white."""
    layout = LAYOUTS[parity]
    for u, v, radius in layout.circles:
        lo = np.floor([u - radius - 0.25, v - radius - 0.25]).astype(int)
        hi = np.ceil([u + radius + 0.25, v + radius + 0.25]).astype(int)
        assert layout.white_mask[lo[1]:hi[1], lo[0]:hi[0]].all()


@pytest.mark.parametrize("parity", [2, 4])
@pytest.mark.parametrize("rotation", range(4))
def test_every_symbol_round_trips_in_every_rotation(parity, rotation):
    layout = LAYOUTS[parity]
    for marker_id in IDS:
        result = DECODERS[layout.parity].decode_algebraic(grid_of(layout, marker_id, rotation))
        assert result is not None and result.id == marker_id
        assert result.rotation == rotation and result.corrected == 0 and result.quality == 1.0


def occlude_lines(grid, lines, along_rows, value):
    occluded = grid.copy()
    for line in lines:
        if along_rows:
            occluded[line, :] = value
        else:
            occluded[:, line] = value
    return occluded


@pytest.mark.parametrize("parity, count", [(2, 1), (4, 2)])
@pytest.mark.parametrize("along_rows", [True, False])
def test_any_occluded_data_rows_or_columns_are_recovered(parity, count, along_rows):
    """Every choice of `count` data rows (or columns), read as unknown, as black or as white."""
    layout = LAYOUTS[parity]
    for marker_id in (0, 13, 31, 49):
        grid = grid_of(layout, marker_id)
        for lines in itertools.combinations(data_rows(layout), count):
            for value in (UNKNOWN, 0, 1):
                result = DECODERS[layout.parity].decode_algebraic(occlude_lines(grid, lines, along_rows, value))
                assert result is not None and result.id == marker_id, (lines, value)


def side_band(layout, side):
    """(N, N) mask of one whole side: its parity band and gap, the full width of the grid."""
    mask = np.zeros((layout.n_cells,) * 2, bool)
    depth = layout.inner_origin
    {"top": lambda: mask.__setitem__(np.s_[:depth, :], True),
     "bottom": lambda: mask.__setitem__(np.s_[-depth:, :], True),
     "left": lambda: mask.__setitem__(np.s_[:, :depth], True),
     "right": lambda: mask.__setitem__(np.s_[:, -depth:], True)}[side]()
    return mask


@pytest.mark.parametrize("parity, count", [(2, 1), (4, 2)])
def test_lost_side_bands_are_recovered(parity, count):
    layout = LAYOUTS[parity]
    for marker_id in (2, 27, 44):
        grid = grid_of(layout, marker_id)
        for sides in itertools.combinations(["top", "right", "bottom", "left"], count):
            if {"top", "bottom"} <= set(sides) or {"left", "right"} <= set(sides):
                continue  # both copies of one code's parity gone
            for value in (UNKNOWN, 0, 1):
                lost = grid.copy()
                for side in sides:
                    lost[side_band(layout, side)] = value
                result = DECODERS[layout.parity].decode_algebraic(lost)
                assert result is not None and result.id == marker_id, (sides, value)


def test_three_erased_rows_exceed_p2_and_are_reported_undecodable():
    layout = LAYOUTS[2]
    for marker_id in IDS:
        grid = occlude_lines(grid_of(layout, marker_id), data_rows(layout)[:3], True, UNKNOWN)
        assert DECODERS[layout.parity].decode_algebraic(grid) is None


@settings(max_examples=300, deadline=None)
@given(marker_id=st.integers(0, 49), parity=st.sampled_from([2, 4]), rotation=st.integers(0, 3),
       corrupted=st.integers(1, 60), seed=st.integers(0, 2**32 - 1))
def test_corruption_never_yields_a_wrong_marker(marker_id, parity, rotation, corrupted, seed):
    """Random cells flipped or erased: the decoder answers the true marker or nothing."""
    layout = LAYOUTS[parity]
    rng = np.random.default_rng(seed)
    grid = grid_of(layout, marker_id, rotation)
    cells = rng.choice(grid.size, size=min(corrupted, grid.size), replace=False)
    grid.flat[cells] = rng.choice([UNKNOWN, 0, 1], size=len(cells))
    result = DECODERS[layout.parity].decode_algebraic(grid)
    assert result is None or (result.id == marker_id and result.rotation == rotation)


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), parity=st.sampled_from([2, 4]), unknown=st.floats(0, 0.5))
def test_random_grids_never_decode(seed, parity, unknown):
    layout = LAYOUTS[parity]
    rng = np.random.default_rng(seed)
    grid = rng.integers(0, 2, size=(layout.n_cells,) * 2).astype(np.int8)
    grid[rng.random(grid.shape) < unknown] = UNKNOWN
    assert DECODERS[layout.parity].decode_algebraic(grid) is None


def test_marker_image_cells_and_circles():
    layout = LAYOUTS[2]
    image = marker_image(layout, 5, px_per_cell=10, quiet_zone_cells=1)
    assert image.shape == (160, 160) and image.dtype == np.uint8
    cells = image[15:150:10, 15:150:10] == 0  # centre pixel of each cell
    centres = np.stack(np.meshgrid(np.arange(14) + 0.5, np.arange(14) + 0.5), axis=-1)  # (v, u) -> (u, v)
    under_circle = np.zeros(cells.shape, bool)
    for u, v, radius in layout.circles:
        under_circle |= np.hypot(centres[..., 0] - u, centres[..., 1] - v) < radius + 0.1
    np.testing.assert_array_equal(cells[~under_circle], layout.cells(5).astype(bool)[~under_circle])
    assert cells[under_circle].any()
    u, v, _ = layout.circles[0]
    assert image[int((v + 1) * 10), int((u + 1) * 10)] == 0  # a large circle's centre is black


@pytest.mark.parametrize("parity", [2, 4])
def test_parity_copies_sit_where_the_spec_puts_them(parity):
    """docs/marker-spec.md: symbol k is k cells from the gap, in the band before and after the data;
    the data starts one cell inside the inner marker, which starts at p + 1."""
    layout = LAYOUTS[parity]
    n, last = layout.data_size, layout.n_cells - 1
    assert layout.data_origin == parity + 2
    data = slice(parity + 2, parity + 2 + n)
    for marker_id in (0, 31):
        cells = layout.cells(marker_id)
        rows, columns = layout.parity_symbols(layout.dictionary.bits[marker_id])
        for k in range(parity):
            row_bits = ((rows[k] >> np.arange(n - 1, -1, -1)) & 1).tolist()
            column_bits = ((columns[k] >> np.arange(n - 1, -1, -1)) & 1).tolist()
            near, far = parity - 1 - k, last - parity + 1 + k
            assert cells[near, data].tolist() == row_bits == cells[far, data].tolist()
            assert cells[data, near].tolist() == column_bits == cells[data, far].tolist()


def test_both_decoding_steps_report_the_same_result():
    """A strip over one data column: the whole-codeword and the algebraic step agree on every field."""
    layout, decoder = LAYOUTS[2], DECODERS[2]
    grid = grid_of(layout, 9, rotation=1)
    grid[:, layout.data_origin + 2] = UNKNOWN
    (whole,) = decoder.decode(grid)
    assert whole == decoder.decode_algebraic(grid)
    assert (whole.id, whole.rotation, whole.corrected) == (9, 1, 1)


def test_decoder_params_are_checked_by_name():
    with pytest.raises(ParamsError, match="min_gap_cells"):
        DecoderParams(min_gap_cells=0)
    with pytest.raises(ParamsError, match="max_mismatch_fraction"):
        DecoderParams(max_mismatch_fraction=0.7)
