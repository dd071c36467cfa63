"""Output safety in hallcal.io.files: outputs that are inputs, output sets, write errors.

The command-line recipes (every command, every fault) are hostile cases
(tests/hostile_safety.py); these are the building blocks, fast and in-process, plus Ctrl-C
sent to real processes (a signal cannot be injected into click's runner).
"""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hallcal.errors import HallcalInputError
from hallcal.io import atomic_write, check_outputs, make_folder, output_set, write_json
from hallcal.io.files import _temporary_name

SRC = Path(__file__).resolve().parents[1] / "src"


def test_an_output_that_is_an_input_is_refused_however_it_is_spelled(tmp_path: Path) -> None:
    data = tmp_path / "cal.csv"
    data.write_text("x\n")
    (tmp_path / "sub").mkdir()
    (tmp_path / "link.json").symlink_to(data)
    os.link(data, tmp_path / "hard.json")
    for out in (data, tmp_path / "sub" / ".." / "cal.csv", tmp_path / "link.json",
                tmp_path / "hard.json"):  # fmt: skip
        with pytest.raises(HallcalInputError, match="is the input"):
            check_outputs([out], [data])
    check_outputs([tmp_path / "other.json"], [data, None])  # a new name is fine


def test_two_outputs_on_one_file_are_refused(tmp_path: Path) -> None:
    with pytest.raises(HallcalInputError, match="same file"):
        check_outputs([tmp_path / "b.png", tmp_path / "sub" / ".." / "b.png"])


def test_an_input_inside_an_output_folder_is_refused(tmp_path: Path) -> None:
    (tmp_path / "figures").mkdir()
    art = tmp_path / "figures" / "a.json"
    art.write_text("{}")
    with pytest.raises(HallcalInputError, match="holds the input"):
        check_outputs([], [art], folders=[tmp_path / "figures"])


def test_names_longer_than_the_file_system_allows_are_refused_and_255_works(
    tmp_path: Path,
) -> None:
    with pytest.raises(HallcalInputError, match="above the limit of 255"):
        check_outputs([tmp_path / ("x" * 256)])
    legal = tmp_path / ("y" * 255)
    check_outputs([legal])
    assert len(_temporary_name(legal)) <= 255  # the temporary name fits too
    write_json(legal, {"a": 1})
    assert legal.read_text() == '{\n "a": 1\n}\n'


def test_an_output_set_appears_whole_or_not_at_all(tmp_path: Path) -> None:
    old = {"a.h": "old a\n", "a.c": "old c\n"}
    for name, text in old.items():
        (tmp_path / name).write_text(text)
    with pytest.raises(HallcalInputError, match="cannot write"):
        with output_set():
            with atomic_write(tmp_path / "a.h") as f:
                f.write("new a\n")
            raise HallcalInputError(f"{tmp_path / 'a.c'}: cannot write (No space left on device)")
    assert {p.name: p.read_text() for p in tmp_path.iterdir()} == old  # no temporary left
    with output_set():
        for name in old:
            with atomic_write(tmp_path / name) as f:
                f.write("new\n")
        assert (tmp_path / "a.h").read_text() == "old a\n"  # nothing moves before the end
    assert {p.read_text() for p in tmp_path.iterdir()} == {"new\n"}


def test_a_failed_set_removes_the_folders_it_made_and_keeps_the_others(tmp_path: Path) -> None:
    (tmp_path / "kept").mkdir()
    with pytest.raises(KeyboardInterrupt):
        with output_set():
            make_folder(tmp_path / "kept")
            make_folder(tmp_path / "new" / "figures")
            with atomic_write(tmp_path / "new" / "figures" / "f.png", "wb") as f:
                f.write(b"png")
            raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kept"]


def test_a_folder_in_the_way_fails_the_set_before_any_rename(tmp_path: Path) -> None:
    (tmp_path / "a.h").write_text("old\n")
    (tmp_path / "a.c").mkdir()
    with pytest.raises(HallcalInputError, match="Is a directory"):
        with output_set():
            for name in ("a.h", "a.c"):
                with atomic_write(tmp_path / name) as f:
                    f.write("new\n")
    assert (tmp_path / "a.h").read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.c", "a.h"]


def test_a_file_size_limit_is_one_error_naming_the_path(tmp_path: Path) -> None:
    """EFBIG under RLIMIT_FSIZE, in a child process (the limit is the process's)."""
    code = (
        "import resource, sys\n"
        "from hallcal.io import write_json\n"
        "from hallcal.errors import HallcalInputError\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))\n"
        "try:\n"
        "    write_json(sys.argv[1], {'x': 'y' * 20000})\n"
        "except HallcalInputError as e:\n"
        "    print(e)\n"
    )
    target = tmp_path / "o.json"
    res = subprocess.run(
        [sys.executable, "-c", code, str(target)],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(SRC)},
        timeout=60,
    )
    assert res.stdout.strip() == f"{target}: cannot write (File too large)", res.stderr
    assert list(tmp_path.iterdir()) == []


