"""The RS marker dictionaries: 50 symbols, each an n x n bit pattern.

The bit patterns are frozen package data (``companion/data/dictionary_*.json``)
written by ``python docs/tools/dictionary_search.py``; ids and patterns never
change between releases. A pattern is indexed ``bits[row, column]`` with
row 0 at the top of the upright marker; 1 is a black cell.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources

import cv2
import numpy as np

LETTERS = [chr(c) for c in range(ord("A"), ord("Z") + 1)]
DIGITS = [str(d) for d in range(10)]
# Signs for asset identification and navigation (ids 36-49), in id order.
SIGNS = {
    "UP": "arrow: go up / ascend",
    "DOWN": "arrow: go down / descend",
    "LEFT": "arrow: turn left",
    "RIGHT": "arrow: turn right",
    "HOME": "home / take-off point",
    "DOCK": "charging dock",
    "STOP": "stop / no-fly beyond",
    "EXIT": "exit",
    "ENTRY": "entry",
    "PLUS": "+ (next / increasing index)",
    "MINUS": "- (previous / decreasing index)",
    "HASH": "# (bay or slot number follows)",
    "AT": "@ (location tag)",
    "STAR": "* (point of interest)",
}
SYMBOLS: tuple[str, ...] = tuple(LETTERS + DIGITS + list(SIGNS))
SIZES = (5, 6, 8)


class DictionaryError(ValueError):
    """An unknown dictionary or symbol was asked for."""


@dataclass(frozen=True)
class MarkerDictionary:
    """Bit patterns of one dictionary.

    size: n, the data grid is n x n cells.
    bits: (50, n, n) uint8, 1 = black, upright orientation.
    min_distance: minimum Hamming distance between any two markers under all
        four rotations and of each marker to its own rotations.
    """

    size: int
    bits: np.ndarray
    min_distance: int
    seed: int

    @property
    def symbols(self) -> tuple[str, ...]:
        return SYMBOLS[: len(self.bits)]

    def id_of(self, symbol: str) -> int:
        try:
            return self.symbols.index(symbol.upper())
        except ValueError:
            raise DictionaryError(f"unknown symbol {symbol!r}; known: {', '.join(self.symbols)}") from None

    def symbol_of(self, marker_id: int) -> str:
        if not 0 <= marker_id < len(self.bits):
            raise DictionaryError(f"unknown marker id {marker_id}; ids are 0-{len(self.bits) - 1}")
        return self.symbols[marker_id]

    def aruco(self, max_correction_bits: int | None = None) -> cv2.aruco.Dictionary:
        """This dictionary as an OpenCV ArUco dictionary (same ids, same orientation).

        OpenCV's bit 1 is a white cell, ours a black one.
        """
        byte_list = np.stack([cv2.aruco.Dictionary_getByteListFromBits(1 - b) for b in self.bits])[:, 0]
        if max_correction_bits is None:
            max_correction_bits = (self.min_distance - 1) // 2
        return cv2.aruco.Dictionary(byte_list, self.size, max_correction_bits)


def dictionary_path(size: int):
    return resources.files("companion") / "data" / f"dictionary_{size}x{size}.json"


@lru_cache(maxsize=None)
def load_dictionary(name: str | int = "6x6") -> MarkerDictionary:
    """Load a frozen dictionary: "5x5", "6x6" (the default) or "8x8"."""
    size = int(str(name).split("x")[0])
    if size not in SIZES:
        raise DictionaryError(f"unknown dictionary {name!r}; choose one of {', '.join(f'{s}x{s}' for s in SIZES)}")
    data = json.loads(dictionary_path(size).read_text())
    bits = np.array([[[int(ch) for ch in row] for row in marker] for marker in data["markers"]], dtype=np.uint8)
    return MarkerDictionary(size=size, bits=bits, min_distance=int(data["min_distance"]), seed=int(data["seed"]))
