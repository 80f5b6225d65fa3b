"""The frozen dictionaries: stable ids, distances as documented, identical to their generator."""
import re
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.markers.dictionary import SYMBOLS, DictionaryError, load_dictionary

DOCS = Path(__file__).resolve().parents[1] / "docs"
SPEC = DOCS / "marker-spec.md"
sys.path.insert(0, str(DOCS / "tools"))  # the dictionary search is a development tool, not package code
from dictionary_search import PRESETS, min_distance, search  # noqa: E402


def test_fifty_unique_symbols_with_stable_ids():
    assert len(SYMBOLS) == len(set(SYMBOLS)) == 50
    dictionary = load_dictionary("6x6")
    assert dictionary.id_of("A") == 0 and dictionary.id_of("Z") == 25
    assert dictionary.id_of("0") == 26 and dictionary.id_of("9") == 35
    assert dictionary.symbol_of(36) == "UP" and dictionary.symbol_of(49) == "STAR"
    assert dictionary.id_of("home") == dictionary.id_of("HOME")


def test_unknown_symbol_and_dictionary_are_clear_errors():
    with pytest.raises(DictionaryError, match="unknown symbol 'QQ'"):
        load_dictionary("6x6").id_of("QQ")
    with pytest.raises(DictionaryError, match="7x7"):
        load_dictionary("7x7")


@pytest.mark.parametrize("size", sorted(PRESETS))
def test_frozen_distance_is_the_documented_one(size):
    dictionary = load_dictionary(size)
    assert dictionary.bits.shape == (50, size, size)
    assert min_distance(dictionary.bits) == dictionary.min_distance == PRESETS[size][0]
    documented = re.search(rf"\|\s*{size}x{size}\s*\|[^|]*\|\s*(\d+)\s*\|", SPEC.read_text())
    assert documented, f"docs/marker-spec.md has no row for {size}x{size}"
    assert int(documented.group(1)) == dictionary.min_distance


def test_6x6_beats_opencv_dict_6x6_50():
    assert load_dictionary("6x6").min_distance >= 14
    opencv = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_50)
    opencv_bits = np.stack([1 - opencv.getBitsFromByteList(opencv.bytesList[i:i + 1], 6) for i in range(50)])
    assert min_distance(opencv_bits) < load_dictionary("6x6").min_distance


@pytest.mark.slow  # 6x6 alone re-runs a minute of search: CI runs it after the main suite (.ci/run)
@pytest.mark.parametrize("size", sorted(PRESETS))
def test_frozen_dictionary_matches_its_generator(size):
    target, seed = PRESETS[size]
    assert load_dictionary(size).seed == seed
    np.testing.assert_array_equal(search(size, target=target, seed=seed), load_dictionary(size).bits)


def test_opencv_view_has_the_same_ids_and_orientation():
    dictionary = load_dictionary("6x6")
    aruco = dictionary.aruco()
    for marker_id in (0, 17, 49):
        image = cv2.aruco.generateImageMarker(aruco, marker_id, 80)
        black = (image[5::10, 5::10] == 0).astype(np.uint8)
        np.testing.assert_array_equal(black[1:-1, 1:-1], dictionary.bits[marker_id])
