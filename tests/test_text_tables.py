"""Text tables (hallcal.io.text): the fast reader agrees with the careful one; .txt/.dat files.

The fast reader (pyarrow, NumPy loadtxt) and the careful line-by-line reader must give the same
columns, or the same one-line message, on every file. Each case below is read twice: as
``read_dataset`` reads it, and with the fast reader switched off.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hallcal.errors import HallcalInputError
from hallcal.io import read_dataset, write_dataset
from hallcal.io import text as text_module

#: The real recordings shipped with the tests (tests/data/README.md).
RINGJIG = Path(__file__).parent / "data" / "ring-jig"

#: (extension, file content); regular and irregular files, good and bad.
CASES: list[tuple[str, str]] = [
    (".csv", "d1,d2,d3\n1,2,3\n4,5,6\n"),
    (".csv", "d1,d2,d3\r\n1,2,3\r\n4,5,6\r\n"),
    (".csv", "d1,d2,d3\n1,2,3\n4,5,6"),  # no final newline
    (".csv", "\ufeffd1,d2,d3\n1,2,3\n4,5,6\n"),
    (".csv", "# bench 3, 2024\n# run 1\nd1,d2,d3\n1,2,3\n4,5,6\n"),
    (".csv", "# d1,d2,d3\n1,2,3\n4,5,6\n"),
    (".csv", "# d1;d2;d3\n\n1;2;3\n# a comment\n 4 ; 5 ;6e0\n\n"),
    (".csv", "d1\td2\td3\n1\t2\t3\n4\t5\t6\n"),
    (".csv", "d1,d2,d3,\n1,2,3,\n4,5,6,\n"),
    (".csv", "d1,d2,d3,\n1,2,3,\n4,5,6\n"),
    (".csv", '"d1","d2","d3"\n"1",2,3\n4,5,6\n'),
    (".csv", "d1,d2,d3\n1,2,3\n\n\n4,5,6\n"),
    (".csv", "d1,d2,d3\n1,2,3\n   \n4,5,6\n"),
    (".csv", "d1,d2,d3\r1,2,3\r4,5,6\r"),  # old Mac line ends
    (".csv", "d1,d2,d3\n-0,1e-310,1_000\n.5,+2,3.\n"),
    (".csv", "d1,d2,d3\n1,2,3\n4,,6\n"),
    (".csv", "d1,d2,d3\n1,2,3\n4,abc,6\n"),
    (".csv", "d1,d2,d3\n1,2,3\n1,2\n"),
    (".csv", "d1,d2,d3\n1,2,3\n1,2,3,4\n"),
    (".csv", "d1,d2,d3\n1,2,3\nnan,2,3\n"),
    (".csv", "d1,d2,d3\n1,2,3\n\n1,inf,3\n"),  # a blank line before the bad row
    (".csv", "d1,d2,d3,realization\n1,2,3,0\n\n1,2,3,0.5\n"),
    (".csv", "d1,d2,d3\n1,2,3\n1,2,1e400\n"),
    (".csv", "d1,d2,d3\n"),
    (".csv", "1,2,3\n4,5,6\n"),
    (".csv", "d1,d2,d1\n1,2,3\n"),
    (".csv", "d1,,d3\n1,2,3\n"),
    (".csv", "d1,d3,u\n1,2,3\n1,2,3\n"),
    (".csv", "d1,d2,d3\n1,2,3\n# only a comment\n"),
    (".csv", "d1,d2,d3\n1,2,3\n4,5\x0c,6\n"),
    (".txt", "37053 42140 42483\n37080 42218 42439\n37072 42250 42366\n"),
    (".txt", "37053 42140 42483\r\n37080 42218 42439\r\n"),
    (".txt", "d1 d2 d3\n1 2 3\n4 5 6\n"),
    (".txt", "t d1 d2 d3\n0 1 2 3\n1 4 5 6\n"),
    (".txt", "# d1 d2 d3\n1 2 3\n4 5 6\n"),
    (".txt", "# recorded on the ring jig, 2024\n1 2 3\n4 5 6\n"),
    (".txt", "# t d1 d2 d3\n1 2 3\n4 5 6\n"),
    (".txt", "   1.0000000e+00   2.0000000e+00   3.0000000e+00\n   4.0e+00   5.0e+00   6e0\n"),
    (".txt", "d1\td2\td3\n1\t2\t3\n4\t5\t6\n"),
    (".txt", "d1,d2,d3\n1,2,3\n4,5,6\n"),
    (".txt", "1 2 3\n\n4 5 6\n# end\n"),
    (".txt", "1 2 3 4\n5 6 7 8\n"),
    (".txt", "1 2\n3 4\n"),
    (".txt", "1 2 3\n4 5\n"),
    (".txt", "1 2 3\n4 x 6\n"),
    (".txt", "1 2 3\n4 nan 6\n"),
    (".txt", "d1 d2 d2\n1 2 3\n"),
    (".txt", "# only a comment\n"),
    (".dat", "d1 d2 d3 y_ref\n1 2 3 0.5\n4 5 6 0.25\n"),
]


def _outcome(path: Path) -> tuple[str, object]:
    try:
        ds = read_dataset(path, required=(), min_samples=1)
    except HallcalInputError as exc:
        return "error", str(exc)
    return "ok", {name: ds[name].tobytes() for name in ds.names}


def _careful_outcome(path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[str, object]:
    def decline(*args: object, **kwargs: object) -> None:
        raise text_module._NotRegular

    with monkeypatch.context() as m:
        m.setattr(text_module, "_read_fast", decline)
        return _outcome(path)


@pytest.mark.parametrize(("ext", "content"), CASES)
def test_fast_and_careful_readers_agree(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, ext: str, content: str
) -> None:
    path = tmp_path / f"data{ext}"
    path.write_bytes(content.encode("utf-8"))
    fast = _outcome(path)
    careful = _careful_outcome(path, monkeypatch)
    assert fast == careful
    if fast[0] == "error":
        assert "\n" not in str(fast[1]) and str(fast[1]).startswith(f"{path}: ")


@pytest.mark.parametrize(
    "content",
    [
        "d1,d2,d3\n1,2,3\n4,5,6\n",
        "d1,d2,d3\r\n1,2,3\r\n\r\n4,5,6",
        "# d1;d2;d3\n1;2;3\n",
        "d1,d2,d3\n1,2,3\n4,,6\n",  # declined only later, by the missing value
    ],
)
def test_the_fast_reader_takes_regular_files(tmp_path: Path, content: str) -> None:
    """The agreement above is not vacuous: regular files go through pyarrow."""
    path = tmp_path / "data.csv"
    path.write_bytes(content.encode())
    raw = path.read_bytes()
    if ",," in content:
        with pytest.raises(text_module._NotRegular):
            text_module._read_fast(path, raw, headerless_ok=False)
    else:
        cols = text_module._read_fast(path, raw, headerless_ok=False)
        assert list(cols) == ["d1", "d2", "d3"]


def test_the_fast_reader_takes_aligned_whitespace(tmp_path: Path) -> None:
    path = tmp_path / "data.txt"
    path.write_text("   1.5   2.5   3.5\n  -4.0   5.0   6.0\n")
    cols = text_module._read_fast(path, path.read_bytes(), headerless_ok=True)
    np.testing.assert_array_equal(cols["d1"], [1.5, -4.0])


_value_text = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False).map(repr),
    st.integers(-(10**20), 10**20).map(str),
    st.floats(allow_nan=False, allow_infinity=False).map(lambda v: f"{v:.6e}"),
    st.sampled_from(["", "x", "nan", "-inf", "1e999", " 7 ", "0x1", "1_0", '"2"']),
)


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    rows=st.lists(st.lists(_value_text, min_size=3, max_size=3), min_size=1, max_size=8),
    ext=st.sampled_from([".csv", ".txt"]),
    newline=st.sampled_from(["\n", "\r\n"]),
    blank_every=st.integers(0, 4),
    header=st.booleans(),
)
def test_fast_and_careful_readers_agree_on_generated_files(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    rows: list[list[str]],
    ext: str,
    newline: str,
    blank_every: int,
    header: bool,
) -> None:
    sep = "," if ext == ".csv" else " "
    lines = [sep.join(["d1", "d2", "d3"])] if header or ext == ".csv" else []
    for k, row in enumerate(rows):
        if ext == ".txt":
            row = [v.strip() or "0" for v in row]  # no empty fields between spaces
        lines.append(sep.join(row))
        if blank_every and k % blank_every == 0:
            lines.append("")
    path = tmp_path / f"gen{ext}"
    path.write_bytes((newline.join(lines) + newline).encode())
    assert _outcome(path) == _careful_outcome(path, monkeypatch)


def test_headerless_text_needs_three_columns(tmp_path: Path) -> None:
    path = tmp_path / "run.txt"
    path.write_text("1 2 3 4\n5 6 7 8\n")
    with pytest.raises(HallcalInputError) as excinfo:
        read_dataset(path)
    assert str(excinfo.value) == (
        f"{path}: no header line and 4 columns; a file without a header is read only with "
        "3 columns (d1 d2 d3): add a first line naming the columns (for example 't d1 d2 d3')"
    )


def test_headerless_ragged_row_names_the_first_row(tmp_path: Path) -> None:
    path = tmp_path / "run.txt"
    path.write_text("1 2 3\n4 5\n")
    with pytest.raises(HallcalInputError) as excinfo:
        read_dataset(path)
    assert str(excinfo.value) == f"{path}: row 2 (line 2) has 2 fields, the first row has 3"


def test_headerless_csv_is_still_refused(tmp_path: Path) -> None:
    path = tmp_path / "run.csv"
    path.write_text("1,2,3\n4,5,6\n")
    with pytest.raises(HallcalInputError, match="the first line must be a header"):
        read_dataset(path)


def test_text_files_of_the_recording_guide(tmp_path: Path) -> None:
    """The ring-jig layout: three whitespace-separated integers per line, no header."""
    path = tmp_path / "hall_calibration_one_rotation_1.txt"
    path.write_text("37053 42140 42483\n37080 42218 42439\n37072 42250 42366\n")
    ds = read_dataset(path)
    assert ds.names == ("d1", "d2", "d3")
    np.testing.assert_array_equal(ds["d2"], [42140.0, 42218.0, 42250.0])
    with_header = tmp_path / "run.dat"
    np.savetxt(with_header, np.arange(12.0).reshape(4, 3), header="d1 d2 d3")
    np.testing.assert_array_equal(read_dataset(with_header)["d3"], [2.0, 5.0, 8.0, 11.0])
    comment = tmp_path / "c.txt"
    comment.write_text("# jig 3, ring B, 2 kHz\n1 2 3\n4 5 6\n")
    assert read_dataset(comment).names == ("d1", "d2", "d3")


def test_real_ringjig_files_read_as_hall_signals() -> None:
    paths = sorted(RINGJIG.glob("*.txt"))
    assert len(paths) == 3  # the three captures ship with the tests
    for path in paths:
        ds = read_dataset(path)
        reference = np.loadtxt(path)
        assert ds.names == ("d1", "d2", "d3") and ds.n_samples == reference.shape[0]
        np.testing.assert_array_equal(ds.d, reference)


def test_text_writer_batches_and_whole_numbers(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """Rows written in several batches; whole floats keep '.0', exponents and -0.0 survive."""
    monkeypatch.setattr(text_module, "_ROWS_PER_BATCH", 3)
    # "v", not a known column: 1e22 and 5e-324 are no angle (hallcal.limits refuses them in "y")
    y = np.array([0.1, 1.0, -0.0, 1e22, 2.5e-8, 123456789.0, 5e-324, -7.0])
    n = np.arange(y.size)
    path = tmp_path / "out.csv"
    write_dataset(path, {"v": y, "n": n})
    lines = path.read_text().splitlines()
    assert lines[0] == "v,n"
    assert [line.split(",")[0] for line in lines[1:]][:3] == ["0.1", "1.0", "-0.0"]
    assert lines[4].split(",")[0] in ("1e+22", "1e22")
    assert [line.split(",")[1] for line in lines[1:]] == [str(k) for k in range(y.size)]
    back = read_dataset(path, required=())
    assert back["v"].tobytes() == y.tobytes()
    txt = tmp_path / "out.txt"
    write_dataset(txt, {"v": y, "n": n})
    assert txt.read_text().splitlines()[:2] == ["v n", "0.1 0"]
    assert read_dataset(txt, required=())["v"].tobytes() == y.tobytes()


def test_text_writer_refuses_names_whitespace_cannot_hold(tmp_path: Path) -> None:
    with pytest.raises(HallcalInputError, match="'y star' cannot be stored in a whitespace"):
        write_dataset(tmp_path / "out.txt", {"y star": np.zeros(2)})
    assert not (tmp_path / "out.txt").exists()
