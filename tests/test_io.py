"""Tests of hallcal.io: datasets, setup files, artifacts, atomic writes."""

from __future__ import annotations

import json
import os
import tempfile
import zipfile
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import scipy.io
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from hallcal.errors import HallcalInputError
from hallcal.io import (
    ARTIFACT_FORMAT,
    DATASET_EXTENSIONS,
    KNOWN_COLUMNS,
    BenchSpec,
    BLASpec,
    Dataset,
    MissingColumnError,
    ModelSpec,
    Setup,
    TrajectorySpec,
    atomic_write,
    default_setup,
    read_artifact,
    read_dataset,
    read_json,
    read_setup,
    setup_from_dict,
    setup_to_toml,
    write_artifact,
    write_dataset,
    write_json,
    write_setup,
)
from hallcal.sim.lti import ContinuousTF, DiscreteTF

# ================================================================================================
# Datasets
# ================================================================================================

HALL = ("d1", "d2", "d3")


def _columns(n: int = 6) -> dict[str, np.ndarray]:
    k = np.arange(n, dtype=np.float64)
    return {
        "r": 0.1 * k,
        "y": 0.1 * k + 1e-3,
        "u": np.sin(k),
        "d1": np.cos(k),
        "d2": np.cos(k - 2.0),
        "d3": np.cos(k + 2.0),
    }


def _write_csv(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def _message(excinfo: pytest.ExceptionInfo[BaseException]) -> str:
    text = str(excinfo.value)
    assert "\n" not in text, "error messages are one line"
    return text


_column_names = st.from_regex(r"[a-z][a-z0-9_]{0,8}", fullmatch=True)
_finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
#: Hall readings from 1e-2 to 1e2 of either sign, and zeros of both signs: the largest value is
#: within 2e4 of any nonzero median (the mean of 0 and 1e-2 at the least), far inside
#: limits.SPIKE_RATIO = 1e6.
_hall_value = st.one_of(st.sampled_from([0.0, -0.0]), st.floats(1e-2, 1e2), st.floats(-1e2, -1e-2))
#: Other known columns (angles, time): within limits.MAX_ABS_VALUE.
_known = st.floats(-1e12, 1e12)


@st.composite
def _tables(draw: st.DrawFn) -> dict[str, np.ndarray]:
    n = draw(st.integers(2, 40))
    names = draw(st.lists(_column_names, min_size=1, max_size=5, unique=True))
    names = ["d1", "d2", "d3", *[name for name in names if name not in HALL]]
    out: dict[str, np.ndarray] = {}
    for name in names:
        # known columns must be plausible (no 1e300, no Hall value of 1e-300: hallcal.limits);
        # the others are any finite numbers
        elements = _hall_value if name in HALL else _known if name in KNOWN_COLUMNS else _finite
        out[name] = draw(hnp.arrays(np.float64, n, elements=elements))
    if draw(st.booleans()):
        out["realization"] = draw(hnp.arrays(np.int64, n, elements=st.integers(0, 50)))
    return out


@pytest.mark.parametrize("ext", DATASET_EXTENSIONS)
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(columns=_tables())
def test_dataset_round_trip(ext: str, columns: dict[str, np.ndarray]) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"data{ext}"
        write_dataset(path, columns)
        ds = read_dataset(path)
        assert os.listdir(tmp) == [path.name]  # no temporary file left behind
    assert ds.names == tuple(columns)
    assert ds.n_samples == len(columns["d1"])
    for name, values in columns.items():
        got = ds[name]
        assert got.dtype == np.float64 and got.ndim == 1
        # bit-exact, including the sign of zero
        np.testing.assert_array_equal(got, values.astype(np.float64))
        assert np.array_equal(np.signbit(got), np.signbit(values.astype(np.float64)))


def test_dataset_accessors(tmp_path: Path) -> None:
    cols = _columns()
    path = tmp_path / "data.npz"
    write_dataset(path, cols)
    ds = read_dataset(path, required=("r", "y", "u", *HALL))
    assert ds.path == path
    assert "u" in ds and "y_ref" not in ds
    assert ds.get("y_ref") is None
    assert ds.get("y_ref", 3) == 3
    np.testing.assert_array_equal(ds.get("u"), cols["u"])
    assert ds.d.shape == (6, 3)
    np.testing.assert_array_equal(ds.d[:, 1], cols["d2"])
    with pytest.raises(ValueError, match="read-only"):
        ds["u"][0] = 1.0
    with pytest.raises(KeyError) as excinfo:
        ds["y_ref"]
    assert isinstance(excinfo.value, HallcalInputError)
    assert _message(excinfo) == f"{path}: column 'y_ref' is missing"
    with pytest.raises(MissingColumnError, match="'t' is missing"):
        ds.require("u", "t")
    assert "n_samples=6" in repr(ds)


def test_from_columns_checks_like_read() -> None:
    ds = Dataset.from_columns({"d1": [1, 2], "d2": [3.0, 4.0], "d3": np.zeros(2)}, required=HALL)
    assert ds.path is None and ds.n_samples == 2 and ds["d1"].dtype == np.float64
    with pytest.raises(HallcalInputError, match=r"<dataset>: column 'd2' contains NaN or inf"):
        Dataset.from_columns({"d1": [1.0, 2.0], "d2": [1.0, np.nan]})
    with pytest.raises(HallcalInputError, match="column 'd1' must be 1-D"):
        Dataset.from_columns({"d1": np.zeros((2, 2))})
    with pytest.raises(HallcalInputError, match="sim: column 'd3' is missing"):
        Dataset.from_columns({"d1": [1.0], "d2": [1.0]}, path="sim", required=HALL)


# ---- CSV specifics -----------------------------------------------------------------------------


def test_csv_dialects(tmp_path: Path) -> None:
    path = _write_csv(
        tmp_path / "a.csv",
        "\ufeff# d1;d2;d3\n\n1;2;3\n# a comment\n 4 ; 5 ;6e0\n\n",
    )
    ds = read_dataset(path)
    np.testing.assert_array_equal(ds["d3"], [3.0, 6.0])
    commented = _write_csv(tmp_path / "e.csv", "# bench 3, 2024\n# run 1\nd1,d2,d3\n1,2,3\n")
    assert read_dataset(commented, min_samples=1).names == HALL
    saved = tmp_path / "f.csv"
    np.savetxt(saved, np.ones((3, 3)), delimiter=",", header="d1,d2,d3")
    assert read_dataset(saved).n_samples == 3
    tabbed = _write_csv(tmp_path / "b.csv", "d1\td2\td3\n1\t2\t3\n4\t5\t6\n")
    np.testing.assert_array_equal(read_dataset(tabbed)["d2"], [2.0, 5.0])
    trailing = _write_csv(tmp_path / "c.csv", "d1,d2,d3,\n1,2,3,\n4,5,6,\n")
    assert read_dataset(trailing).names == HALL
    quoted = _write_csv(tmp_path / "d.csv", '"d1","d2","d3"\n"1",2,3\n4,5,6\n')
    np.testing.assert_array_equal(read_dataset(quoted)["d1"], [1.0, 4.0])


def test_csv_writes_integers_and_shortest_floats(tmp_path: Path) -> None:
    path = tmp_path / "out.csv"
    write_dataset(path, {"y_star": np.array([0.1, 1.0]), "realization": np.array([0, 3])})
    assert path.read_text() == "y_star,realization\n0.1,0\n1.0,3\n"


def test_csv_non_numeric_value_names_column_and_row(tmp_path: Path) -> None:
    rows = [f"{k},{k},{k},{k}" for k in range(20)]
    rows[16] = "16,abc,16,16"  # data row 17, line 18
    path = _write_csv(tmp_path / "data.csv", "d1,u,d2,d3\n" + "\n".join(rows) + "\n")
    with pytest.raises(HallcalInputError) as excinfo:
        read_dataset(path)
    assert _message(excinfo) == (
        f"{path}: column 'u' has a non-numeric value 'abc' in row 17 (line 18)"
    )


def test_csv_missing_value(tmp_path: Path) -> None:
    path = _write_csv(tmp_path / "data.csv", "d1,d2,d3\n1,2,3\n4,,6\n")
    with pytest.raises(HallcalInputError) as excinfo:
        read_dataset(path)
    assert _message(excinfo) == f"{path}: column 'd2' has a missing value in row 2 (line 3)"


def test_csv_nan_and_inf(tmp_path: Path) -> None:
    path = _write_csv(tmp_path / "data.csv", "d1,d2,d3\n1,2,3\n1,2,3\n1,2,3\n1,2,3\nnan,2,3\n")
    with pytest.raises(HallcalInputError) as excinfo:
        read_dataset(path)
    assert _message(excinfo) == f"{path}: column 'd1' contains NaN or inf (row 5, line 6)"
    path = _write_csv(tmp_path / "data.csv", "d1,d2,d3\n1,-inf,3\n1,2,3\n")
    with pytest.raises(HallcalInputError, match=r"column 'd2' contains NaN or inf \(row 1"):
        read_dataset(path)


def test_csv_ragged_row(tmp_path: Path) -> None:
    path = _write_csv(tmp_path / "data.csv", "d1,d2,d3\n1,2,3\n1,2\n")
    with pytest.raises(HallcalInputError) as excinfo:
        read_dataset(path)
    assert _message(excinfo) == f"{path}: row 2 (line 3) has 2 fields, the header has 3"


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("", "file is empty"),
        ("\n  \n", "file is empty"),
        ("d1,d2,d3\n", "no data rows"),
        ("d1,d2,d3\n\n# only a comment\n", "no data rows"),
        ("1,2,3\n4,5,6\n", "the first line must be a header of column names, found the number"),
        ("d1,d2,d1\n1,2,3\n", "column 'd1' appears twice in the header"),
        ("d1,,d3\n1,2,3\n", "column 2 of the header has no name"),
        ("d1,d3,u\n1,2,3\n1,2,3\n", "column 'd2' is missing"),
        ("d1,d2,d3\n1,2,3\n", "1 data rows, at least 2 needed"),
    ],
)
def test_csv_structural_errors(tmp_path: Path, text: str, expected: str) -> None:
    path = _write_csv(tmp_path / "data.csv", text)
    with pytest.raises(HallcalInputError) as excinfo:
        read_dataset(path)
    message = _message(excinfo)
    assert message.startswith(f"{path}: ")
    assert expected in message


