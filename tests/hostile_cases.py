"""The hostile cases: malformed, corrupt, truncated, oversized and adversarial inputs.

Each :class:`Case` writes its inputs into its own folder and returns the command line to run
there; ``tests/test_hostile.py`` runs them (in a worker process under resource limits) and checks
the command-line contract of :mod:`hostile_support`, plus the case's own expectation: the exit
status (2 for a bad input, detected as such) and, for corrupt files, that the message says so.

Classes (the hostile-input contract lists the first four):

* datasets, for every reader (CSV, Parquet, HDF5, MATLAB, NPZ): empty, truncated (1 byte,
  100 bytes, half, all but the last byte), corrupt headers and footers, random bytes in the Hall
  data (no checksum: the values must be refused as implausible), the wrong format under an
  extension, scaled by 1e-300 and 1e300, NaN and inf, pickled and raw NPZ members, declared
  sizes far above the limits (HDF5 and NPZ bombs), links to other files, matrices, strings, one
  row, different lengths, special files;
* setups: invalid TOML, deep nesting, numbers out of range, and every resource limit
  (harmonics count and highest, kernel points, table size, delay, pole pairs, orders,
  experiment lengths) just above its maximum;
* artifacts: invalid JSON, deep nesting, 1e999, 10^400, a zero or rank-1 projection, implausible
  offsets and pole pairs, broken tables (too few or too many nodes, not monotone, not bijective),
  wrong shapes and types, markup and script in the texts;
* paths and options of every subcommand (export-c's C-injection paths among them), and demo.
"""

from __future__ import annotations

import copy
import dataclasses
import io
import json
import os
import shutil
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

#: Exit statuses: success, bad input, refused, fleet incomplete, interrupted (Ctrl-C).
OK, INPUT, REFUSED, FLEET_INCOMPLETE, ABORTED = 0, 2, 3, 4, 130
#: The base calibration is in normalized units (Hall amplitude 1): export-c needs the ADC's
#: counts per unit for the fixed-point variant (2048: a 12-bit converter's half range). A case's
#: own --adc-scale comes later on the command line and wins.
ADC_SCALE = ["--adc-scale", "2048"]
#: What the error line of a corrupt or truncated file must say.
CORRUPT = r"corrupt|truncated|implausible|not a valid|cannot be read|is empty|holds Python objects"


@dataclasses.dataclass(frozen=True)
class Base:
    """The valid inputs the hostile cases are derived from (tests/test_hostile.py builds them).

    Attributes
    ----------
    dir : Path
    setup_text : str
        The paper's setup, harmonics 1..11, a 1.5 s ramp (6000 samples), 2 SEM iterations.
    bla_setup_text : str
        The same with a ``[bla]`` table.
    columns : dict
        The calibration run's columns (t, r, y, u, d1, d2, d3, y_ref).
    multisine : dict
        A multisine experiment's columns (with realization).
    artifact : dict
        The calibration artifact of the run (parsed JSON).
    """

    dir: Path
    setup_text: str
    bla_setup_text: str
    columns: dict[str, np.ndarray]
    multisine: dict[str, np.ndarray]
    artifact: dict[str, Any]


@dataclasses.dataclass(frozen=True)
class Case:
    """One hostile command.

    Attributes
    ----------
    id : str
    build : callable
        ``build(folder, base) -> argv``: writes the inputs into ``folder``, returns the arguments
        after ``hallcal`` (paths relative to ``folder``, where the command runs).
    expect : tuple of int
        Exit statuses this case may end with.
    message : str or None
        A regular expression the error line must match (``re.search``).
    c_dir : str or None
        export-c's output folder: on exit 0 the generated C must compile with no symbol or macro
        beyond those of the valid export.
    html_dir : str or None
        report's output folder: on exit 0 the HTML must not contain the case's raw markup.
    xfail : str or None
        Reason of a strict expected failure (a fix owned by another branch).
    fault : dict or None
        A fault the worker injects while the case runs (``hostile_worker._fault``): a file-size
        limit, a write error or Ctrl-C at the k-th file written.
    """

    id: str
    build: Callable[[Path, Base], list[str]]
    expect: tuple[int, ...] = (INPUT,)
    message: str | None = None
    c_dir: str | None = None
    html_dir: str | None = None
    xfail: str | None = None
    fault: dict[str, Any] | None = None


def _link(base: Base, name: str, folder: Path) -> None:
    """Put one of the base inputs (s.toml, b.toml, cal.npz, ms.npz, a.json) into a case folder
    as a hard link: 800 folders share one copy (a command that writes over its input replaces
    the link, atomically, and leaves the shared file alone)."""
    os.link(base.dir / name, folder / name)


# ------------------------------------------------------------------------------------------------
# Writing datasets


def write_columns(path: Path, cols: dict[str, Any]) -> None:
    """Write columns with hallcal's own writer (the valid files every corruption starts from)."""
    from hallcal.io import write_dataset

    write_dataset(path, cols)


