"""Whole recordings: f_init and f_star in blocks, .npz members mapped from the file.

The block size and the mapping are about speed and memory; these tests check that they change
no number: the blocked functions against the streaming reconstructors and against themselves
with another block size, the mapped arrays against ``numpy.load``.
"""

from __future__ import annotations

import math
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import hallcal.sensor.lut as lut_module
import hallcal.sensor.reconstruction as rec_module
from hallcal._constants import TWO_PI
from hallcal.errors import HallcalInputError
from hallcal.io import read_dataset, write_dataset
from hallcal.io.dataset import _map_stored_members
from hallcal.sensor.flux import FluxModel, FourierBasis
from hallcal.sensor.lut import StarReconstructor, build_lut
from hallcal.sensor.reconstruction import (
    InitReconstructor,
    f_init,
    f_init_columns,
    projection_matrix,
)


def _recording(n_samples: int, pole_pairs: int, seed: int, *, offset=(0.0, 0.0, 0.0)):
    """Hall signals of a rotor that turns back and forth over several revolutions, with noise."""
    rng = np.random.default_rng(seed)
    k = np.arange(n_samples)
    y0 = 3.0 * np.sin(2e-3 * k) + 25.0 * k / n_samples - 4.0
    phases = np.array([0.0, 2.0, 4.1])
    d = np.cos(pole_pairs * y0[:, None] - phases) + np.asarray(offset)
    d += 0.01 * rng.standard_normal(d.shape)
    return d, phases


@settings(max_examples=20)
@given(
    block=st.integers(1, 97),
    n=st.integers(1, 13),
    seed=st.integers(0, 2**16),
    y_initial=st.floats(-20.0, 20.0),
)
def test_blocked_f_init_equals_streaming(block, n, seed, y_initial):
    """Blocks of any size give the streaming f_init, to rounding; across block edges too."""
    d, phases = _recording(600, n, seed, offset=(0.1, -0.2, 0.05))
    P = projection_matrix(phases)
    offset = np.array([0.1, -0.2, 0.05])
    with pytest.MonkeyPatch.context() as m:
        m.setattr(rec_module, "BLOCK_ROWS", block)
        y = f_init_columns(
            d[:, 0], d[:, 1], d[:, 2], n, y_initial=y_initial, projection=P, offset=offset
        )
    stream = InitReconstructor(n, y_initial=y_initial, projection=P, offset=offset)
    expected = np.array([stream.update(*row) for row in d])
    np.testing.assert_allclose(y, expected, rtol=0, atol=1e-13 * max(1.0, np.abs(expected).max()))


def test_block_size_changes_no_bit():
    d, _ = _recording(5000, 11, 3)
    whole = f_init(d, 11, y_initial=0.3)
    for block in (1, 2, 7, 4096):
        with pytest.MonkeyPatch.context() as m:
            m.setattr(rec_module, "BLOCK_ROWS", block)
            assert f_init(d, 11, y_initial=0.3).tobytes() == whole.tobytes()


def test_f_init_checks_its_arguments():
    with pytest.raises(ValueError, match="shape"):
        f_init(np.zeros((4, 2)), 3)
    with pytest.raises(ValueError, match="same length"):
        f_init_columns(np.zeros(3), np.zeros(3), np.zeros(4), 3)
    assert f_init(np.zeros((0, 3)), 3).shape == (0,)


def _table(n: int):
    basis = FourierBasis(tuple(range(1, 2 * n + 2)))
    theta = np.zeros((3, basis.size))
    rng = np.random.default_rng(n)
    for h, phase in enumerate((0.0, TWO_PI / 3, 2 * TWO_PI / 3)):
        j = basis.harmonics.index(n)
        theta[h, 1 + 2 * j] = math.sin(phase)
        theta[h, 2 + 2 * j] = math.cos(phase)
    theta[:, 1:] += 0.01 * rng.standard_normal((3, basis.size - 1))
    return build_lut(FluxModel(basis, theta), n, points=512)