def test_missing_column_lists_what_was_found(tmp_path: Path) -> None:
    path = _write_csv(tmp_path / "data.csv", "D1,d2,d3\n1,2,3\n1,2,3\n")
    with pytest.raises(MissingColumnError) as excinfo:
        read_dataset(path)
    assert _message(excinfo) == (
        f"{path}: column 'd1' is missing (did you mean 'D1'?) (found: D1, d2, d3)"
    )


def test_csv_not_utf8(tmp_path: Path) -> None:
    path = tmp_path / "data.csv"
    path.write_bytes(b"d1,d2,d3\n1,2,3\n\xff\xfe,2,3\n")
    with pytest.raises(HallcalInputError, match=r"data.csv: not UTF-8 text \(line 3\)"):
        read_dataset(path)


def test_min_samples_and_required_are_the_callers(tmp_path: Path) -> None:
    path = _write_csv(tmp_path / "data.csv", "y_init,y_star\n1,2\n")
    ds = read_dataset(path, required=(), min_samples=1)
    assert ds.names == ("y_init", "y_star")
    with pytest.raises(HallcalInputError, match="1 data rows, at least 5 needed"):
        read_dataset(path, required=(), min_samples=5)


def test_realization_must_be_whole(tmp_path: Path) -> None:
    path = _write_csv(tmp_path / "data.csv", "d1,d2,d3,realization\n1,2,3,0\n1,2,3,0.5\n")
    with pytest.raises(HallcalInputError) as excinfo:
        read_dataset(path)
    assert _message(excinfo) == (
        f"{path}: column 'realization' must hold whole numbers (row 2, line 3 has 0.5)"
    )


# ---- File-level errors for every format --------------------------------------------------------


def test_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "nope.csv"
    with pytest.raises(HallcalInputError) as excinfo:
        read_dataset(path)
    assert _message(excinfo) == f"{path}: file not found"
    with pytest.raises(HallcalInputError, match="not a regular file"):
        read_dataset(tmp_path)