def _plain_parquet(path: Path, cols: dict[str, np.ndarray]) -> None:
    """Parquet without compression or dictionary encoding: the float64 values are in the file
    as they are, with no checksum over them (a corruption there parses)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    pq.write_table(
        pa.table({k: pa.array(v) for k, v in cols.items()}),
        path,
        compression="none",
        use_dictionary=False,
    )


def _rng(name: str) -> np.random.Generator:
    """A generator seeded by the case name: every run builds the same bytes."""
    return np.random.default_rng(sum(ord(c) * 131**i for i, c in enumerate(name)) % 2**63)


def _bytes_of(ext: str, cols: dict[str, np.ndarray], tmp: Path) -> bytes:
    p = tmp / f"valid{ext}"
    if ext == ".pq-plain":
        p = tmp / "valid.parquet"
        _plain_parquet(p, cols)
    else:
        write_columns(p, cols)
    raw = p.read_bytes()
    p.unlink()
    return raw


BINARY = (".parquet", ".h5", ".hdf5", ".mat", ".npz")
FORMATS = (".csv", *BINARY)


def _dataset_variants() -> list[
    tuple[str, str, Callable[[Path, Base], None], tuple[int, ...], str | None]
]:
    """(name, extension, maker, expected exits, message) of every hostile dataset file."""
    out: list[tuple[str, str, Callable[[Path, Base], None], tuple[int, ...], str | None]] = []

    def add(name: str, ext: str, maker: Callable[[Path, Base], None], expect=(INPUT,), msg=CORRUPT):
        out.append((name, ext, maker, expect, msg))

    def raw_maker(transform: Callable[[bytes, str], bytes], ext: str, source: str | None = None):
        def make(path: Path, base: Base) -> None:
            raw = _bytes_of(source or ext, base.columns, path.parent)
            path.write_bytes(transform(raw, path.name))

        return make

    for ext in FORMATS:
        e = ext.lstrip(".")
        add(f"empty-{e}", ext, lambda p, b: p.write_bytes(b""))
        # a truncated CSV is a malformed table (a short row, no rows): exit 2, any message
        tmsg = None if ext == ".csv" else CORRUPT
        add(f"trunc1-{e}", ext, raw_maker(lambda r, n: r[:1], ext), msg=tmsg)
        add(f"trunc100-{e}", ext, raw_maker(lambda r, n: r[:100], ext), msg=tmsg)
        add(f"trunchalf-{e}", ext, raw_maker(lambda r, n: r[: len(r) // 2], ext), msg=tmsg)
        # the last byte missing: a CSV then ends inside its last number, which still parses
        add(
            f"truncminus1-{e}",
            ext,
            raw_maker(lambda r, n: r[:-1], ext),
            (OK, INPUT) if ext == ".csv" else (INPUT,),
            None if ext == ".csv" else CORRUPT,
        )
        for label, scale in (("tiny", 1e-300), ("huge", 1e300)):
            add(
                f"scaled-{label}-{e}",
                ext,
                lambda p, b, s=scale: write_columns(
                    p, {k: v * s if k.startswith("d") else v for k, v in b.columns.items()}
                ),
                msg="implausible",
            )
        add(
            f"spike-{e}",
            ext,
            lambda p, b: write_columns(p, _with(b.columns, "d1", 7, 1e9)),
            msg="implausible",
        )
        add(
            f"onerow-{e}",
            ext,
            lambda p, b: write_columns(p, {k: v[:1] for k, v in b.columns.items()}),
            msg=None,
        )
        add(
            f"missing-d3-{e}",
            ext,
            lambda p, b: write_columns(p, {k: v for k, v in b.columns.items() if k != "d3"}),
            msg="d3",
        )
        add(
            f"extra-column-1e300-{e}",
            ext,
            lambda p, b: write_columns(
                p, {**b.columns, "logged": np.full(b.columns["t"].size, 1e300)}
            ),
            (OK, REFUSED),
            None,
        )
        add(
            f"int16-counts-{e}",
            ext,
            lambda p, b: write_columns(
                p,
                {
                    **b.columns,
                    **{
                        k: np.round(2000 * b.columns[k]).astype(np.int16)
                        for k in ("d1", "d2", "d3")
                    },
                },
            ),
            (OK, REFUSED),
            None,
        )
    for ext in (".csv", ".parquet", ".h5", ".mat", ".npz"):
        e = ext.lstrip(".")
        # NaN and inf cannot be written by hallcal's writer: the CSV gets them as text
        if ext == ".csv":
            add("nan-csv", ext, lambda p, b: _csv_with(p, b, "nan"), msg="NaN or inf")
            add("inf-csv", ext, lambda p, b: _csv_with(p, b, "1e999"), msg="NaN or inf")
        else:
            add(f"nan-{e}", ext, lambda p, b, x=ext: _native(p, b, "nan", x), msg="NaN or inf")
            add(f"inf-{e}", ext, lambda p, b, x=ext: _native(p, b, "inf", x), msg="NaN or inf")
    for ext in BINARY:
        e = ext.lstrip(".")
        # MATLAB's first 116 bytes are free text: its header proper starts after them
        start = 116 if ext == ".mat" else 0
        add(
            f"header-garbage-{e}",
            ext,
            raw_maker(lambda r, n, s=start: _overwrite(r, s, 64, n), ext),
        )
        add(
            f"tail-garbage-{e}", ext, raw_maker(lambda r, n: _overwrite(r, len(r) - 64, 64, n), ext)
        )
        add(
            f"text-{e}",
            ext,
            lambda p, b: p.write_bytes(b"time,d1,d2,d3\n0,1,2,3\n" * 50),
            msg="not a valid|corrupt",
        )
        add(
            f"random-{e}",
            ext,
            lambda p, b: p.write_bytes(_rng(p.name).bytes(4096)),
            msg="not a valid|corrupt",
        )
        add(
            f"middle-random-{e}",
            ext,
            raw_maker(lambda r, n: _overwrite(r, len(r) // 2, 256, n), ext),
        )
    # random bytes in the Hall data themselves: no checksum (HDF5, MATLAB, plain Parquet) so
    # the file parses; the values must be refused as implausible (NPZ: the zip's CRC-32)
    for ext, src in (
        (".h5", ".h5"),
        (".hdf5", ".hdf5"),
        (".mat", ".mat"),
        (".npz", ".npz"),
        (".parquet", ".pq-plain"),
    ):
        for k, column in enumerate(("d1", "d2", "d3")):
            add(
                f"hall-data-random-{column}-{ext.lstrip('.')}",
                ext,
                lambda p, b, x=ext, s=src, c=column, j=k: p.write_bytes(
                    _corrupt_column(
                        _bytes_of(s, b.columns, p.parent), b.columns[c], p.name, 48 + 16 * j
                    )
                ),
            )
    # the wrong format under an extension
    for ext, other in (
        (".h5", ".npz"),
        (".mat", ".parquet"),
        (".npz", ".h5"),
        (".parquet", ".mat"),
        (".csv", ".npz"),
    ):
        add(
            f"format-{other.lstrip('.')}-as-{ext.lstrip('.')}",
            ext,
            raw_maker(lambda r, n: r, ext, other),
            msg="not a valid|corrupt|UTF-8|header",
        )
    # container members that are not columns
    add("npz-pickled-object", ".npz", _npz_pickled, msg="Python objects")
    add("npz-raw-member", ".npz", _npz_raw_member)
    add("npz-header-bomb", ".npz", _npz_header_bomb, msg="limit|corrupt|declares")
    add("npz-deflate-bomb", ".npz", _npz_deflate_bomb, msg="limit")
    add("npz-bad-crc", ".npz", _npz_bad_crc, msg="corrupt")
    add(
        "npz-single-npy",
        ".npz",
        lambda p, b: np.save(open(p, "wb"), b.columns["d1"]),
        msg="single .npy",
    )
    add(
        "npz-strings",
        ".npz",
        lambda p, b: np.savez(p, **{**b.columns, "d1": b.columns["d1"].astype(str)}),
        msg="d1",
    )
    add(
        "npz-matrix",
        ".npz",
        lambda p, b: np.savez(p, **{**b.columns, "d1": np.ones((b.columns["d1"].size, 2))}),
        msg="d1",
    )
    add(
        "npz-lengths",
        ".npz",
        lambda p, b: np.savez(p, **{**b.columns, "d2": b.columns["d2"][:-5]}),
        msg="length",
    )
    add("h5-bomb", ".h5", _h5_bomb, msg="limit")
    add("h5-external-storage", ".h5", _h5_external, msg="d1")
    add("h5-external-link", ".h5", _h5_external_link, msg="d1")
    add("h5-soft-link", ".h5", _h5_soft_link, msg="d1")
    add("h5-group-column", ".h5", _h5_group_column, msg="d1")
    add("h5-string-column", ".h5", _h5_string_column, msg="d1")
    add("h5-data-group", ".h5", _h5_data_group, (OK, REFUSED), None)
    add("mat-v73", ".mat", _mat_v73, (OK, REFUSED), None)
    add("mat-struct-column", ".mat", _mat_struct, msg="d1")
    add("mat-char-column", ".mat", _mat_char, msg="d1")
    add("parquet-nulls", ".parquet", _parquet_nulls, msg="missing value")
    add("parquet-list-column", ".parquet", _parquet_list, msg="not numeric")
    add("parquet-int64-huge", ".parquet", _parquet_int_huge, msg="implausible")
    add(
        "csv-not-utf8", ".csv", lambda p, b: p.write_bytes(b"d1,d2,d3\n\xff\xfe,1,2\n"), msg="UTF-8"
    )
    add("csv-nul-bytes", ".csv", lambda p, b: p.write_bytes(b"d1,d2,d3\n1,2,\x003\n"), msg=None)
    add("csv-header-only", ".csv", lambda p, b: p.write_text("r,y,d1,d2,d3\n"), msg="no data")
    add(
        "csv-duplicate-header",
        ".csv",
        lambda p, b: p.write_text("d1,d1,d2,d3\n1,2,3,4\n2,3,4,5\n"),
        msg=None,
    )
    add("csv-ragged", ".csv", lambda p, b: p.write_text("d1,d2,d3\n1,2,3\n1,2\n"), msg=None)
    add(
        "csv-long-line",
        ".csv",
        lambda p, b: p.write_text("d1,d2,d3\n" + "1" * 5_000_000 + ",2,3\n"),
        msg=None,
    )
    add("csv-words", ".csv", lambda p, b: p.write_text("d1,d2,d3\nx,y,z\nq,r,s\n"), msg=None)
    add(
        "unknown-extension", ".xyz", lambda p, b: p.write_text("d1,d2,d3\n1,2,3\n"), msg="extension"
    )
    add("directory", ".csv", lambda p, b: p.mkdir(), msg="directory|not a regular file")
    add("missing-file", ".npz", lambda p, b: None, msg="not found")
    add("symlink-loop", ".npz", lambda p, b: os.symlink(p.name, p), msg="not found|not a regular")
    add(
        "symlink-dev-zero",
        ".npz",
        lambda p, b: os.symlink("/dev/zero", p),
        msg="not a regular file",
    )
    add("fifo", ".csv", lambda p, b: os.mkfifo(p), msg="not a regular file")
    return out


def _with(cols: dict[str, np.ndarray], name: str, i: int, value: float) -> dict[str, np.ndarray]:
    out = dict(cols)
    v = np.array(out[name], dtype=np.float64)
    v[i] = value
    out[name] = v
    return out


def _csv_with(path: Path, base: Base, token: str) -> None:
    write_columns(path, base.columns)
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    row = lines[5].split(",")
    row[header.index("d2")] = token
    lines[5] = ",".join(row)
    path.write_text("\n".join(lines) + "\n")


def _native(path: Path, base: Base, what: str, ext: str) -> None:
    """A NaN or inf in d2, written by the format's own library (hallcal's writer refuses)."""
    cols = {k: np.array(v, dtype=np.float64) for k, v in base.columns.items()}
    cols["d2"][5] = np.nan if what == "nan" else np.inf
    if ext == ".npz":
        np.savez(path, **cols)
    elif ext in (".h5", ".hdf5"):
        import h5py

        with h5py.File(path, "w") as f:
            for k, v in cols.items():
                f[k] = v
    elif ext == ".mat":
        import scipy.io

        scipy.io.savemat(path, cols, oned_as="column")
    else:
        _plain_parquet(path, cols)


def _overwrite(raw: bytes, offset: int, n: int, name: str) -> bytes:
    b = bytearray(raw)
    offset = max(0, min(offset, len(b) - n))
    b[offset : offset + n] = _rng(name).bytes(n)
    return bytes(b)


def _corrupt_column(raw: bytes, column: np.ndarray, name: str, n: int) -> bytes:
    """Random bytes over `n` bytes of a column's float64 data, found in the file."""
    needle = np.ascontiguousarray(column, dtype="<f8")[100:104].tobytes()
    i = raw.find(needle)
    if i < 0:
        raise AssertionError(f"{name}: the column's data are not stored as they are")
    return _overwrite(raw, i, n, name)


def _npz_pickled(path: Path, base: Base) -> None:
    buf = io.BytesIO()
    np.save(buf, np.array([{"evil": 1}] * 3, dtype=object), allow_pickle=True)
    with zipfile.ZipFile(path, "w") as z:
        for k, v in base.columns.items():
            b = io.BytesIO()
            np.save(b, v)
            z.writestr(f"{k}.npy", b.getvalue() if k != "d1" else buf.getvalue())