@pytest.mark.parametrize("block", [1, 5, 64, 1 << 18])
def test_lut_reconstruct_equals_f_star_and_the_streaming_table(block):
    lut = _table(5)
    assert lut.bijective
    d, _ = _recording(3000, 5, 8)
    with pytest.MonkeyPatch.context() as m:
        m.setattr(rec_module, "BLOCK_ROWS", block)
        m.setattr(lut_module, "BLOCK_ROWS", block)
        y_init, y_star = lut.reconstruct(d[:, 0], d[:, 1], d[:, 2], y_initial=0.1)
    scale = np.abs(y_star).max()
    np.testing.assert_array_equal(y_init, lut.f_init(d, y_initial=0.1))
    np.testing.assert_allclose(y_star, lut.f_star(d, y_initial=0.1), rtol=0, atol=1e-14 * scale)
    stream = StarReconstructor(lut, y_initial=0.1)
    expected = np.array([stream.update(*row) for row in d[:300]])
    np.testing.assert_allclose(y_star[:300], expected, rtol=0, atol=1e-13 * scale)


def test_correction_equals_numpy_periodic_interpolation():
    """The table padded once equals np.interp(..., period=2 pi) on every call (the oracle)."""
    lut = _table(4)
    y = np.linspace(-30.0, 30.0, 10001)
    oracle = np.interp(np.mod(y, TWO_PI), lut.y_hat, lut.eta, period=TWO_PI)
    np.testing.assert_allclose(lut.correction(y), oracle, rtol=0, atol=1e-15)


# ---- .npz members mapped from the file ---------------------------------------------------------


def test_mapped_npz_members_equal_numpy_load(tmp_path: Path):
    path = tmp_path / "a.npz"
    arrays = {
        "f8": np.linspace(0, 1, 1001),
        "big_endian": np.arange(50, dtype=">f8"),
        "i4": np.arange(-20, 20, dtype=np.int32),
        "u1": np.arange(200, dtype=np.uint8),
        "fortran": np.asfortranarray(np.arange(12.0).reshape(3, 4)),
        "column": np.arange(7.0).reshape(7, 1),
        "empty": np.zeros(0),
    }
    np.savez(path, **arrays)
    mapped = _map_stored_members(path)
    assert set(mapped) == set(arrays)
    with np.load(path) as ref:
        for name in arrays:
            assert mapped[name].dtype == ref[name].dtype
            np.testing.assert_array_equal(mapped[name], ref[name])
            assert not mapped[name].flags.writeable


def test_compressed_and_object_members_are_read_by_numpy(tmp_path: Path):
    path = tmp_path / "c.npz"
    np.savez_compressed(path, d1=np.ones(5), d2=np.zeros(5), d3=np.arange(5.0))
    assert _map_stored_members(path) == {}
    np.testing.assert_array_equal(read_dataset(path)["d3"], np.arange(5.0))
    objects = tmp_path / "o.npz"
    np.savez(objects, d1=np.array([1, "a"], dtype=object), d2=np.zeros(2), d3=np.zeros(2))
    assert set(_map_stored_members(objects)) == {"d2", "d3"}
    with pytest.raises(HallcalInputError, match="holds Python objects"):
        read_dataset(objects)


def test_corrupted_member_is_caught_by_its_crc(tmp_path: Path):
    path = tmp_path / "bad.npz"
    write_dataset(path, {"d1": np.ones(1000), "d2": np.ones(1000), "d3": np.ones(1000)})
    raw = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo("d2.npy")
    raw[info.header_offset + 30 + len("d2.npy") + 200] ^= 0xFF  # inside d2's data
    path.write_bytes(bytes(raw))
    assert "d2" not in _map_stored_members(path)
    with pytest.raises(HallcalInputError, match="corrupt or truncated .npz archive .*'d2.npy'"):
        read_dataset(path)


def test_big_recording_round_trip_through_npz(tmp_path: Path):
    """A recording longer than a block: written, mapped back, reconstructed block by block."""
    n = (1 << 18) + 12345
    d, _ = _recording(n, 7, 1)
    path = tmp_path / "run.npz"
    write_dataset(path, {"d1": d[:, 0], "d2": d[:, 1], "d3": d[:, 2]})
    ds = read_dataset(path)
    assert ds.n_samples == n and ds["d2"].tobytes() == d[:, 1].tobytes()
    lut = _table(7)
    y_init, y_star = lut.reconstruct(ds["d1"], ds["d2"], ds["d3"])
    np.testing.assert_array_equal(y_init, lut.f_init(d))