@pytest.mark.parametrize("name", ["data.xlsx", "data", "data.CSV.bak"])
def test_unknown_extension(tmp_path: Path, name: str) -> None:
    path = tmp_path / name
    path.write_text("d1,d2,d3\n1,2,3\n")
    with pytest.raises(HallcalInputError) as excinfo:
        read_dataset(path)
    message = _message(excinfo)
    assert message.startswith(f"{path}: unknown dataset extension")
    assert ".parquet" in message
    with pytest.raises(HallcalInputError, match="unknown dataset extension"):
        write_dataset(tmp_path / name, _columns())


def test_extension_is_case_insensitive(tmp_path: Path) -> None:
    path = tmp_path / "DATA.CSV"
    write_dataset(path, _columns())
    assert read_dataset(path).n_samples == 6


@pytest.mark.parametrize("ext", DATASET_EXTENSIONS)
def test_empty_file(tmp_path: Path, ext: str) -> None:
    path = tmp_path / f"data{ext}"
    path.write_bytes(b"")
    with pytest.raises(HallcalInputError) as excinfo:
        read_dataset(path)
    assert _message(excinfo) == f"{path}: file is empty"


@pytest.mark.parametrize(
    ("ext", "expected"),
    [
        (".parquet", "not a valid Parquet file"),
        (".h5", "not a valid HDF5 file"),
        (".hdf5", "not a valid HDF5 file"),
        (".mat", "not a valid MATLAB .mat file"),
        (".npz", "not a valid .npz archive"),
    ],
)
def test_garbage_binary_file(tmp_path: Path, ext: str, expected: str) -> None:
    path = tmp_path / f"data{ext}"
    path.write_bytes(b"this is not a binary table at all\n" * 20)
    with pytest.raises(HallcalInputError) as excinfo:
        read_dataset(path)
    message = _message(excinfo)
    assert message.startswith(f"{path}: {expected}")


@pytest.mark.parametrize("ext", [".parquet", ".h5", ".mat", ".npz"])
def test_binary_no_rows(tmp_path: Path, ext: str) -> None:
    path = tmp_path / f"data{ext}"
    write_dataset(path, {name: np.zeros(0) for name in HALL})
    with pytest.raises(HallcalInputError) as excinfo:
        read_dataset(path)
    assert _message(excinfo) == f"{path}: no data rows"


@pytest.mark.parametrize("ext", [".parquet", ".h5", ".mat", ".npz"])
def test_binary_missing_column(tmp_path: Path, ext: str) -> None:
    path = tmp_path / f"data{ext}"
    cols = _columns()
    del cols["d2"]
    write_dataset(path, cols)
    with pytest.raises(MissingColumnError) as excinfo:
        read_dataset(path)
    assert _message(excinfo).startswith(f"{path}: column 'd2' is missing")


def _write_raw(path: Path, cols: dict[str, np.ndarray]) -> None:
    """Write columns without write_dataset's checks (NaN, different lengths)."""
    ext = path.suffix
    if ext == ".npz":
        np.savez(path, **cols)
    elif ext == ".mat":
        scipy.io.savemat(path, cols, oned_as="column")
    elif ext == ".h5":
        with h5py.File(path, "w") as h5:
            for name, values in cols.items():
                h5.create_dataset(name, data=values)
    else:
        raise AssertionError(ext)


@pytest.mark.parametrize("ext", [".h5", ".mat", ".npz"])
def test_binary_nan_names_column_and_row(tmp_path: Path, ext: str) -> None:
    path = tmp_path / f"data{ext}"
    cols = _columns()
    cols["d1"] = cols["d1"].copy()
    cols["d1"][4] = np.inf
    _write_raw(path, cols)
    with pytest.raises(HallcalInputError) as excinfo:
        read_dataset(path)
    assert _message(excinfo) == f"{path}: column 'd1' contains NaN or inf (row 5)"


def test_parquet_nan_and_missing_value(tmp_path: Path) -> None:
    path = tmp_path / "data.parquet"
    table = pa.table({"d1": [1.0, 2.0, float("nan")], "d2": [1.0, 2.0, 3.0], "d3": [1, 2, 3]})
    pq.write_table(table, path)
    with pytest.raises(HallcalInputError) as excinfo:
        read_dataset(path)
    assert _message(excinfo) == f"{path}: column 'd1' contains NaN or inf (row 3)"
    table = pa.table({"d1": [1.0, 2.0, 3.0], "d2": [1.0, None, 3.0], "d3": [1, 2, 3]})
    pq.write_table(table, path)
    with pytest.raises(HallcalInputError) as excinfo:
        read_dataset(path)
    assert _message(excinfo) == f"{path}: column 'd2' has a missing value in row 2"


def test_parquet_non_numeric_column(tmp_path: Path) -> None:
    path = tmp_path / "data.parquet"
    table = pa.table({"d1": [1.0, 2.0], "d2": [1.0, 2.0], "d3": [1.0, 2.0], "u": ["a", "b"]})
    pq.write_table(table, path)
    with pytest.raises(HallcalInputError) as excinfo:
        read_dataset(path)
    assert _message(excinfo) == f"{path}: column 'u' is not numeric (type string)"


def test_parquet_bool_and_dictionary_columns(tmp_path: Path) -> None:
    path = tmp_path / "data.parquet"
    realization = pa.array([0, 0, 1]).dictionary_encode()
    table = pa.table(
        {
            "d1": [1.0, 2.0, 3.0],
            "d2": [True, False, True],
            "d3": [1, 2, 3],
            "realization": realization,
        }
    )
    pq.write_table(table, path)
    ds = read_dataset(path)
    np.testing.assert_array_equal(ds["d2"], [1.0, 0.0, 1.0])
    np.testing.assert_array_equal(ds["realization"], [0.0, 0.0, 1.0])


@pytest.mark.parametrize("ext", [".h5", ".mat", ".npz"])
def test_known_columns_of_different_lengths(tmp_path: Path, ext: str) -> None:
    path = tmp_path / f"data{ext}"
    cols = _columns()
    cols["d2"] = cols["d2"][:-1]
    _write_raw(path, cols)
    with pytest.raises(HallcalInputError) as excinfo:
        read_dataset(path)
    message = _message(excinfo)
    assert message.startswith(f"{path}: columns have different lengths")
    assert "'d2': 5 rows" in message


