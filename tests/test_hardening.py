"""Hostile names and files are refused with one clear line, before any work or memory is spent."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from sssphase_core.errors import InputError
from sssphase_core.session import check_object_name


@pytest.mark.parametrize("name", ["nl\n", "apple\n", "../x", "a/b", "", ".", "..", "x" * 65, "\napple"])
def test_object_names_that_are_not_plain_are_refused(name):
    with pytest.raises(InputError):
        check_object_name(name)


def test_plain_object_names_pass():
    assert check_object_name("green_apple-2.v1") == "green_apple-2.v1"


def _png_header_only(path: Path, width: int, height: int) -> None:
    """A PNG that claims ``width x height`` (8-bit grey) with an empty image stream: the header is all
    that a size check may read."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"")) + chunk(b"IEND", b""))


def test_a_huge_pattern_is_refused_from_its_header(tmp_path):
    from sssphase_core.relight import read_pattern

    bomb = tmp_path / "bomb.png"
    _png_header_only(bomb, 40000, 40000)
    with pytest.raises(InputError, match="refused without decoding"):
        read_pattern(bomb, (256, 192), resize=True)


def test_a_truncated_pattern_is_one_line(tmp_path):
    from sssphase_core.relight import read_pattern

    bad = tmp_path / "cut.png"
    _png_header_only(bad, 256, 192)
    with pytest.raises(InputError, match="cannot read pattern"):
        read_pattern(bad, (256, 192))
    ok = tmp_path / "ok.npy"
    np.save(ok, np.zeros((2, 2)))
    with pytest.raises(InputError):
        read_pattern(ok, (256, 192))
