"""The restricted unpickler is bounded: tiny crafted files are refused at once, with a clear line.

The files are built here from raw pickle opcodes (protocol 2), as an attacker would."""

from __future__ import annotations

import io
import pickle
import pickletools
import struct
import time

import numpy as np
import pytest

from mfdesign.data.spa_design import UnsafePickleError, restricted_load, restricted_loads


def shared_nested_lists(levels: int, fanout: int = 4) -> bytes:
    """List k holds ``fanout`` references to list k - 1 (memo BINGET): a DAG of ``levels``
    lists that unfolds to ``fanout ** levels`` nodes, in ~8 bytes per level."""
    out = b"\x80\x02" + b"]q\x00" + b"0"  # PROTO 2; EMPTY_LIST; BINPUT 0; POP
    for i in range(1, levels):
        out += b"]q" + bytes([i]) + b"(" + (b"h" + bytes([i - 1])) * fanout + b"e"  # MARK BINGET.. APPENDS
        out += b"0" if i < levels - 1 else b""
    return out + b"."


def huge_array(shape: tuple[int, ...]) -> bytes:
    """``numpy.core.multiarray._reconstruct(ndarray, shape, 'f')``: NumPy would allocate
    the whole shape on the REDUCE, before any data is read."""
    sizes = b"".join(b"J" + struct.pack("<i", n) for n in shape)  # BININT each size
    return (
        b"\x80\x02cnumpy.core.multiarray\n_reconstruct\ncnumpy\nndarray\n"
        + sizes
        + {1: b"\x85", 2: b"\x86", 3: b"\x87"}[len(shape)]
        + b"U\x01f\x87R."
    )  # TUPLEn; 'f'; TUPLE3; REDUCE


def refused_quickly(data: bytes, match: str) -> None:
    pickletools.dis(data, out=io.StringIO())  # a well-formed stream: refused for what it says, not as junk
    t0 = time.perf_counter()
    with pytest.raises(UnsafePickleError, match=match):
        restricted_loads(data)
    assert time.perf_counter() - t0 < 1.0


def test_shared_nested_lists_are_counted_once_each():
    data = shared_nested_lists(levels=25)
    assert len(data) < 400
    refused_quickly(data, r"shared references unfold to more than 10,000,000 nodes")
    # the same shape, small enough, loads (shared references themselves are fine)
    assert len(restricted_loads(shared_nested_lists(levels=5))) == 4


def test_deep_shared_lists_are_refused_by_depth():
    refused_quickly(shared_nested_lists(levels=60), r"deeper than 32 levels")


@pytest.mark.parametrize("shape", [(30_000_000, 7), (1_000_000_000, 7), (2**31 - 1, 2**31 - 1, 7)])
def test_huge_array_shape_is_refused_before_allocation(shape):
    data = huge_array(shape)
    assert len(data) < 400
    refused_quickly(data, r"refused before allocating")


def test_small_reconstruct_is_fine():
    out = restricted_loads(huge_array((3, 7)))
    assert isinstance(out, np.ndarray) and out.shape == (3, 7)


@pytest.mark.parametrize("protocol", [2, 4])
def test_a_set_is_refused(protocol):
    refused_quickly(pickle.dumps({"a": [1.0, {1, 2}]}, protocol=protocol), r"set")


def test_cycle_and_bytearray_and_corrupt(tmp_path):
    cyc = []
    cyc.append(cyc)
    refused_quickly(pickle.dumps(cyc), "contains itself")
    refused_quickly(pickle.dumps(bytearray(b"ab"), protocol=5), "bytearray")
    good = pickle.dumps({"x": np.arange(4.0)}, protocol=4)
    for bad in (good[: len(good) // 2], good[:-1], b"", b"\x00garbage"):
        (tmp_path / "p.pkl").write_bytes(bad)
        with pytest.raises(pickle.UnpicklingError, match="p.pkl"):
            restricted_load(tmp_path / "p.pkl")