@pytest.mark.parametrize("ext", [".h5", ".mat", ".npz"])
def test_containers_ignore_non_columns(tmp_path: Path, ext: str) -> None:
    path = tmp_path / f"data{ext}"
    cols: dict[str, Any] = _columns()
    cols["extra"] = np.arange(6.0)  # a column: kept
    cols["Ts"] = np.array(2.5e-4)  # a scalar: ignored
    cols["theta"] = np.arange(23.0)  # a vector of another length: ignored
    cols["K"] = np.eye(3)  # a matrix: ignored
    _write_raw(path, cols)
    ds = read_dataset(path)
    assert set(ds.names) == {"r", "y", "u", "d1", "d2", "d3", "extra"}


@pytest.mark.parametrize("ext", [".h5", ".mat", ".npz"])
def test_known_column_that_is_not_a_vector(tmp_path: Path, ext: str) -> None:
    path = tmp_path / f"data{ext}"
    cols = _columns()
    cols["u"] = np.ones((6, 2))
    _write_raw(path, cols)
    with pytest.raises(HallcalInputError) as excinfo:
        read_dataset(path)
    assert _message(excinfo) == f"{path}: column 'u' must be a numeric vector, got shape (6, 2)"


def test_hdf5_data_group_and_row_vectors(tmp_path: Path) -> None:
    path = tmp_path / "data.hdf5"
    cols = _columns()
    with h5py.File(path, "w") as h5:
        h5.create_dataset("d1", data=np.zeros(3))  # ignored: the group "data" wins
        h5.attrs["sample_time"] = 2.5e-4
        group = h5.create_group("data")
        for name, values in cols.items():
            group.create_dataset(name, data=values[np.newaxis, :])  # 1 x N
        group.create_dataset("label", data="text")
    ds = read_dataset(path, required=("r", "y", "u", *HALL))
    assert ds.n_samples == 6
    np.testing.assert_array_equal(ds["u"], cols["u"])
    assert "label" not in ds


def test_mat_row_vectors_and_strings(tmp_path: Path) -> None:
    path = tmp_path / "data.mat"
    cols: dict[str, Any] = {k: v[np.newaxis, :] for k, v in _columns().items()}
    cols["note"] = "bench 3"
    scipy.io.savemat(path, cols)
    ds = read_dataset(path)
    assert ds.names == ("r", "y", "u", "d1", "d2", "d3")


def test_mat_that_is_hdf5(tmp_path: Path) -> None:
    """MATLAB v7.3 files are HDF5; their variables are datasets at the root (as 1 x N)."""
    path = tmp_path / "data.mat"
    with h5py.File(path, "w") as h5:
        for name, values in _columns().items():
            dset = h5.create_dataset(name, data=values[np.newaxis, :])
            dset.attrs["MATLAB_class"] = np.bytes_(b"double")
        h5.create_dataset("note", data=np.array([98, 101], dtype=np.uint16))
        h5["note"].attrs["MATLAB_class"] = np.bytes_(b"char")
    ds = read_dataset(path)
    assert ds.names == ("d1", "d2", "d3", "r", "u", "y")


def test_npz_object_array_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "data.npz"
    cols: dict[str, Any] = _columns()
    cols["d1"] = np.array([1.0, "x", None, 2, 3, 4], dtype=object)
    np.savez(path, **cols)  # numpy pickles object arrays
    with pytest.raises(HallcalInputError) as excinfo:
        read_dataset(path)
    message = _message(excinfo)
    assert message.startswith(f"{path}: array 'd1' holds Python objects")
    assert "never unpickles" in message


def test_npz_that_is_a_pickle_or_npy(tmp_path: Path) -> None:
    path = tmp_path / "data.npz"
    path.write_bytes(b"\x80\x04\x95" + b"\x00" * 40)  # pickle protocol 4 header
    with pytest.raises(HallcalInputError, match=r"not a valid \.npz archive \(not a zip file\)"):
        read_dataset(path)
    with open(path, "wb") as f:
        np.save(f, np.zeros(4))
    with pytest.raises(HallcalInputError, match=r"a single \.npy array"):
        read_dataset(path)


def test_npz_written_without_pickle_and_with_awkward_names(tmp_path: Path) -> None:
    path = tmp_path / "data.npz"
    cols = {**_columns(), "file": np.ones(6), "allow_pickle": np.zeros(6)}
    write_dataset(path, cols)
    with zipfile.ZipFile(path) as zf:
        assert sorted(zf.namelist()) == sorted(f"{name}.npy" for name in cols)
    assert read_dataset(path).names == tuple(cols)


def test_write_dataset_refuses_bad_columns(tmp_path: Path) -> None:
    cols = _columns()
    with pytest.raises(ValueError, match="column 'd1' contains NaN or inf"):
        write_dataset(tmp_path / "a.csv", {**cols, "d1": np.full(6, np.nan)})
    with pytest.raises(ValueError, match="different lengths"):
        write_dataset(tmp_path / "a.csv", {**cols, "d1": np.zeros(5)})
    with pytest.raises(ValueError, match="numeric 1-D"):
        write_dataset(tmp_path / "a.csv", {**cols, "d1": np.array(["a,b"] * 6)})  # not a word
    with pytest.raises(HallcalInputError, match="'2nd' is not a valid MATLAB variable name"):
        write_dataset(tmp_path / "a.mat", {**cols, "2nd": np.zeros(6)})
    with pytest.raises(HallcalInputError, match="does not exist"):
        write_dataset(tmp_path / "missing" / "a.csv", cols)
    assert os.listdir(tmp_path) == []


def test_write_dataset_replaces_atomically(tmp_path: Path) -> None:
    path = tmp_path / "data.parquet"
    write_dataset(path, _columns(6))
    write_dataset(path, _columns(9))
    assert read_dataset(path).n_samples == 9
    assert os.listdir(tmp_path) == ["data.parquet"]


# ================================================================================================
# Setup
# ================================================================================================