def test_write_errors_of_the_system_are_one_line(tmp_path: Path, monkeypatch) -> None:
    from hallcal.io import files

    for code in (errno.ENOSPC, errno.EACCES, errno.EROFS, errno.ENAMETOOLONG):

        def fail(target: Path, code: int = code) -> Path:
            raise OSError(code, os.strerror(code))

        monkeypatch.setattr(files, "_create_temporary", fail)
        with pytest.raises(HallcalInputError) as info:
            write_json(tmp_path / "o.json", {})
        assert str(info.value) == f"{tmp_path / 'o.json'}: cannot write ({os.strerror(code)})"


def _default_interrupt() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _interrupt_when(args: list[str], cwd: Path, ready, *, group: bool = False):  # noqa: ANN001
    """Run ``hallcal ARGS``; send SIGINT (to its process group with `group`, as a terminal's
    Ctrl-C does) once ``ready(stderr_so_far)`` is true (polled every 0.02 s).

    On a loaded machine the poll can wake up after the command has already finished; then no
    signal reached it and nothing was tested, so the run is repeated (at most 3 times). A
    command that was still running when the signal was sent is judged on that run.
    """
    err = cwd / "stderr.txt"
    for _ in range(3):
        with open(err, "w") as sink:
            proc = subprocess.Popen(
                [sys.executable, "-m", "hallcal.cli", *args],
                cwd=cwd,
                env={**os.environ, "PYTHONPATH": str(SRC), "OMP_NUM_THREADS": "1"},
                stdout=subprocess.DEVNULL,
                stderr=sink,
                start_new_session=group,
                # a terminal's command: SIGINT at its default, whatever the test process inherited
                # (the suite's workers can run with it ignored: then every child ignored it too)
                preexec_fn=_default_interrupt,
            )
            for _ in range(6000):  # at most 120 s
                if proc.poll() is not None or ready(err.read_text()):
                    break
                time.sleep(0.02)
            running = proc.poll() is None
            if running and group:
                with contextlib.suppress(ProcessLookupError):  # it may end in between
                    os.killpg(proc.pid, signal.SIGINT)
            elif running:
                proc.send_signal(signal.SIGINT)
            proc.wait(timeout=120)
        if running:
            break
    assert running, "the command finished before every interrupt (3 runs)"
    return proc.returncode, err.read_text()


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A paper bench and its setup, as the hostile suite's, long enough that the SEM and each
    fleet motor take about a second or more at low load (at 8 s of recording the whole calibrate
    took 0.8 s, and a quiet machine finished before the interrupt arrived)."""
    from hostile_cases import BASE_SETUP
    from hostile_support import run_in_process, to_toml

    d = tmp_path_factory.mktemp("ctrl-c")
    setup = {**BASE_SETUP, "bench": {"ramp_end": 200.0, "duration": 40.0, "seed": 5}}
    setup["model"] = {"harmonics": list(range(1, 12)), "max_iterations": 50}  # SEM: seconds
    (d / "s.toml").write_text(to_toml(setup))
    cwd = os.getcwd()
    os.chdir(d)
    try:
        assert run_in_process(["simulate", "--setup", "s.toml", "--out", "cal.npz"]).exit_code == 0
    finally:
        os.chdir(cwd)
    return d


def test_ctrl_c_in_a_compiled_loop_is_one_line_and_exit_130(bench: Path) -> None:
    """SIGINT while numba's SEM runs (numba hands it back as a SystemError's cause)."""
    code, err = _interrupt_when(
        ["calibrate", "cal.npz", "--setup", "s.toml", "--out", "o.json"],
        bench,
        lambda text: "SEM" in text,
    )
    assert code == 130, err
    assert err.strip().splitlines()[-1] == "hallcal: aborted"
    assert "Traceback" not in err
    assert not (bench / "o.json").exists()


def test_ctrl_c_on_a_local_cluster_is_one_line(bench: Path) -> None:
    """Ctrl-C reaches the whole process group: the Dask workers must stay quiet."""
    rows = "".join(f"m{i},cal.npz,s.toml\n" for i in range(4))
    (bench / "m.csv").write_text("motor_id,data,setup\n" + rows)
    code, err = _interrupt_when(
        ["fleet", "m.csv", "--out", "batch", "--workers", "2", "--quiet"],
        bench,
        lambda text: any((bench / "batch").glob("m*/fleet.json")),  # workers are busy
        group=True,
    )
    assert code == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert err.strip().splitlines()[-1].endswith("hallcal: aborted")
