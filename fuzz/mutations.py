"""Structured mutations of valid point-cloud files: what broken files look like in the field.

Pure functions of bytes, used by the hypothesis tests (``tests/test_fuzz_hypothesis.py``), which
draw their arguments. Unlike atheris' byte-level mutations, these aim at the header: a count or
size that lies, a type that is wrong, a file cut short.
"""

from __future__ import annotations

import re

__all__ = [
    "HOSTILE_NUMBERS",
    "WRONG_TYPES",
    "cut",
    "flip_bits",
    "header_end",
    "header_lie",
    "overwrite",
    "wrong_type",
]

#: Replacements for a number in a header: zero, off by one, sign, the integer-width edges, huge
#: counts, and things that are not integers at all.
HOSTILE_NUMBERS = (
    "0", "1", "2", "3", "-1", "-3", "4", "7", "255", "256", "65535", "65536",
    "2147483647", "2147483648", "4294967295", "4294967296", "357913942", "1000000000000",
    "9223372036854775807", "9223372036854775808", "1" + "0" * 30,
    "1.5", "1e3", "nan", "inf", "0x10", "", " ", "x", "٣",
)

#: Replacements for a type word (PLY types, PCD TYPE letters and SIZEs, NumPy descrs).
WRONG_TYPES = (
    "char", "uchar", "short", "ushort", "int", "uint", "float", "double", "int8", "uint8",
    "int16", "uint16", "int32", "uint32", "float32", "float64", "float16", "int64", "list",
    "F", "U", "I", "f", "X", "1", "2", "8", "16", "0",
    "<f8", ">f4", "<f2", "|b1", "<c16", "|O", "<U3", "|V8", ">i8", "<M8", "|S3", "<u8",
)

_NUMBER = re.compile(rb"-?\d+(?:\.\d+)?")
_TYPE_WORDS = re.compile(
    rb"\b(?:char|uchar|short|ushort|int|uint|float|double|u?int(?:8|16|32)|float(?:32|64)|list|[FUI])\b"
    rb"|'[<>|=][a-zA-Z]\d*'"
)


def header_end(data: bytes) -> int:
    """Where a file's text header ends (the data starts), or a guess for headerless formats."""
    for marker in (b"end_header\n", b"end_header\r\n", b"end_header\r"):
        index = data.find(marker)
        if index >= 0:
            return index + len(marker)
    match = re.search(rb"\nDATA [^\n]*\n", data)
    if match:
        return match.end()
    if data.startswith(b"\x93NUMPY"):
        newline = data.find(b"\n")
        return newline + 1 if newline >= 0 else len(data)
    if len(data) >= 84 and not data.lstrip()[:5].lower() == b"solid" and not data[:3] in (b"OFF", b"COF"):
        return 84  # a binary STL: the 80-byte comment and the triangle count
    return min(len(data), 200)


def cut(data: bytes, keep: int) -> bytes:
    """The first ``keep`` bytes (``keep`` wraps around the length)."""
    return data[: keep % (len(data) + 1)]


def flip_bits(data: bytes, flips: list[tuple[int, int]]) -> bytes:
    """Flip bit ``bit % 8`` of byte ``position % len`` for every ``(position, bit)``."""
    if not data:
        return data
    mutable = bytearray(data)
    for position, bit in flips:
        mutable[position % len(mutable)] ^= 1 << (bit % 8)
    return bytes(mutable)


def overwrite(data: bytes, position: int, replacement: bytes) -> bytes:
    """Replace bytes at ``position % len`` by ``replacement`` (the file keeps its length, or grows)."""
    if not data:
        return replacement
    start = position % len(data)
    return data[:start] + replacement + data[start + len(replacement) :]


def _substitute(data: bytes, pattern: re.Pattern, choice: int, replacement: str, binary_count: bool) -> bytes:
    end = header_end(data)
    matches = list(pattern.finditer(data[:end]))
    if binary_count and end == 84 and len(data) >= 84:
        # A binary STL's count is a uint32, not text: write the number there.
        try:
            value = int(replacement) % 2**32
        except ValueError:
            value = 2**32 - 1
        return data[:80] + value.to_bytes(4, "little") + data[84:]
    if not matches:
        return data
    match = matches[choice % len(matches)]
    return data[: match.start()] + replacement.encode("utf-8") + data[match.end() :]


def header_lie(data: bytes, choice: int, number: str) -> bytes:
    """Replace the ``choice``-th number of the header (counts, sizes, shape, version) by ``number``."""
    return _substitute(data, _NUMBER, choice, number, binary_count=True)


def wrong_type(data: bytes, choice: int, type_word: str) -> bytes:
    """Replace the ``choice``-th type word of the header (PLY type, PCD TYPE, NumPy descr)."""
    if data.startswith(b"\x93NUMPY") and type_word[:1] in "<>|=":
        type_word = f"'{type_word}'"
    return _substitute(data, _TYPE_WORDS, choice, type_word, binary_count=False)