DESIGN_EXAMPLE = """\
pole_pairs = 11
sample_time = 2.5e-4                # s
[controller]                        # discrete-time C(q), coefficients in descending powers of q
num = [2.94, -3.29, -2.10, 2.45]
den = [1, -3.45, 4.52, -2.68, 0.61]
[plant]                             # continuous-time G(s) in descending powers of s; omit it when a
num = [1.663e5]                     # BLA experiment is given instead
den = [1, 632.6, 2702, 0]
delay = 1.2e-4                      # s, input delay, 0 <= delay
[model]
basis = "fourier"                   # or "kernel"
harmonics = [1,2,3,4,5,6,7,8,9,10,11]   # fourier: mechanical harmonics (constant term always included)
# points = 400                      # kernel: number of kernel centres
[trajectory]                        # how the true angle moved during the calibration run
kind = "closed-loop"                # default (the paper); or "constant-speed" (open-loop spin) with
# start = 150                       #   start/stop: sample indices of the constant-speed part
# stop = 3300
[bla]                               # only for BLA experiments
period_samples = 4000
periods = 4                         # per realization, including transient_periods
transient_periods = 1
"""  # noqa: E501

MINIMAL: dict[str, Any] = {
    "pole_pairs": 11,
    "sample_time": 2.5e-4,
    "controller": {"num": [1.0], "den": [1.0, -0.5]},
}


def test_design_example_is_default_setup(tmp_path: Path) -> None:
    path = tmp_path / "setup.toml"
    path.write_text(DESIGN_EXAMPLE)
    setup = read_setup(path)
    assert setup == default_setup()
    assert setup.controller == DiscreteTF((2.94, -3.29, -2.10, 2.45), (1, -3.45, 4.52, -2.68, 0.61))
    assert setup.plant == ContinuousTF((1.663e5,), (1, 632.6, 2702, 0), 1.2e-4)
    assert setup.model.harmonics == tuple(range(1, 12))
    assert setup.bla is not None and setup.bla.band == (1.0, 400.0)
    assert setup.bench == BenchSpec()
    assert setup.bench.noise_variance == 7.5e-6 and setup.bench.ramp_end == 13.0
    assert all(isinstance(c, float) for c in setup.controller.den)


def test_defaults_of_a_minimal_setup() -> None:
    setup = setup_from_dict(MINIMAL)
    assert setup.plant is None and setup.bla is None
    assert setup.model == ModelSpec()
    assert setup.model.harmonics == "auto" and setup.model.lut_points == 4096
    assert setup.trajectory == TrajectorySpec(kind="closed-loop")
    assert setup.bench.cogging_periods == 0  # 0: six per pole pair (sim.bench)


def _kernel_setup() -> Setup:
    return Setup(
        pole_pairs=4,
        sample_time=1.0,
        controller=None,
        plant=ContinuousTF([2.0, 1.0], [1.0, 3.0, 0.0]),
        model=ModelSpec(basis="kernel", points=64, lengthscale=0.3, force=True),
        trajectory=TrajectorySpec(kind="constant-speed", start=150, stop=3300),
        bla=BLASpec(period_samples=64, periods=3, band=(0.05, 0.4), lines="odd", drift=-0.5),
        bench=BenchSpec(
            experiment="multisine",
            seed=7,
            misalignment_deg=[1.0, -2.0, 0.5],
            gain_mismatch=[0.01, 0.0, -0.02],
            offset=[0.0, 0.1, 0.0],
            electrical_harmonics=[[3, 0.1], [5, -0.02]],
            cogging=0.3,
            cogging_periods=24,
            shape_variation=0.05,
            shape_harmonics=3,
        ),
    )


@pytest.mark.parametrize("setup", [default_setup(), _kernel_setup(), setup_from_dict(MINIMAL)])
def test_setup_round_trips(tmp_path: Path, setup: Setup) -> None:
    d = setup.to_dict()
    assert json.loads(json.dumps(d)) == d  # JSON-serializable
    assert setup_from_dict(d) == setup
    assert setup_from_dict(json.loads(json.dumps(d))) == setup
    path = tmp_path / "s.toml"
    write_setup(path, setup)
    assert read_setup(path) == setup
    assert setup_to_toml(setup) == path.read_text()


def test_setup_is_frozen_and_hashable() -> None:
    setup = default_setup()
    with pytest.raises(AttributeError):
        setup.pole_pairs = 3  # type: ignore[misc]
    assert hash(setup) == hash(default_setup())


def _bad(update: dict[str, Any], *, drop: tuple[str, ...] = ()) -> str:
    d: dict[str, Any] = json.loads(json.dumps(MINIMAL))
    for key in drop:
        d.pop(key)
    for key, value in update.items():
        if "." in key:
            table, name = key.split(".")
            d.setdefault(table, {})[name] = value
        else:
            d[key] = value
    with pytest.raises(HallcalInputError) as excinfo:
        setup_from_dict(d, source="setup.toml")
    return _message(excinfo)