def _npz_raw_member(path: Path, base: Base) -> None:
    with zipfile.ZipFile(path, "w") as z:
        for k, v in base.columns.items():
            b = io.BytesIO()
            np.save(b, v)
            z.writestr(f"{k}.npy", b.getvalue() if k != "d1" else b"\x80\x04K\x01." * 100)


def _npz_header_bomb(path: Path, base: Base) -> None:
    """d1's header declares 10^12 values (8 TB); the member holds a few bytes."""
    header = {"descr": "<f8", "fortran_order": False, "shape": (10**12,)}
    b = io.BytesIO()
    np.lib.format.write_array_header_1_0(b, header)
    with zipfile.ZipFile(path, "w") as z:
        for k, v in base.columns.items():
            m = io.BytesIO()
            np.save(m, v)
            z.writestr(f"{k}.npy", m.getvalue() if k != "d1" else b.getvalue() + b"\0" * 64)


def _npz_deflate_bomb(path: Path, base: Base) -> None:
    """A compressed member of 30 M zeros (240 MB) in a file of a few hundred kB."""
    n = 30_000_000
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        with z.open("d1.npy", "w", force_zip64=True) as f:
            np.lib.format.write_array_header_1_0(
                f, {"descr": "<f8", "fortran_order": False, "shape": (n,)}
            )
            zeros = bytes(8 * 1_000_000)
            for _ in range(n // 1_000_000):
                f.write(zeros)
        for k in ("d2", "d3"):
            m = io.BytesIO()
            np.save(m, base.columns[k])
            z.writestr(f"{k}.npy", m.getvalue())


def _npz_bad_crc(path: Path, base: Base) -> None:
    write_columns(path, base.columns)
    raw = bytearray(path.read_bytes())
    needle = np.ascontiguousarray(base.columns["d2"], dtype="<f8")[10:12].tobytes()
    i = raw.find(needle)
    raw[i : i + 8] = np.array([0.5]).tobytes()  # a plausible value: only the CRC can tell
    path.write_bytes(bytes(raw))


def _h5_bomb(path: Path, base: Base) -> None:
    import h5py

    with h5py.File(path, "w") as f:
        for k in ("d1", "d2", "d3"):
            f.create_dataset(k, shape=(10**11,), dtype="f8", chunks=(2**20,), compression="gzip")


def _h5_external(path: Path, base: Base) -> None:
    import h5py

    with h5py.File(path, "w") as f:
        n = base.columns["d1"].size
        f.create_dataset("d1", shape=(n,), dtype="f8", external=[("/etc/passwd", 0, 8 * n)])
        f["d2"] = base.columns["d2"]
        f["d3"] = base.columns["d3"]


def _h5_external_link(path: Path, base: Base) -> None:
    import h5py

    write_columns(path.with_name("other.h5"), base.columns)
    with h5py.File(path, "w") as f:
        f["d1"] = h5py.ExternalLink("other.h5", "d1")
        f["d2"] = base.columns["d2"]
        f["d3"] = base.columns["d3"]


def _h5_soft_link(path: Path, base: Base) -> None:
    import h5py

    with h5py.File(path, "w") as f:
        f["x"] = base.columns["d1"]
        f["d1"] = h5py.SoftLink("/x")
        f["d2"] = base.columns["d2"]
        f["d3"] = base.columns["d3"]


def _h5_group_column(path: Path, base: Base) -> None:
    import h5py

    with h5py.File(path, "w") as f:
        f.create_group("d1")
        f["d2"] = base.columns["d2"]
        f["d3"] = base.columns["d3"]


def _h5_string_column(path: Path, base: Base) -> None:
    import h5py

    with h5py.File(path, "w") as f:
        f["d1"] = np.array([b"x"] * base.columns["d1"].size)
        f["d2"] = base.columns["d2"]
        f["d3"] = base.columns["d3"]


def _h5_data_group(path: Path, base: Base) -> None:
    import h5py

    with h5py.File(path, "w") as f:
        g = f.create_group("data")
        for k, v in base.columns.items():
            g[k] = v
        f["junk"] = np.ones((3, 3))


def _mat_v73(path: Path, base: Base) -> None:
    import h5py

    with h5py.File(path, "w", userblock_size=512) as f:
        for k, v in base.columns.items():
            f[k] = v[None, :]
            f[k].attrs["MATLAB_class"] = np.bytes_(b"double")
    with open(path, "r+b") as f:
        f.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64".ljust(116) + bytes(8) + b"\x00\x02IM")


def _mat_struct(path: Path, base: Base) -> None:
    import scipy.io

    scipy.io.savemat(path, {**base.columns, "d1": {"a": base.columns["d1"]}}, oned_as="column")


def _mat_char(path: Path, base: Base) -> None:
    import scipy.io

    scipy.io.savemat(path, {**base.columns, "d1": "not a signal"}, oned_as="column")


def _parquet_nulls(path: Path, base: Base) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    d1 = [float(v) for v in base.columns["d1"]]
    d1[3] = None
    cols = {k: pa.array(v) for k, v in base.columns.items()}
    cols["d1"] = pa.array(d1, type=pa.float64())
    pq.write_table(pa.table(cols), path)


def _parquet_list(path: Path, base: Base) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    cols = {k: pa.array(v) for k, v in base.columns.items()}
    cols["d1"] = pa.array([[float(v)] for v in base.columns["d1"]])
    pq.write_table(pa.table(cols), path)


def _parquet_int_huge(path: Path, base: Base) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    cols = {k: pa.array(v) for k, v in base.columns.items()}
    cols["d1"] = pa.array(np.full(base.columns["d1"].size, 2**62, dtype=np.int64))
    pq.write_table(pa.table(cols), path)


def dataset_cases() -> list[Case]:
    """Every hostile dataset through reconstruct and calibrate (each reader, both requirements
    of columns), a selection also through report, bla and calibrate --bla-data."""
    cases: list[Case] = []
    for name, ext, maker, expect, msg in _dataset_variants():
        fname = f"data{ext}"

        def build_for(cmd: str, maker=maker, fname=fname) -> Callable[[Path, Base], list[str]]:
            def build(folder: Path, base: Base) -> list[str]:
                maker(folder / fname, base)
                _link(base, "s.toml", folder)
                _link(base, "a.json", folder)
                if cmd == "reconstruct":
                    return ["reconstruct", "a.json", fname, "--out", "rec.csv"]
                if cmd == "calibrate":
                    return ["calibrate", fname, "--setup", "s.toml", "--out", "c.json"]
                if cmd == "inspect":
                    return ["inspect", fname, "--setup", "s.toml"]
                return ["report", "a.json", fname, "--out", "rep"]

            return build

        cmds = ["reconstruct", "calibrate"]
        if name.startswith(("trunchalf-", "scaled-tiny-", "hall-data-random-d1-", "spike-")):
            cmds.append("report")
        if name.startswith(("trunc", "scaled-", "hall-data-random-d2-", "empty-", "nan-", "h5-")):
            cmds.append("inspect")
        for cmd in cmds:
            # int16 counts and an extra column are valid data: calibrate may refuse the model
            # fitted to rounded counts; reconstruct must succeed
            exp = (OK,) if cmd == "reconstruct" and expect == (OK, REFUSED) else expect
            cases.append(Case(f"data-{name}-{cmd}", build_for(cmd), exp, msg))
    # the multisine experiment of bla, and --bla-data of calibrate
    for name, ext, maker, expect, msg in _multisine_variants():
        fname = f"ms{ext}"

        def build_bla(folder: Path, base: Base, maker=maker, fname=fname) -> list[str]:
            maker(folder / fname, base)
            _link(base, "b.toml", folder)
            return ["bla", fname, "--setup", "b.toml", "--out", "bla.json"]

        def build_cal(folder: Path, base: Base, maker=maker, fname=fname) -> list[str]:
            maker(folder / fname, base)
            _link(base, "b.toml", folder)
            _link(base, "cal.npz", folder)
            return [
                "calibrate",
                "cal.npz",
                "--setup",
                "b.toml",
                "--bla-data",
                fname,
                "--out",
                "c.json",
            ]

        cases.append(Case(f"ms-{name}-bla", build_bla, expect, msg))
        cases.append(Case(f"ms-{name}-calibrate", build_cal, expect, msg))
    return cases


def _multisine_variants() -> list[
    tuple[str, str, Callable[[Path, Base], None], tuple[int, ...], str | None]
]:
    def cols(base: Base, **changes: Any) -> dict[str, np.ndarray]:
        out = dict(base.multisine)
        for k, v in changes.items():
            if v is None:
                out.pop(k)
            else:
                out[k] = v
        return out

    def mk(**changes: Any) -> Callable[[Path, Base], None]:
        return lambda p, b: write_columns(
            p, cols(b, **{k: (v(b) if callable(v) else v) for k, v in changes.items()})
        )

    return [
        ("no-realization", ".npz", mk(realization=None), (INPUT,), "realization"),
        (
            "fractional-realization",
            ".npz",
            mk(realization=lambda b: b.multisine["realization"] + 0.5),
            (INPUT,),
            "whole numbers",
        ),
        (
            "realization-not-contiguous",
            ".npz",
            # realizations interleaved sample by sample
            mk(realization=lambda b: np.resize([0, 1], b.multisine["realization"].size)),
            (INPUT,),
            "realization",
        ),
        (
            "one-period",
            ".npz",
            lambda p, b: write_columns(p, {k: v[:256] for k, v in b.multisine.items()}),
            (INPUT,),
            None,
        ),
        ("u-huge", ".npz", mk(u=lambda b: b.multisine["u"] * 1e300), (INPUT,), "implausible"),
        (
            "truncated",
            ".npz",
            lambda p, b: (write_columns(p, b.multisine), p.write_bytes(p.read_bytes()[:-100])),
            (INPUT,),
            CORRUPT,
        ),
        (
            "corrupt-h5",
            ".h5",
            lambda p, b: p.write_bytes(
                _overwrite(_bytes_of(".h5", b.multisine, p.parent), 0, 64, p.name)
            ),
            (INPUT,),
            CORRUPT,
        ),
        ("empty", ".csv", lambda p, b: p.write_bytes(b""), (INPUT,), CORRUPT),
    ]


# ------------------------------------------------------------------------------------------------
# Setups


#: The base setup as the TOML layout (tests/test_hostile.py writes it with hostile_support.to_toml).
BASE_SETUP: dict[str, Any] = {
    "pole_pairs": 11,
    "sample_time": 2.5e-4,
    "controller": {"num": [2.94, -3.29, -2.10, 2.45], "den": [1, -3.45, 4.52, -2.68, 0.61]},
    "plant": {"num": [1.663e5], "den": [1, 632.6, 2702, 0], "delay": 1.2e-4},
    "model": {"harmonics": list(range(1, 12)), "max_iterations": 2},
    "bench": {"ramp_end": 7.0, "duration": 1.5, "seed": 5},
}
BLA_TABLE: dict[str, Any] = {
    "period_samples": 256,
    "periods": 3,
    "transient_periods": 1,
    "realizations": 2,
    "band": [2.0, 400.0],
}


def _setup_with(**changes: Any) -> Callable[[], str]:
    """The base setup with ``table__key=value`` changes (value None removes the key)."""

    def text() -> str:
        from hostile_support import to_toml

        d = copy.deepcopy(BASE_SETUP)
        for name, value in changes.items():
            table, _, key = name.rpartition("__")
            target = d.setdefault(table, {}) if table else d
            if value is None:
                target.pop(key, None)
            else:
                target[key] = value
        return to_toml(d)

    return text


def _setup_text(raw: str | bytes) -> Callable[[], str | bytes]:
    return lambda: raw


def _base_text() -> str:
    return _setup_with()()


def _setup_variants() -> list[
    tuple[str, Callable[[], str | bytes], tuple[int, ...], tuple[int, ...], str | None]
]:
    """(name, text, expected exits of simulate, of calibrate, message)."""
    both = (INPUT,)
    unused = (OK, REFUSED)  # a [bench] key calibrate does not read
    v: list[tuple[str, Callable[[], str | bytes], tuple[int, ...], tuple[int, ...], str | None]] = [
        ("invalid-toml", _setup_text("pole_pairs = = 3\n"), both, both, "invalid TOML"),
        ("not-utf8", _setup_text(b"pole_pairs = 11\n# \xff\xfe\n"), both, both, "UTF-8"),
        ("empty", _setup_text(""), both, both, "pole_pairs"),
        ("oversized", lambda: _base_text() + "#" * (2 * 2**20) + "\n", both, both, "limit"),
        (
            "deep-arrays",
            lambda: _base_text().replace("[model]", "x = " + "[" * 5000 + "]" * 5000 + "\n[model]"),
            both,
            both,
            "nested",
        ),
        (
            "deep-arrays-40",
            lambda: _base_text().replace("[model]", "x = " + "[" * 40 + "]" * 40 + "\n[model]"),
            both,
            both,
            "nested|limit",
        ),
        (
            "deep-inline-tables",
            lambda: _base_text().replace(
                "[model]", "x = " + "{a = " * 3000 + "1" + "}" * 3000 + "\n[model]"
            ),
            both,
            both,
            "nested",
        ),
        (
            "sample-time-1e999",
            lambda: _base_text().replace("sample_time = 0.00025", "sample_time = 1e999"),
            both,
            both,
            "range|finite",
        ),
        (
            "sample-time-nan",
            lambda: _base_text().replace("sample_time = 0.00025", "sample_time = nan"),
            both,
            both,
            "sample_time",
        ),
        (
            "pole-pairs-10e400",
            lambda: _base_text().replace("pole_pairs = 11", "pole_pairs = 1" + "0" * 400),
            both,
            both,
            "range",
        ),
        ("pole-pairs-0", _setup_with(pole_pairs=0), both, both, "pole_pairs"),
        ("pole-pairs-negative", _setup_with(pole_pairs=-11), both, both, "pole_pairs"),
        ("pole-pairs-257", _setup_with(pole_pairs=257), both, both, "limit of 256"),
        ("pole-pairs-1e6", _setup_with(pole_pairs=10**6), both, both, "limit"),
        ("pole-pairs-float", _setup_with(pole_pairs=11.0), both, both, "pole_pairs"),
        ("pole-pairs-string", _setup_with(pole_pairs="11"), both, both, "pole_pairs"),
        (
            "pole-pairs-table",
            lambda: _base_text().replace("pole_pairs = 11", "pole_pairs = {a = 1}"),
            both,
            both,
            "pole_pairs",
        ),
        ("sample-time-zero", _setup_with(sample_time=0.0), both, both, "sample_time"),
        ("sample-time-negative", _setup_with(sample_time=-2.5e-4), both, both, "sample_time"),
        ("sample-time-string", _setup_with(sample_time="fast"), both, both, "sample_time"),
        ("sample-time-1e-9", _setup_with(sample_time=1e-9), both, both, "delay"),
        (
            "harmonics-5000",
            _setup_with(model__harmonics=list(range(1, 5001))),
            both,
            both,
            "limit of 512",
        ),
        ("harmonics-1e9", _setup_with(model__harmonics=[1, 10**9]), both, both, "limit of 2048"),
        ("harmonics-zero", _setup_with(model__harmonics=[0, 1]), both, both, "harmonics"),
        ("harmonics-fraction", _setup_with(model__harmonics=[1.5]), both, both, "harmonics"),
        ("harmonics-mixed", _setup_with(model__harmonics=[1, "2"]), both, both, "harmonics"),
        ("harmonics-duplicate", _setup_with(model__harmonics=[1, 2, 2]), both, both, "twice"),
        ("harmonics-empty", _setup_with(model__harmonics=[]), both, both, "harmonics"),
        ("harmonics-typo", _setup_with(model__harmonics="Auto"), both, both, "harmonics"),
        (
            "kernel-points-1e6",
            _setup_with(model__basis="kernel", model__harmonics=None, model__points=10**6),
            both,
            both,
            "limit of 4096",
        ),
        (
            "kernel-points-4",
            _setup_with(model__basis="kernel", model__harmonics=None, model__points=4),
            both,
            both,
            "points",
        ),
        ("lut-points-8", _setup_with(model__lut_points=8), both, both, "lut_points"),
        ("lut-points-1e9", _setup_with(model__lut_points=10**9), both, both, "limit of 65000"),
        ("max-iterations-0", _setup_with(model__max_iterations=0), both, both, "max_iterations"),
        (
            "max-iterations-1e9",
            _setup_with(model__max_iterations=10**9),
            both,
            both,
            "limit of 1000",
        ),
        ("delay-1e6", _setup_with(plant__delay=1e6), both, both, "limit of 64"),
        ("delay-65-samples", _setup_with(plant__delay=65 * 2.5e-4), both, both, "limit of 64"),
        ("delay-negative", _setup_with(plant__delay=-1e-4), both, both, "delay"),
        (
            "plant-100-coefficients",
            _setup_with(plant__den=[1.0] + [0.1] * 99),
            both,
            both,
            "limit of 17",
        ),
        (
            "plant-den-leading-zero",
            _setup_with(plant__den=[0, 1, 632.6, 2702, 0]),
            both,
            both,
            "leading",
        ),
        ("plant-num-zero", _setup_with(plant__num=[0.0, 0.0]), both, both, "zero"),
        ("plant-improper", _setup_with(plant__num=[1, 2, 3, 4, 5, 6]), both, both, "proper"),
        (
            "plant-feedthrough",
            _setup_with(plant__num=[1, 2], plant__den=[1, 1], plant__delay=0.0),
            both,
            both,
            "feedthrough",
        ),
        (
            "controller-improper",
            _setup_with(controller__num=[1, 2, 3, 4, 5, 6, 7]),
            both,
            both,
            "causal",
        ),
        (
            "controller-30-coefficients",
            _setup_with(controller__den=[1.0] + [0.01] * 29),
            both,
            both,
            "limit of 17",
        ),
        (
            "controller-unstable",
            _setup_with(controller__num=[5.0], controller__den=[1, -2.5]),
            both,
            (INPUT, REFUSED),
            None,
        ),
        ("controller-missing", _setup_with(controller=None), both, both, "controller"),
        ("no-plant", _setup_with(plant=None), both, both, "plant"),
        (
            "bla-too-long",
            _setup_with(bla={**BLA_TABLE, "period_samples": 10**7, "periods": 10}),
            both,
            both,
            "limit",
        ),
        (
            "bla-realizations-1e6",
            _setup_with(bla={**BLA_TABLE, "realizations": 10**6}),
            both,
            both,
            "limit",
        ),
        (
            "bla-order-100",
            _setup_with(bla={**BLA_TABLE, "denominator_order": 100}),
            both,
            both,
            "limit",
        ),
        ("bench-duration-1e9", _setup_with(bench__duration=1e9), both, unused, "limit"),
        ("bench-duration-tiny", _setup_with(bench__duration=1e-6), both, unused, "samples"),
        ("bench-amplitude-1e300", _setup_with(bench__amplitude=1e300), both, both, "limit"),
        ("bench-offset-1e300", _setup_with(bench__offset=[1e300, 0.0, 0.0]), both, both, "limit"),
        (
            "bench-electrical-harmonics-1000",
            _setup_with(bench__electrical_harmonics=[[h, 0.01] for h in range(2, 1002)]),
            both,
            both,
            "limit",
        ),
        (
            "bench-electrical-harmonic-1e6",
            _setup_with(bench__electrical_harmonics=[[10**6, 0.01]]),
            both,
            both,
            "limit",
        ),
        ("bench-seed-negative", _setup_with(bench__seed=-1), both, both, "seed"),
        (
            "bench-seed-2e64",
            lambda: _base_text().replace("seed = 5", "seed = 36893488147419103232"),
            both,
            both,
            "range",
        ),
        (
            "bench-multisine-without-bla",
            _setup_with(bench__experiment="multisine"),
            both,
            both,
            "bla",
        ),
        ("unknown-key", _setup_with(pole_pair=11), both, both, "did you mean"),
        (
            "unknown-table",
            lambda: _base_text() + "\n[modle]\nharmonics = [1]\n",
            both,
            both,
            "unknown key",
        ),
        (
            "markup-key",
            lambda: _base_text() + '\n"[bold red]x[/]" = 1\n',
            both,
            both,
            r"\[bold red\]x\[/\]",
        ),
        (
            "trajectory-stop-before-start",
            _setup_with(trajectory={"kind": "constant-speed", "start": 100, "stop": 50}),
            both,
            both,
            "stop",
        ),
        (
            "trajectory-start-1e12",
            _setup_with(trajectory={"kind": "constant-speed", "start": 10**12}),
            both,
            both,
            "limit",
        ),
        ("bom", lambda: "\ufeff" + _base_text(), (OK,), (OK, REFUSED), None),
    ]
    return v


def setup_cases() -> list[Case]:
    """Every hostile setup through simulate and calibrate, plus setup files that are not files."""
    cases: list[Case] = []
    for name, text, exp_sim, exp_cal, msg in _setup_variants():

        def write(folder: Path, base: Base, text=text) -> None:
            content = text()
            if isinstance(content, bytes):
                (folder / "s.toml").write_bytes(content)
            else:
                (folder / "s.toml").write_text(content, encoding="utf-8")

        def build_sim(folder: Path, base: Base, write=write) -> list[str]:
            write(folder, base)
            return ["simulate", "--setup", "s.toml", "--out", "sim.npz"]

        def build_cal(folder: Path, base: Base, write=write) -> list[str]:
            write(folder, base)
            _link(base, "cal.npz", folder)
            return ["calibrate", "cal.npz", "--setup", "s.toml", "--out", "c.json"]

        cases.append(
            Case(f"setup-{name}-simulate", build_sim, exp_sim, msg if exp_sim == (INPUT,) else None)
        )
        cases.append(
            Case(
                f"setup-{name}-calibrate", build_cal, exp_cal, msg if exp_cal == (INPUT,) else None
            )
        )
    for name, maker, msg in (
        ("directory", lambda p: p.mkdir(), "directory|not a regular file"),
        ("missing", lambda p: None, "not found"),
        ("dev-zero", lambda p: os.symlink("/dev/zero", p), "not a regular file"),
    ):

        def build(folder: Path, base: Base, maker=maker) -> list[str]:
            maker(folder / "s.toml")
            return ["simulate", "--setup", "s.toml", "--out", "sim.npz"]

        cases.append(Case(f"setup-file-{name}-simulate", build, (INPUT,), msg))
    return cases


# ------------------------------------------------------------------------------------------------
# Artifacts


@dataclasses.dataclass(frozen=True)
class _Sparse:
    """A file of `size` bytes that starts with `text` (the rest a hole: instant to write)."""

    text: str
    size: int


def _art(mutate: Callable[[dict[str, Any]], Any]) -> Callable[[Base], str]:
    def text(base: Base) -> str:
        a = copy.deepcopy(base.artifact)
        mutate(a)
        return json.dumps(a)

    return text


def _art_text(edit: Callable[[str], str]) -> Callable[[Base], str | bytes]:
    return lambda base: edit(json.dumps(base.artifact))


def _set_in(path: str, value: Any) -> Callable[[dict[str, Any]], None]:
    """Set ``a.b.c`` (value None: delete it)."""

    def mutate(a: dict[str, Any]) -> None:
        *parents, last = path.split(".")
        target = a
        for p in parents:
            target = target[p]
        if value is None:
            del target[last]
        else:
            target[last] = value

    return mutate


def _lut(
    edit: Callable[[np.ndarray, np.ndarray], tuple[Any, Any]],
) -> Callable[[dict[str, Any]], None]:
    def mutate(a: dict[str, Any]) -> None:
        y_hat, eta = np.array(a["lut"]["y_hat"]), np.array(a["lut"]["eta"])
        y_hat, eta = edit(y_hat, eta)
        a["lut"]["y_hat"] = np.asarray(y_hat).tolist() if isinstance(y_hat, np.ndarray) else y_hat
        a["lut"]["eta"] = np.asarray(eta).tolist() if isinstance(eta, np.ndarray) else eta
        a["lut"]["points"] = len(a["lut"]["y_hat"]) if isinstance(a["lut"]["y_hat"], list) else 0
        a["lut"].pop("y0", None)

    return mutate


def _swap(y: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    y, e = y.copy(), e.copy()
    y[[10, 11]] = y[[11, 10]]
    e[[10, 11]] = e[[11, 10]]
    return y, e


def _fold(y: np.ndarray, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Grid kept, the map folded back over 20 nodes (y_hat decreasing there)."""
    y0 = y + e
    y2 = y.copy()
    y2[100:120] = y[100] - np.linspace(0, 0.01, 20)
    return y2, y0 - y2


def _both(pole_pairs: int) -> Callable[[dict[str, Any]], None]:
    def mutate(a: dict[str, Any]) -> None:
        a["pole_pairs"] = pole_pairs
        a["setup"]["pole_pairs"] = pole_pairs

    return mutate


def _many_harmonics(a: dict[str, Any]) -> None:
    a["model"]["harmonics"] = list(range(1, 1001))
    a["model"]["theta"] = np.zeros((3, 2001)).tolist()


def _markup_messages(a: dict[str, Any]) -> None:
    a["diagnostics"]["messages"] = [
        "<script>alert('hallcal')</script>",
        "[bold red]markup[/] and [/] and ${PFX} and %s%n",
    ]
    a["created"] = "<img src=x onerror=alert(1)>"


def _artifact_variants() -> list[
    tuple[str, Callable[[Base], str | bytes], tuple[int, ...], str | None]
]:
    """(name, content, expected exits, message)."""
    bad = (INPUT,)
    return [
        ("not-json", lambda b: "hello", bad, "invalid JSON"),
        ("empty", lambda b: "", bad, "invalid JSON"),
        (
            "truncated",
            lambda b: json.dumps(b.artifact)[: len(json.dumps(b.artifact)) // 2],
            bad,
            "invalid JSON",
        ),
        ("array", lambda b: "[1, 2, 3]", bad, "not a hallcal calibration artifact"),
        ("not-utf8", lambda b: b"\xff\xfe{}", bad, "UTF-8"),
        ("bom", lambda b: "\ufeff" + json.dumps(b.artifact), (OK,), None),
        (
            "deep-nesting",
            _art_text(lambda t: t[:-1] + ', "x": ' + "[" * 100000 + "]" * 100000 + "}"),
            bad,
            "nested",
        ),
        (
            "nesting-40",
            _art_text(lambda t: t[:-1] + ', "x": ' + "[" * 40 + "]" * 40 + "}"),
            bad,
            "nested",
        ),
        ("oversized", lambda b: _Sparse(json.dumps(b.artifact), 65 * 2**20), bad, "limit"),
        (
            "offset-1e999",
            _art_text(
                lambda t: t.replace('"offset": [', '"offset": [1e999, ', 1).replace(
                    ", 0.0]", "]", 1
                )
            ),
            bad,
            "range|offset",
        ),
        (
            "pole-pairs-10e400",
            _art_text(lambda t: t.replace('"pole_pairs": 11', '"pole_pairs": 1' + "0" * 400, 1)),
            bad,
            "range",
        ),
        (
            "pole-pairs-5000-digits",
            _art_text(lambda t: t.replace('"pole_pairs": 11', '"pole_pairs": 1' + "0" * 5000, 1)),
            bad,
            "invalid JSON|range",
        ),
        (
            "nan-literal",
            _art_text(lambda t: t.replace('"pole_pairs": 11', '"pole_pairs": NaN', 1)),
            bad,
            "NaN",
        ),
        ("format-missing", _art(_set_in("format", None)), bad, "format"),
        ("format-2", _art(_set_in("format", "hallcal-calibration/2")), bad, "unsupported format"),
        ("format-number", _art(_set_in("format", 1)), bad, "unsupported format"),
        ("no-lut", _art(_set_in("lut", None)), bad, "'lut' is missing"),
        ("no-reconstruction", _art(_set_in("reconstruction", None)), bad, "missing"),
        ("no-model", _art(_set_in("model", None)), bad, "missing"),
        ("no-setup", _art(_set_in("setup", None)), bad, "missing"),
        ("no-diagnostics", _art(_set_in("diagnostics", None)), bad, "missing"),
        ("no-version", _art(_set_in("hallcal_version", None)), bad, "hallcal_version"),
        ("pole-pairs-0", _art(_both(0)), bad, "pole_pairs"),
        ("pole-pairs-negative", _art(_both(-11)), bad, "pole_pairs"),
        ("pole-pairs-1e6", _art(_both(10**6)), bad, "limit of 256"),
        ("pole-pairs-257", _art(_both(257)), bad, "limit of 256"),
        ("pole-pairs-float", _art(_set_in("pole_pairs", 11.0)), bad, "pole_pairs"),
        ("pole-pairs-string", _art(_set_in("pole_pairs", "11")), bad, "pole_pairs"),
        ("pole-pairs-true", _art(_set_in("pole_pairs", True)), bad, "pole_pairs"),
        ("pole-pairs-mismatch", _art(_set_in("pole_pairs", 12)), bad, "differs"),
        (
            "projection-zero",
            _art(_set_in("reconstruction.projection", [[0, 0, 0], [0, 0, 0]])),
            bad,
            "all zero",
        ),
        (
            "projection-rank1",
            _art(_set_in("reconstruction.projection", [[1, -0.5, -0.5], [2, -1, -1]])),
            bad,
            "rank 1",
        ),
        (
            "projection-ill-conditioned",
            _art(_set_in("reconstruction.projection", [[1, -0.5, -0.5], [1, -0.5, -0.5 + 1e-7]])),
            bad,
            "condition number",
        ),
        (
            "projection-3x3",
            _art(_set_in("reconstruction.projection", [[1, 0, 0], [0, 1, 0], [0, 0, 1]])),
            bad,
            "2x3",
        ),
        (
            "projection-strings",
            _art(_set_in("reconstruction.projection", [["a", "b", "c"], ["d", "e", "f"]])),
            bad,
            "2x3",
        ),
        (
            "projection-ragged",
            _art(_set_in("reconstruction.projection", [[1, 0], [0, 1, 0]])),
            bad,
            "2x3",
        ),
        (
            "projection-1e300",
            _art(
                _set_in("reconstruction.projection", [[1e300, -5e299, -5e299], [0, 8e299, -8e299]])
            ),
            bad,
            "implausible",
        ),
        (
            "projection-1e-300",
            _art(
                _set_in(
                    "reconstruction.projection", [[1e-300, -5e-301, -5e-301], [0, 8e-301, -8e-301]]
                )
            ),
            bad,
            "implausible",
        ),
        ("offset-1e300", _art(_set_in("reconstruction.offset", [1e300, 0, 0])), bad, "implausible"),
        ("offset-short", _art(_set_in("reconstruction.offset", [0, 0])), bad, "offset"),
        ("offset-null", _art(_set_in("reconstruction.offset", None)), bad, "offset"),
        ("lut-8-nodes", _art(_lut(lambda y, e: (y[::512], e[::512]))), bad, "at least 16"),
        (
            "lut-70000-nodes",
            _art(_lut(lambda y, e: (np.linspace(0, 6.28, 70000), np.zeros(70000)))),
            bad,
            "limit of 65000",
        ),
        ("lut-not-monotone", _art(_lut(_swap)), bad, "not bijective"),
        (
            "lut-reversed",
            _art(_lut(lambda y, e: (y[::-1].copy(), e[::-1].copy()))),
            bad,
            "not bijective",
        ),
        ("lut-folded", _art(_lut(_fold)), bad, "not bijective"),
        ("lut-eta-4", _art(_lut(lambda y, e: (y, e + 4.0))), bad, "pi"),
        ("lut-shifted", _art(_lut(lambda y, e: (y + 100.0, e))), bad, "revolution"),
        ("lut-lengths", _art(_lut(lambda y, e: (y, e[:-1]))), bad, "lengths"),
        ("lut-strings", _art(_lut(lambda y, e: (["x"] * y.size, e))), bad, "y_hat"),
        ("lut-empty", _art(_lut(lambda y, e: ([], []))), bad, "at least 16"),
        ("lut-points-mismatch", _art(_set_in("lut.points", 7)), bad, "points"),
        ("lut-y0-inconsistent", _art(lambda a: a["lut"]["y0"].__setitem__(5, 3.0)), bad, "y0"),
        ("theta-shape", _art(_set_in("model.theta", [[1.0, 2.0]])), bad, "theta"),
        (
            "theta-1e300",
            _art(lambda a: a["model"]["theta"][0].__setitem__(0, 1e300)),
            bad,
            "implausible",
        ),
        ("harmonics-1e9", _art(_set_in("model.harmonics", [10**9])), bad, "limit"),
        ("harmonics-1000", _art(_many_harmonics), bad, "limit"),
        ("basis-unknown", _art(_set_in("model.basis", "spline")), bad, "basis"),
        ("setup-unknown-key", _art(_set_in("setup.bogus", 1)), bad, "unknown key"),
        ("setup-not-table", _art(_set_in("setup", [1, 2])), bad, "setup"),
        ("setup-delay-huge", _art(_set_in("setup.plant.delay", 1e6)), bad, "limit"),
        (
            "setup-feedthrough",
            _art(lambda a: a["setup"]["plant"].update(num=[1, 2], den=[1, 1], delay=0.0)),
            bad,
            "feedthrough",
        ),
        ("status-bogus", _art(_set_in("diagnostics.status", "bogus")), bad, "status"),
        ("messages-huge", _art(_set_in("diagnostics.messages", ["x" * 100_000])), bad, "limit"),
        ("messages-numbers", _art(_set_in("diagnostics.messages", [1, 2])), bad, "messages"),
        (
            "cost-history-strings",
            _art(_set_in("diagnostics.cost_history", ["a", "b"])),
            bad,
            "cost_history",
        ),
        (
            "cost-history-long",
            _art(_set_in("diagnostics.cost_history", [1.0] * 5000)),
            bad,
            "limit",
        ),
        (
            "noise-variance-string",
            _art(_set_in("diagnostics.noise_variance", "small")),
            bad,
            "noise_variance",
        ),
        ("timings-strings", _art(_set_in("diagnostics.timings", {"sem": "fast"})), bad, "timings"),
        ("diagnostics-list", _art(_set_in("diagnostics", [1])), bad, "diagnostics"),
        (
            "plant-feedthrough",
            _art(lambda a: a["plant"].update(num=[1, 2], den=[1, 1], delay=0.0)),
            bad,
            "feedthrough",
        ),
        ("plant-delay-huge", _art(_set_in("plant.delay", 1e6)), bad, "limit"),
        ("plant-strings", _art(_set_in("plant.num", ["x"])), bad, "plant.num"),
        ("plant-den-zero", _art(_set_in("plant.den", [0, 0, 1])), bad, "plant"),
        ("version-huge", _art(_set_in("hallcal_version", "1" * 10_000)), bad, "limit|version"),
        ("version-number", _art(_set_in("hallcal_version", 1)), bad, "hallcal_version"),
        ("version-newline", _art(_set_in("hallcal_version", "1.0\n#define X")), bad, "version"),
        ("markup-and-script", _art(_markup_messages), (OK,), None),
    ]


def artifact_cases() -> list[Case]:
    """Every hostile artifact through reconstruct, export-c and report."""
    cases: list[Case] = []
    for name, content, expect, msg in _artifact_variants():

        def write(folder: Path, base: Base, content=content) -> None:
            data = content(base)
            if isinstance(data, _Sparse):
                with open(folder / "a.json", "w", encoding="utf-8") as f:
                    f.write(data.text)
                    f.truncate(data.size)
            elif isinstance(data, bytes):
                (folder / "a.json").write_bytes(data)
            else:
                (folder / "a.json").write_text(data, encoding="utf-8")
            _link(base, "cal.npz", folder)

        def rec(folder: Path, base: Base, write=write) -> list[str]:
            write(folder, base)
            return ["reconstruct", "a.json", "cal.npz", "--out", "rec.csv"]

        def exp(folder: Path, base: Base, write=write) -> list[str]:
            write(folder, base)
            return ["export-c", *ADC_SCALE, "a.json", "--out", "fw"]

        def rep(folder: Path, base: Base, write=write) -> list[str]:
            write(folder, base)
            return ["report", "a.json", "cal.npz", "--out", "rep"]

        html = "rep" if name == "markup-and-script" else None
        cases.append(Case(f"artifact-{name}-reconstruct", rec, expect, msg))
        cases.append(Case(f"artifact-{name}-export-c", exp, expect, msg, c_dir="fw"))
        cases.append(Case(f"artifact-{name}-report", rep, expect, msg, html_dir=html))
    return cases


# ------------------------------------------------------------------------------------------------
# Paths and options


#: Artifact paths that try to close the C comment the exporter writes them into (the
#: injection: a line splice by backslash-newline or by the trigraph ??/, or a plain "*/"), and
#: other names that must come out as harmless text.
INJECTION_PATHS: dict[str, str] = {
    "splice": "x*\\\n/\n#define HALLCAL_INJECTED 1\nint hallcal_injected_symbol = 42;\n/*.json",
    "trigraph": "x*??/\n/\n#define HALLCAL_INJECTED 1\nint hallcal_injected_symbol = 42;\n/*.json",
    "newline": "a\n#define HALLCAL_INJECTED 1\nb.json",
    "comment-close": "x*/int hallcal_injected_symbol = 42;/*.json",
}
HARMLESS_PATHS: dict[str, str] = {
    "non-ascii": "é ü 中 ☃.json",
    "long-name": "a" * 240 + ".json",
    "format-strings": "%s%n$PFX${banner}{0}.json",
    "backslash-end": "x\\.json",
    "quotes": "\"'`.json",
}


def _place_artifact(folder: Path, base: Base, rel: str) -> None:
    p = folder / rel
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(base.artifact))


def option_cases() -> list[Case]:
    """Hostile paths and option values for every subcommand, and the group itself."""
    cases: list[Case] = []

    def c(
        id: str, build: Callable[[Path, Base], list[str]], expect=(INPUT,), msg=None, **kw: Any
    ) -> None:
        cases.append(Case(f"option-{id}", build, expect, msg, **kw))

    def with_inputs(args: list[str]) -> Callable[[Path, Base], list[str]]:
        def build(folder: Path, base: Base) -> list[str]:
            _link(base, "s.toml", folder)
            _link(base, "b.toml", folder)
            _link(base, "a.json", folder)
            _link(base, "cal.npz", folder)
            _link(base, "ms.npz", folder)
            (folder / "afile").write_text("x")
            return list(args)

        return build

    for key, rel in INJECTION_PATHS.items():

        def build(folder: Path, base: Base, rel=rel) -> list[str]:
            _place_artifact(folder, base, rel)
            return ["export-c", *ADC_SCALE, rel, "--out", "fw"]

        c(f"export-c-path-{key}", build, (OK, INPUT), c_dir="fw")
    for key, rel in HARMLESS_PATHS.items():

        def build(folder: Path, base: Base, rel=rel) -> list[str]:
            _place_artifact(folder, base, rel)
            return ["export-c", *ADC_SCALE, rel, "--out", "fw"]

        c(f"export-c-path-{key}", build, (OK,), c_dir="fw")
    c(
        "export-c-out-non-ascii",
        with_inputs(["export-c", *ADC_SCALE, "a.json", "--out", "fw é ☃"]),
        (OK,),
        c_dir="fw é ☃",
    )
    c(
        "export-c-out-newline",
        with_inputs(["export-c", *ADC_SCALE, "a.json", "--out", "fw\nx"]),
        (OK,),
        c_dir="fw\nx",
    )
    c(
        "export-c-out-markup",
        with_inputs(["export-c", *ADC_SCALE, "a.json", "--out", "fw[/]"]),
        (OK,),
        c_dir="fw[/]",
    )
    c(
        "export-c-out-is-file",
        with_inputs(["export-c", *ADC_SCALE, "a.json", "--out", "afile"]),
        msg="afile",
    )
    c(
        "export-c-out-proc",
        with_inputs(["export-c", *ADC_SCALE, "a.json", "--out", "/proc/hallcal-fw"]),
        msg="hallcal-fw",
    )
    c(
        "export-c-no-fixed-point",
        with_inputs(["export-c", *ADC_SCALE, "a.json", "--out", "fw", "--no-fixed-point"]),
        (OK,),
        c_dir="fw",
    )
    for label, value in (
        ("1e30", "1e30"),
        ("zero", "0"),
        ("negative", "-1"),
        ("nan", "nan"),
        ("inf", "inf"),
        ("1e-30", "1e-30"),
        ("word", "big"),
    ):
        c(
            f"export-c-adc-scale-{label}",
            with_inputs(["export-c", *ADC_SCALE, "a.json", "--out", "fw", "--adc-scale", value]),
            msg="adc[-_]scale",
        )
    c(
        "export-c-adc-scale-2e31",
        with_inputs(["export-c", *ADC_SCALE, "a.json", "--out", "fw", "--adc-scale", str(2.0**31)]),
        (OK, INPUT),
        c_dir="fw",
    )
    c(
        "export-c-missing-artifact",
        with_inputs(["export-c", *ADC_SCALE, "nope.json", "--out", "fw"]),
        msg="not found",
    )
    c("export-c-no-out", with_inputs(["export-c", *ADC_SCALE, "a.json"]), msg="--out")
    # the exporter's own options
    for option, values in (
        ("--prefix", ["x; int y", "int", "a" * 200, "", "hallcal\n#define X 1", "é"]),
        ("--table-points", ["0", "-1", "3", "1000000000", "x"]),
        ("--tolerance", ["nan", "-1", "inf", "1e300"]),
        ("--max-speed", ["nan", "-1", "0", "inf", "1e300"]),
        ("--fault-after", ["-1", "1000000000000", "x"]),
    ):
        for i, value in enumerate(values):
            c(
                f"export-c{option[1:]}-{i}",
                with_inputs(["export-c", *ADC_SCALE, "a.json", "--out", "fw", option, value]),
                msg=option.strip("-").replace("-", "[-_]"),
            )
    # simulate
    c(
        "simulate-out-unknown-extension",
        with_inputs(["simulate", "--setup", "s.toml", "--out", "x.xyz"]),
        msg="extension",
    )
    c(
        "simulate-out-missing-dir",
        with_inputs(["simulate", "--setup", "s.toml", "--out", "nope/x.npz"]),
        msg="does not exist",
    )
    c(
        "simulate-out-proc",
        with_inputs(["simulate", "--setup", "s.toml", "--out", "/proc/x.npz"]),
        msg="x.npz",
    )
    c(
        "simulate-out-markup",
        with_inputs(["simulate", "--setup", "s.toml", "--out", "x[bold].npz"]),
        (OK,),
    )
    c("simulate-out-is-dir", with_inputs(["simulate", "--setup", "s.toml", "--out", "."]), msg=None)
    c(
        "simulate-multisine-without-bla",
        with_inputs(
            ["simulate", "--setup", "s.toml", "--experiment", "multisine", "--out", "x.npz"]
        ),
        msg="bla",
    )
    c(
        "simulate-experiment-bogus",
        with_inputs(["simulate", "--setup", "s.toml", "--experiment", "sine", "--out", "x.npz"]),
        msg="experiment",
    )
    c(
        "simulate-seed-negative",
        with_inputs(["simulate", "--setup", "s.toml", "--seed", "-1", "--out", "x.npz"]),
        msg="seed",
    )
    c(
        "simulate-seed-2e70",
        with_inputs(["simulate", "--setup", "s.toml", "--seed", str(2**70), "--out", "x.npz"]),
        msg="seed",
    )
    c(
        "simulate-seed-word",
        with_inputs(["simulate", "--setup", "s.toml", "--seed", "abc", "--out", "x.npz"]),
        msg="seed",
    )
    c("simulate-no-out", with_inputs(["simulate", "--setup", "s.toml"]), msg="--out")

    def sidecar_is_dir(folder: Path, base: Base) -> list[str]:
        _link(base, "s.toml", folder)
        (folder / "x.truth.json").mkdir()  # where simulate writes the truth next to the data
        return ["simulate", "--setup", "s.toml", "--out", "x.npz"]

    c("simulate-sidecar-is-dir", sidecar_is_dir, msg="truth.json")
    c(
        "simulate-missing-setup",
        with_inputs(["simulate", "--setup", "nope.toml", "--out", "x.npz"]),
        msg="not found",
    )
    # calibrate
    c(
        "calibrate-out-missing-dir",
        with_inputs(["calibrate", "cal.npz", "--setup", "s.toml", "--out", "nope/c.json"]),
        msg="does not exist",
    )
    c(
        "calibrate-out-proc",
        with_inputs(["calibrate", "cal.npz", "--setup", "s.toml", "--out", "/proc/c.json"]),
        msg="c.json",
    )
    c(
        "calibrate-bla-data-missing",
        with_inputs(
            [
                "calibrate",
                "cal.npz",
                "--setup",
                "b.toml",
                "--bla-data",
                "nope.npz",
                "--out",
                "c.json",
            ]
        ),
        msg="not found",
    )
    c(
        "calibrate-bla-data-without-bla-table",
        with_inputs(
            ["calibrate", "cal.npz", "--setup", "s.toml", "--bla-data", "ms.npz", "--out", "c.json"]
        ),
        msg="bla",
    )
    c("calibrate-no-setup", with_inputs(["calibrate", "cal.npz", "--out", "c.json"]), msg="--setup")
    c(
        "calibrate-data-is-artifact",
        with_inputs(["calibrate", "a.json", "--setup", "s.toml", "--out", "c.json"]),
        msg="extension",
    )
    c(
        "calibrate-force",
        with_inputs(["calibrate", "cal.npz", "--setup", "s.toml", "--out", "c.json", "--force"]),
        (OK,),
    )
    # reconstruct
    c(
        "reconstruct-out-unknown-extension",
        with_inputs(["reconstruct", "a.json", "cal.npz", "--out", "x.xyz"]),
        msg="extension",
    )
    c(
        "reconstruct-out-missing-dir",
        with_inputs(["reconstruct", "a.json", "cal.npz", "--out", "nope/x.csv"]),
        msg="does not exist",
    )
    c(
        "reconstruct-out-is-dir",
        with_inputs(["reconstruct", "a.json", "cal.npz", "--out", "."]),
        msg=None,
    )
    c(
        "reconstruct-artifact-is-data",
        with_inputs(["reconstruct", "cal.npz", "cal.npz", "--out", "x.csv"]),
        msg="JSON|UTF-8",
    )
    c(
        "reconstruct-data-is-setup",
        with_inputs(["reconstruct", "a.json", "s.toml", "--out", "x.csv"]),
        msg="extension",
    )
    c(
        "reconstruct-over-its-input",
        with_inputs(["reconstruct", "a.json", "cal.npz", "--out", "cal.npz"]),
        msg="is the input",  # the recording would be lost: refused before any work
    )
    # report
    c(
        "report-out-is-file",
        with_inputs(["report", "a.json", "cal.npz", "--out", "afile"]),
        msg="afile",
    )
    c(
        "report-out-proc",
        with_inputs(["report", "a.json", "cal.npz", "--out", "/proc/hallcal-rep"]),
        msg="hallcal-rep",
    )
    c(
        "report-validation-corrupt",
        _report_with("val.npz", lambda p, b: p.write_bytes(b"PK\x03\x04garbage")),
        msg=CORRUPT,
    )
    c(
        "report-validation-no-y-ref",
        _report_with(
            "val.npz",
            lambda p, b: write_columns(p, {k: v for k, v in b.columns.items() if k != "y_ref"}),
        ),
        msg="y_ref",
    )
    c("report-auto-bla-corrupt", _report_auto_bla(lambda: "{not json"), (OK,))
    c(
        "report-auto-bla-hostile",
        _report_auto_bla(
            lambda: json.dumps(
                {
                    "format": "hallcal-bla/1",
                    "nonparametric": {"freq": [[1]] * 3},
                    "parametric": [],
                    "plant": "x",
                }
            )
        ),
        (OK,),
    )
    c("report-auto-bla-deep", _report_auto_bla(lambda: "[" * 100000 + "]" * 100000), (OK,))
    c(
        "report-auto-bla-lists",
        _report_auto_bla(
            lambda: json.dumps(
                {"format": "hallcal-bla/1", "nonparametric": [1], "parametric": [2], "plant": [3]}
            )
        ),
        (OK,),
    )
    c(
        "report-auto-bla-huge-arrays",
        _report_auto_bla(
            lambda: json.dumps(
                {
                    "format": "hallcal-bla/1",
                    "nonparametric": {"kind": "nonparametric-bla", "freq": [1e300] * 1000},
                    "parametric": {"kind": "parametric-bla", "num": ["x"], "den": [0]},
                    "plant": {"num": [1], "den": [1, 1], "delay": -1},
                }
            )
        ),
        (OK,),
    )
    # reconstruct --absolute reads the artifact's power-up entry
    c(
        "reconstruct-absolute",
        with_inputs(["reconstruct", "a.json", "cal.npz", "--absolute", "--out", "x.csv"]),
        (OK, REFUSED),
    )
    for label, entry, msg in (
        ("grid-1e9", {"grid": 10**9}, "identifiability.grid"),
        ("list", [1, 2], "identifiability"),
        ("empty", {}, "identifiability"),
        ("strings", {"status": 5, "reason": [], "message": {}}, "identifiability"),
        ("pole-pairs", {"pole_pairs": 12}, "identifiability.pole_pairs"),
        ("budget-1e12", {"standstill_budget": 10**12}, "standstill_budget"),
    ):

        def build_absolute(folder: Path, base: Base, entry=entry) -> list[str]:
            art = copy.deepcopy(base.artifact)
            if isinstance(entry, dict) and entry and isinstance(art.get("identifiability"), dict):
                art["identifiability"].update(entry)
            else:
                art["identifiability"] = entry
            (folder / "a.json").write_text(json.dumps(art))
            _link(base, "cal.npz", folder)
            return ["reconstruct", "a.json", "cal.npz", "--absolute", "--out", "x.csv"]

        c(f"reconstruct-absolute-identifiability-{label}", build_absolute, msg=msg)
    # inspect
    for label, value in (("zero", "0"), ("257", "257"), ("1e6", "1000000"), ("word", "x")):
        c(
            f"inspect-pole-pairs-{label}",
            with_inputs(["inspect", "cal.npz", "--pole-pairs", value]),
            msg="pole-pairs",
        )
    c("inspect-plain", with_inputs(["inspect", "cal.npz", "--setup", "s.toml"]), (OK,))
    c(
        "inspect-setup-is-data",
        with_inputs(["inspect", "cal.npz", "--setup", "cal.npz"]),
        msg="UTF-8",
    )
    # bla
    c(
        "bla-no-bla-table",
        with_inputs(["bla", "ms.npz", "--setup", "s.toml", "--out", "bla.json"]),
        msg="bla",
    )
    c(
        "bla-out-missing-dir",
        with_inputs(["bla", "ms.npz", "--setup", "b.toml", "--out", "nope/bla.json"]),
        msg="does not exist",
    )
    c(
        "bla-calibration-data",
        with_inputs(["bla", "cal.npz", "--setup", "b.toml", "--out", "bla.json"]),
        msg="realization",
    )
    # demo (only options that fail before the study runs: the study itself takes a minute)
    c("demo-out-is-file", with_inputs(["demo", "--out", "afile"]), msg="afile")
    c("demo-out-proc", with_inputs(["demo", "--out", "/proc/hallcal-demo"]), msg="hallcal-demo")
    c("demo-seed-negative", with_inputs(["demo", "--seed", "-1", "--out", "dm"]), msg="seed")
    c("demo-seed-2e70", with_inputs(["demo", "--seed", str(2**70), "--out", "dm"]), msg="seed")
    c("demo-seed-word", with_inputs(["demo", "--seed", "x", "--out", "dm"]), msg="seed")
    c("demo-unknown-option", with_inputs(["demo", "--fast"]), msg="--fast")
    # the group
    c("no-arguments", with_inputs([]), msg="no command")
    c("unknown-command", with_inputs(["calibrat"]), msg="calibrat")
    c("help", with_inputs(["--help"]), (OK,))
    c("version", with_inputs(["--version"]), (OK,))
    c("calibrate-help", with_inputs(["calibrate", "--help"]), (OK,))
    return cases


def _report_with(
    name: str, maker: Callable[[Path, Base], None]
) -> Callable[[Path, Base], list[str]]:
    def build(folder: Path, base: Base) -> list[str]:
        _link(base, "a.json", folder)
        _link(base, "cal.npz", folder)
        maker(folder / name, base)
        return ["report", "a.json", "cal.npz", "--validation", name, "--out", "rep"]

    return build


def _report_auto_bla(text: Callable[[], str]) -> Callable[[Path, Base], list[str]]:
    """report reads bla.json next to an artifact whose plant came from a BLA: a hostile one
    must not break the report (it is optional: the report goes on without it)."""

    def build(folder: Path, base: Base) -> list[str]:
        art = copy.deepcopy(base.artifact)
        art["plant"]["source"] = "bla"
        (folder / "a.json").write_text(json.dumps(art))
        (folder / "bla.json").write_text(text())
        _link(base, "cal.npz", folder)
        return ["report", "a.json", "cal.npz", "--out", "rep"]

    return build


def all_cases() -> list[Case]:
    """Every hostile case, with unique ids."""
    from hostile_safety import safety_cases

    cases = dataset_cases() + setup_cases() + artifact_cases() + option_cases() + safety_cases()
    ids = [c.id for c in cases]
    duplicates = {i for i in ids if ids.count(i) > 1}
    if duplicates:
        raise AssertionError(f"duplicate case ids: {sorted(duplicates)}")
    return cases


def remove(path: Path) -> None:
    """Remove a case folder, whatever is in it (links, FIFOs, read-only files)."""
    shutil.rmtree(path, ignore_errors=True)