@pytest.mark.parametrize(
    ("update", "expected"),
    [
        ({"pole_pairs": 0}, "key 'pole_pairs' must be an integer >= 1, got 0"),
        ({"pole_pairs": 11.0}, "key 'pole_pairs' must be an integer >= 1, got 11.0"),
        ({"pole_pairs": True}, "key 'pole_pairs' must be an integer >= 1, got true"),
        ({"sample_time": 0}, "key 'sample_time' must be a number > 0, got 0"),
        ({"sample_time": "1ms"}, "key 'sample_time' must be a number > 0, got \"1ms\""),
        ({"sample_time": float("inf")}, "key 'sample_time' must be a finite number, got inf"),
        ({"controller": 3}, "key 'controller' must be a table, got 3"),
        ({"controller.den": [0, 1]}, "key 'controller.den' must have a nonzero leading"),
        ({"controller.den": []}, "key 'controller.den' must be a non-empty list of numbers"),
        ({"controller.num": [1, "a"]}, "key 'controller.num' must be a non-empty list of numbers"),
        ({"controller.num": [1, 2, 3]}, "key 'controller.num' has more coefficients than"),
        ({"controller.num": [0.0]}, "key 'controller.num' must not be all zero"),
        ({"plant.num": [1.0]}, "key 'plant.den' is missing"),
        ({"plant.num": [1, 2], "plant.den": [1]}, "key 'plant.num' has more coefficients"),
        (
            {"plant.num": [1], "plant.den": [1, 2], "plant.delay": -1e-4},
            "key 'plant.delay' must be a number >= 0, got -0.0001",
        ),
        ({"model.basis": "fourir"}, "(did you mean 'fourier'?)"),
        ({"model.harmonics": [1, 2, 2]}, "key 'model.harmonics' lists a harmonic twice"),
        ({"model.harmonics": [0, 1]}, 'must be a list of distinct integers >= 1 or "auto"'),
        ({"model.harmonics": "all"}, "key 'model.harmonics' must be a list of distinct"),
        ({"model.points": 100}, "key 'model.points' applies only to basis = \"kernel\""),
        (
            {"model.basis": "kernel", "model.harmonics": [1]},
            "key 'model.harmonics' applies only to basis = \"fourier\"",
        ),
        (
            {"model.basis": "kernel", "model.points": 4},
            "key 'model.points' must be an integer >= 8, got 4",
        ),
        (
            {"model.basis": "kernel", "model.lengthscale": -1.0},
            "key 'model.lengthscale' must be a number > 0 or \"auto\", got -1.0",
        ),
        ({"model.lut_points": 8}, "key 'model.lut_points' must be an integer >= 16, got 8"),
        ({"model.max_iterations": 0}, "key 'model.max_iterations' must be an integer >= 1"),
        ({"model.force": "yes"}, "key 'model.force' must be true or false, got \"yes\""),
        ({"trajectory.kind": "open-loop"}, "key 'trajectory.kind' must be one of"),
        ({"trajectory.start": 5}, "key 'trajectory.start' applies only to kind = \"constant"),
        (
            {"trajectory.kind": "constant-speed", "trajectory.start": 10, "trajectory.stop": 10},
            "key 'trajectory.stop' must be greater than 'trajectory.start' (10), got 10",
        ),
        (
            {"trajectory.kind": "constant-speed", "trajectory.start": -1},
            "key 'trajectory.start' must be an integer >= 0, got -1",
        ),
        ({"bla.periods": 4}, "key 'bla.period_samples' is missing"),
        (
            {"bla.period_samples": 4000, "bla.periods": 2, "bla.transient_periods": 2},
            "key 'bla.transient_periods' must be less than 'bla.periods' (2), got 2",
        ),
        (
            {"bla.period_samples": 4000, "bla.periods": 2, "bla.band": [1.0, 3000.0]},
            "key 'bla.band' must stay below the Nyquist frequency 2000 Hz",
        ),
        (
            {"bla.period_samples": 4000, "bla.periods": 2, "bla.band": [5.0, 1.0]},
            "key 'bla.band' must be [f_lo, f_hi] with 0 <= f_lo < f_hi",
        ),
        (
            {"bla.period_samples": 4000, "bla.periods": 2, "bla.band": [1.2, 1.8]},
            "key 'bla.band' holds no frequency line",
        ),
        (
            {"bla.period_samples": 4000, "bla.periods": 2, "bla.band": [1.0]},
            "key 'bla.band' must be a list of 2 numbers, got [1.0]",
        ),
        (
            {"bla.period_samples": 4000, "bla.periods": 2, "bla.lines": "even"},
            'key \'bla.lines\' must be one of "full", "odd", "random-odd", got "even"',
        ),
        (
            {
                "bla.period_samples": 4000,
                "bla.periods": 2,
                "bla.numerator_order": 4,
                "bla.denominator_order": 2,
            },
            "key 'bla.numerator_order' must not exceed 'bla.denominator_order' (2), got 4",
        ),
        (
            {"bla.period_samples": 4000, "bla.periods": 2, "bla.denominator_order": "two"},
            'key \'bla.denominator_order\' must be an integer >= 0 or "auto", got "two"',
        ),
        ({"bench.experiment": "multisine"}, "key 'bench.experiment' is \"multisine\" but there"),
        ({"bench.noise_variance": -1.0}, "key 'bench.noise_variance' must be a number >= 0"),
        ({"bench.duration": 0.0}, "key 'bench.duration' must be a number > 0, got 0.0"),
        ({"bench.seed": -3}, "key 'bench.seed' must be an integer >= 0, got -3"),
        ({"bench.misalignment_deg": [1, 2]}, "key 'bench.misalignment_deg' must be a list of 3"),
        ({"bench.gain_mismatch": [0, -1, 0]}, "key 'bench.gain_mismatch' must be a list of 3"),
        (
            {"bench.electrical_harmonics": [[1, 0.1]]},
            "key 'bench.electrical_harmonics' must be a list of [harmonic >= 2, relative ampl",
        ),
        (
            {"bench.electrical_harmonics": [[3, 0.1], [3, 0.2]]},
            "key 'bench.electrical_harmonics' lists a harmonic twice",
        ),
        ({"bench.cogging_periods": -1}, "key 'bench.cogging_periods' must be an integer >= 0"),
        ({"bench.shape_variation": -0.1}, "key 'bench.shape_variation' must be a number >= 0"),
        ({"bench.shape_harmonics": 0}, "key 'bench.shape_harmonics' must be an integer >= 1"),
    ],
)
def test_setup_value_errors(update: dict[str, Any], expected: str) -> None:
    message = _bad(update)
    assert message.startswith("setup.toml: key '")
    assert expected in message


@pytest.mark.parametrize(
    ("update", "expected"),
    [
        ({"model.harmonix": [1]}, "unknown key 'model.harmonix' (did you mean 'model.harmonics'?)"),
        ({"pole_pair": 3}, "unknown key 'pole_pair' (did you mean 'pole_pairs'?)"),
        ({"harmonics": [1]}, "unknown key 'harmonics' (did you mean 'model.harmonics'?)"),
        ({"bench.noise_var": 1.0}, "unknown key 'bench.noise_var' (did you mean 'bench.noise_v"),
        ({"plant.delay_s": 1.0}, "unknown key 'plant.delay_s' (did you mean 'plant.delay'?)"),
        ({"trajectory.stop_sample": 3}, "unknown key 'trajectory.stop_sample'"),
        ({"zzz": 1}, "unknown key 'zzz'"),
    ],
)
def test_setup_unknown_keys(update: dict[str, Any], expected: str) -> None:
    message = _bad(update)
    assert message == f"setup.toml: {expected}" or message.startswith(f"setup.toml: {expected}")


def test_setup_required_keys() -> None:
    assert _bad({}, drop=("pole_pairs",)) == (
        "setup.toml: key 'pole_pairs' is missing (it must be an integer >= 1)"
    )
    assert _bad({}, drop=("sample_time",)).startswith("setup.toml: key 'sample_time' is missing")
    assert _bad({}, drop=("controller",)).startswith("setup.toml: key 'controller' is missing")
    # an open-loop spin needs no controller
    d = {k: v for k, v in MINIMAL.items() if k != "controller"}
    d["trajectory"] = {"kind": "constant-speed"}
    setup = setup_from_dict(d)
    assert setup.controller is None
    assert setup.trajectory == TrajectorySpec(kind="constant-speed", start=0, stop=None)


def test_unknown_key_reported_before_missing_key() -> None:
    message = _bad({"model.harmonix": [1]}, drop=("controller",))
    assert "unknown key 'model.harmonix'" in message


def test_read_setup_errors(tmp_path: Path) -> None:
    path = tmp_path / "setup.toml"
    with pytest.raises(HallcalInputError) as excinfo:
        read_setup(path)
    assert _message(excinfo) == f"{path}: file not found"
    path.write_text("pole_pairs = 11\nsample_time = 2.5e-4\n[model\nbasis = 'kernel'\n")
    with pytest.raises(HallcalInputError) as excinfo:
        read_setup(path)
    message = _message(excinfo)
    assert message.startswith(f"{path}: invalid TOML: ")
    assert "line 3" in message
    path.write_text(DESIGN_EXAMPLE.replace("harmonics =", "harmonix ="))
    with pytest.raises(HallcalInputError) as excinfo:
        read_setup(path)
    assert _message(excinfo) == (
        f"{path}: unknown key 'model.harmonix' (did you mean 'model.harmonics'?)"
    )
    path.write_text(DESIGN_EXAMPLE.replace("pole_pairs = 11", "pole_pairs = 0"))
    with pytest.raises(HallcalInputError) as excinfo:
        read_setup(path)
    assert _message(excinfo) == f"{path}: key 'pole_pairs' must be an integer >= 1, got 0"


def test_time_in_samples() -> None:
    d = {**MINIMAL, "sample_time": 1.0, "bla": {"period_samples": 64, "periods": 2}}
    with pytest.raises(HallcalInputError, match="Nyquist frequency 0.5 Hz"):
        setup_from_dict(d)
    d["bla"]["band"] = [0.0, 0.25]
    setup = setup_from_dict(d)
    assert setup.sample_time == 1.0 and setup.bla is not None and setup.bla.band == (0.0, 0.25)


# ================================================================================================
# Artifact and JSON
# ================================================================================================


def _artifact(n: int = 32) -> dict[str, Any]:
    grid = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return {
        "pole_pairs": 11,
        "reconstruction": {
            "projection": np.array(
                [[2 / 3, -1 / 3, -1 / 3], [0.0, 1 / np.sqrt(3), -1 / np.sqrt(3)]]
            ),
            "offset": np.zeros(3),
        },
        "lut": {"y_hat": grid, "eta": 1e-3 * np.sin(grid)},
        "model": {"basis": "fourier", "harmonics": list(range(1, 12)), "theta": np.ones((3, 23))},
        "setup": default_setup(),
        "diagnostics": {"cost": np.float64(0.1), "iterations": np.int64(4), "bijective": True},
    }


def test_artifact_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "CAL.json"
    write_artifact(path, _artifact())
    data = read_artifact(path)
    assert data["format"] == ARTIFACT_FORMAT
    assert list(data)[0] == "format"
    assert isinstance(data["hallcal_version"], str)
    assert data["diagnostics"] == {"cost": 0.1, "iterations": 4, "bijective": True}
    assert setup_from_dict(data["setup"]) == default_setup()
    np.testing.assert_array_equal(data["lut"]["eta"], _artifact()["lut"]["eta"])
    assert np.array(data["model"]["theta"]).shape == (3, 23)
    assert path.read_text().startswith('{\n "format": "hallcal-calibration/1",')
    assert os.listdir(tmp_path) == ["CAL.json"]


def test_artifact_with_nan_is_refused_and_nothing_is_written(tmp_path: Path) -> None:
    path = tmp_path / "CAL.json"
    art = _artifact()
    art["lut"]["eta"][3] = np.nan
    with pytest.raises(ValueError) as excinfo:
        write_artifact(path, art)
    assert not isinstance(excinfo.value, HallcalInputError)
    assert _message(excinfo) == (
        f"{path}: NaN or inf at key 'lut.eta[3]' cannot be written to JSON"
    )
    assert os.listdir(tmp_path) == []
    # an existing artifact is left untouched
    write_artifact(path, _artifact())
    before = path.read_bytes()
    art = _artifact()
    art["diagnostics"]["cost"] = float("inf")
    with pytest.raises(ValueError, match="'diagnostics.cost'"):
        write_artifact(path, art)
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["CAL.json"]


def _write_raw_json(path: Path, data: Any) -> Path:
    path.write_text(json.dumps(data))
    return path


def _good_raw() -> dict[str, Any]:
    return json.loads(json.dumps({"format": ARTIFACT_FORMAT, "hallcal_version": "0.1.0"}))


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        (lambda a: a.pop("format"), "not a hallcal calibration artifact (format key missing)"),
        (lambda a: a.update(format="x"), 'unsupported format "x" (this hallcal reads'),
        (lambda a: a.pop("lut"), "key 'lut' is missing"),
        (lambda a: a.pop("hallcal_version"), "key 'hallcal_version' is missing"),
        (lambda a: a.update(pole_pairs=0), "key 'pole_pairs' must be an integer >= 1, got 0"),
        (lambda a: a.update(model=[1]), "key 'model' must be an object"),
        (
            lambda a: a["reconstruction"].update(projection=[[1, 2, 3]]),
            "key 'reconstruction.projection' must be a 2x3 array of numbers",
        ),
        (
            lambda a: a["reconstruction"].update(offset=[0, 0]),
            "key 'reconstruction.offset' must be a list of 3 numbers",
        ),
        (lambda a: a["reconstruction"].pop("offset"), "key 'reconstruction.offset' is missing"),
        (
            lambda a: a["lut"].update(eta=a["lut"]["eta"][:-1]),
            "keys 'lut.y_hat' and 'lut.eta' have different lengths (32 and 31)",
        ),
        (
            lambda a: a["lut"].update(y_hat=[0.0] * 8, eta=[0.0] * 8),
            "key 'lut.y_hat' must be a list of at least 16 numbers",
        ),
        (
            lambda a: a["lut"].update(eta=["a"] * 32),
            "key 'lut.eta' must be a list of at least 16 numbers",
        ),
        (
            lambda a: a["setup"]["model"].update(harmonix=[1]),
            "unknown key 'setup.model.harmonix' (did you mean 'setup.model.harmonics'?)",
        ),
        (
            lambda a: a["setup"].update(pole_pairs=4),
            "key 'pole_pairs' (11) differs from 'setup.pole_pairs' (4)",
        ),
    ],
)
def test_artifact_validation(tmp_path: Path, mutate: Any, expected: str) -> None:
    path = tmp_path / "CAL.json"
    write_artifact(path, _artifact())
    data = json.loads(path.read_text())
    mutate(data)
    _write_raw_json(path, data)
    with pytest.raises(HallcalInputError) as excinfo:
        read_artifact(path)
    assert _message(excinfo) == f"{path}: {expected}" or _message(excinfo).startswith(
        f"{path}: {expected}"
    )


def test_artifact_not_json_or_not_object(tmp_path: Path) -> None:
    path = tmp_path / "CAL.json"
    path.write_text('{\n "format": "hallcal-calibration/1",\n "pole_pairs": 11,,\n}\n')
    with pytest.raises(HallcalInputError) as excinfo:
        read_artifact(path)
    assert _message(excinfo).startswith(f"{path}: invalid JSON at line 3")
    path.write_text('{"format": "hallcal-calibration/1", "x": NaN}')
    with pytest.raises(HallcalInputError, match="NaN is not valid JSON"):
        read_artifact(path)
    _write_raw_json(path, [1, 2])
    with pytest.raises(HallcalInputError, match=r"not a hallcal calibration artifact \(not a JSON"):
        read_artifact(path)
    with pytest.raises(HallcalInputError, match="file not found"):
        read_artifact(tmp_path / "none.json")


def test_write_artifact_validates_structure(tmp_path: Path) -> None:
    art = _artifact()
    del art["diagnostics"]
    with pytest.raises(HallcalInputError, match="key 'diagnostics' is missing"):
        write_artifact(tmp_path / "CAL.json", art)
    assert os.listdir(tmp_path) == []


def test_json_sidecars(tmp_path: Path) -> None:
    path = tmp_path / "bla.json"
    obj = {
        "freq": np.arange(3.0),
        "ok": np.bool_(True),
        "n": np.int32(5),
        "spec": BLASpec(period_samples=8, periods=2),
        "where": tmp_path,
        "pairs": ((1, 2.5),),
    }
    write_json(path, obj)
    back = read_json(path)
    assert back["freq"] == [0.0, 1.0, 2.0] and back["ok"] is True and back["n"] == 5
    assert back["spec"]["band"] == [1.0, 400.0] and back["where"] == str(tmp_path)
    assert back["pairs"] == [[1, 2.5]]
    with pytest.raises(TypeError, match="complex array at key 'G'"):
        write_json(path, {"G": np.ones(3, dtype=complex)})
    with pytest.raises(ValueError, match=r"at key 'a\[1\]\[0\]'"):
        write_json(path, {"a": np.array([[0.0], [np.nan]])})
    with pytest.raises(TypeError, match="not JSON data"):
        write_json(path, {"a": object()})
    assert read_json(path) == back  # failed writes left the file alone


# ================================================================================================
# atomic_write
# ================================================================================================


def test_atomic_write_success_and_failure(tmp_path: Path) -> None:
    path = tmp_path / "out.txt"
    with atomic_write(path) as f:
        f.write("one\n")
        assert not path.exists()  # nothing visible before the block ends
    assert path.read_text() == "one\n"
    umask = os.umask(0o022)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask
    with pytest.raises(RuntimeError), atomic_write(path) as f:
        f.write("two\n")
        raise RuntimeError("boom")
    assert path.read_text() == "one\n"
    assert os.listdir(tmp_path) == ["out.txt"]
    with atomic_write(tmp_path / "b.bin", "wb") as f:
        f.write(b"\x00\x01")
    assert (tmp_path / "b.bin").read_bytes() == b"\x00\x01"
    with pytest.raises(ValueError, match="mode"), atomic_write(path, "a"):  # type: ignore[arg-type]
        pass


def test_atomic_write_into_missing_directory(tmp_path: Path) -> None:
    target = tmp_path / "no" / "out.json"
    with pytest.raises(HallcalInputError) as excinfo:
        write_json(target, {"a": 1})
    assert _message(excinfo).startswith(f"{target}: directory")


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="counts threads in /proc (Linux)")
def test_reading_starts_no_arrow_thread_pool(tmp_path: Path) -> None:
    """Reading Parquet leaves no Arrow thread behind and reading CSV at most one (the idle
    read-ahead thread of Arrow's serial CSV reader): Arrow's CPU pool (``cpu_count`` threads,
    2 on a 2-core machine, 3 threads in all after a CSV read before this was fixed), still alive
    at interpreter exit, can abort the process with "terminate called without an active
    exception" (apache/arrow#34314; it failed a CI run of ``reconstruct --absolute``). A child
    process counts its threads after importing pyarrow and after each read."""
    import subprocess
    import sys

    columns = {"d1": np.arange(5000.0), "d2": np.ones(5000), "d3": np.zeros(5000)}
    write_dataset(tmp_path / "d.csv", columns)
    write_dataset(tmp_path / "d.parquet", columns)
    code = (
        "import os, sys, pyarrow\n"
        "from hallcal.io import read_dataset\n"
        "n = lambda: len(os.listdir('/proc/self/task'))\n"
        "counts = [n()]\n"
        "read_dataset(sys.argv[1]); counts.append(n())\n"
        "read_dataset(sys.argv[2]); counts.append(n())\n"
        "print(*counts)\n"
    )
    res = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path / "d.parquet"), str(tmp_path / "d.csv")],
        capture_output=True,
        text=True,
        check=True,
    )
    before, after_parquet, after_csv = map(int, res.stdout.split())
    assert after_parquet == before, res.stdout
    assert after_csv <= before + 1, res.stdout
