"""The commands' standard streams in the states operators leave them in: a stdout whose reader
exited (`| head -1`, a killed `tee`) or that cannot be written (a file on a full disk). Each test
runs the real process and checks its exit code and what it printed."""

from __future__ import annotations

import os
import re
import signal
import subprocess
from pathlib import Path
from typing import IO, Any

import httpx
import pytest
from service_process import ServiceProcess, _child_env, fleetmap_command, reaped, wait_for
from test_build import flaser, scene_log

from fleetmap import cli
from fleetmap.cli import STDOUT_GONE


@pytest.mark.parametrize("stdout", ["reader gone", "full disk"])
def test_a_stdout_that_cannot_be_written_does_not_stop_the_service(tmp_path: Path, stdout: str) -> None:
    """The ready line is the service's only output on stdout. Printed into a pipe whose reader had
    exited, or into /dev/full, it raised out of uvicorn's start-up: the service stopped with a
    traceback and exit 1 once it had started. Now it logs that the line could not be printed and
    serves on, and a SIGTERM still stops it with exit 0 (not 120: Python's flush of stdout at exit
    failing too) and no traceback."""
    svc = ServiceProcess(tmp_path, ["--in-memory"])
    sink: IO[bytes]
    if stdout == "reader gone":
        read_end, write_end = os.pipe()
        os.close(read_end)  # the reader exited before the service printed anything
        sink = os.fdopen(write_end, "wb")
    else:
        sink = open("/dev/full", "wb")  # noqa: SIM115 - closed once the child has it
    # As most run it (systemd, a shell): stdout buffered, so that the line is still in the buffer
    # when the interpreter exits.
    env = {name: value for name, value in _child_env().items() if name != "PYTHONUNBUFFERED"}
    with open(svc.log_path, "wb") as log, sink:
        proc = subprocess.Popen(svc.args, stdout=sink, stderr=log, stdin=subprocess.DEVNULL, env=env)
    svc.proc = proc  # so that svc.stop() ends it
    with reaped(proc):  # type: ignore[arg-type]  # (a bytes Popen; reaped only polls and kills)
        wait_for(
            lambda: proc.poll() is not None or "cannot print the ready line" in svc.logs(),
            timeout=60, what="the ready line's failure logged",
        )  # fmt: skip
        assert proc.poll() is None, f"exit {proc.returncode}:\n{svc.logs()}"
        assert httpx.get(f"{svc.base_url}/healthz", timeout=10).status_code == 200
        assert svc.stop() == 0, svc.logs()
    logs = svc.logs()
    assert "Traceback" not in logs and "Exception ignored" not in logs, logs
    assert f"serving on: fleetmap serving {svc.base_url}" in logs, logs


@pytest.mark.parametrize("buffered", [True, False])
def test_a_command_whose_stdout_reader_exited_ends_quietly(tmp_path: Path, buffered: bool) -> None:
    """`fleetmap build ... | head -1`: a reader that exited before the command printed its summary.
    The command ended in a BrokenPipeError traceback and exit 1 (stdout unbuffered), or in Python's
    "Exception ignored ... BrokenPipeError" and exit 120 (buffered, as most run it). It now ends
    quietly with a shell's code for a command that SIGPIPE ended, 141, its outputs written."""
    env = {name: value for name, value in os.environ.items() if name != "PYTHONUNBUFFERED"}
    if not buffered:
        env["PYTHONUNBUFFERED"] = "1"
    read_end, write_end = os.pipe()
    os.close(read_end)
    log, out = scene_log(tmp_path / "scene.log"), tmp_path / "out"
    with os.fdopen(write_end, "wb") as sink:
        done = subprocess.run(
            [*fleetmap_command(), "build", str(log), "--out", str(out), "--quiet"],
            stdout=sink, stderr=subprocess.PIPE, text=True, env=env, timeout=300,
        )  # fmt: skip
    assert done.returncode == STDOUT_GONE == 141, done.stderr
    assert "Traceback" not in done.stderr and "Exception ignored" not in done.stderr, done.stderr
    assert (out / "map.yaml").is_file() and (out / "meta.json").is_file()


@pytest.mark.parametrize("stdout", ["its own", "the same pipe"])
def test_a_build_whose_stderr_reader_exited_still_writes_its_map(tmp_path: Path, stdout: str) -> None:
    """`fleetmap build ... 2>&1 | head -1`, or progress piped to a log reader that died: the reader
    of stderr exited while the build ran. The notice and the progress bar, written into that pipe,
    raised BrokenPipeError out of the build: it ended with exit 141 and without its map, the minutes
    of integration thrown away for a diagnostic no one reads. Now what is written to a stderr whose
    reader left goes nowhere, and the build writes its map: exit 0 with the summary on a stdout of
    its own; 141 when stdout is the same pipe, the map written, as for any stdout whose reader left."""
    read_end, write_end = os.pipe()
    os.close(read_end)  # the reader exited before the build printed anything
    log, out = scene_log(tmp_path / "scene.log"), tmp_path / "out"
    with os.fdopen(write_end, "wb") as sink:
        done = subprocess.run(
            [*fleetmap_command(), "build", str(log), "--out", str(out)],
            stdout=sink if stdout == "the same pipe" else subprocess.PIPE, stderr=sink, timeout=300,
        )  # fmt: skip
    assert (out / "map.yaml").is_file() and (out / "meta.json").is_file(), done.returncode
    if stdout == "the same pipe":
        assert done.returncode == STDOUT_GONE
    else:
        assert done.returncode == 0
        assert done.stdout.decode().startswith("4 scans integrated (0 skipped)"), done.stdout


@pytest.mark.parametrize("stderr", ["a pipe whose reader exited", "a full disk"])
def test_an_error_a_command_cannot_say_still_exits_with_its_code(tmp_path: Path, stderr: str) -> None:
    """A command's error line written to a stderr that cannot take it (its reader exited: `2>&1 |
    head -0`; a full disk: `2>/dev/full`) raised out of the error's handling: a traceback no one saw
    and exit 1, where a script tells a refusal (2) from a crash (1) by the code. The line goes
    nowhere now, and the command exits 2 all the same."""
    if stderr.startswith("a pipe"):
        read_end, write_end = os.pipe()
        os.close(read_end)  # the reader exited
        sink = os.fdopen(write_end, "wb")
    else:
        sink = open("/dev/full", "wb")  # noqa: SIM115 - closed by the with below
    with sink:
        done = subprocess.run(
            [*fleetmap_command(), "build", str(tmp_path / "missing.log"), "--out", str(tmp_path / "out")],
            stdout=subprocess.PIPE, stderr=sink, timeout=120,
        )  # fmt: skip
    assert done.returncode == 2, done.returncode
    assert not (tmp_path / "out").exists()


def long_build(tmp_path: Path, out: Path, sigint: Any) -> subprocess.Popen[str]:
    """`fleetmap build` of 3000 scans into `out`, started with SIGINT's disposition `sigint`."""
    lines = [flaser([19.5] * 361, 0.01 * (k % 500), 0.02 * (k % 300), 0.001 * k) for k in range(3000)]
    log = tmp_path / "long.log"
    log.write_text("\n".join(lines) + "\n")
    return subprocess.Popen(
        [*fleetmap_command(), "build", str(log), "--out", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, sigint),
    )  # fmt: skip


def integrating(build: subprocess.Popen[str]) -> str:
    """Read `long_build`'s stderr until its progress bar shows scans integrated; returns what it read."""
    assert build.stderr is not None
    progress = ""
    while not re.search(r"\| [1-9]\d*/3000 ", progress):  # tqdm's bar: scans integrated
        chunk = build.stderr.read(1)
        assert chunk, f"the build ended before its scans: {progress}"
        progress += chunk
    return progress


def test_ctrl_c_stops_a_build_between_two_scans_in_one_line(tmp_path: Path) -> None:
    """Ctrl-C while `fleetmap build` integrates: the KeyboardInterrupt was raised inside a compiled
    kernel's call and came out as numba's SystemError ("returned a result with an exception set"),
    a traceback and exit 1. Now the build stops between two scans, says so in one line, writes
    nothing and exits 130, as a shell reports Ctrl-C."""
    out = tmp_path / "out"
    build = long_build(tmp_path, out, signal.SIG_DFL)  # as a terminal starts it
    with reaped(build):
        progress = integrating(build)
        build.send_signal(signal.SIGINT)
        stdout, stderr = build.communicate(timeout=60)
    assert build.returncode == 130, progress + stderr
    assert "Traceback" not in stderr, stderr
    assert re.search(r"fleetmap build: interrupted after \d+ of 3000 scans; nothing written", stderr), stderr
    assert stdout == "" and not out.exists()


def test_a_build_started_with_sigint_ignored_keeps_ignoring_it(tmp_path: Path) -> None:
    """A build started with SIGINT ignored (`fleetmap build ... &` in a script: a non-interactive
    shell starts background jobs so, that Ctrl-C on the script leaves them running; Python keeps
    such a disposition too). The build put its own handler in place of the ignore while it
    integrated, so a Ctrl-C meant for the script stopped the background build: "interrupted,
    nothing written", exit 130. Now a SIGINT it was started ignoring changes nothing: the map is
    written and the build exits 0."""
    out = tmp_path / "out"
    build = long_build(tmp_path, out, signal.SIG_IGN)  # as `&` in a script starts it
    with reaped(build):
        progress = integrating(build)
        build.send_signal(signal.SIGINT)
        stdout, stderr = build.communicate(timeout=300)
    assert build.returncode == 0, progress + stderr
    assert "interrupted" not in stderr, stderr
    assert stdout.startswith("3000 scans integrated (0 skipped)"), stdout
    assert (out / "map.yaml").is_file() and (out / "meta.json").is_file()


def test_a_build_started_with_stderr_closed_writes_its_map_and_nothing_else_to_stdout(tmp_path: Path) -> None:
    """A build started with its stderr closed (`2>&-`, a daemon's child): Python has no sys.stderr
    then, so the kernels' notice and the progress, printed to `file=None`, went to STDOUT, into the
    summary a script reads, and the progress bar raised AttributeError: exit 1, nothing written and
    nothing said. Now its diagnostics go nowhere, as a shell's closed stderr means, and stdout has
    the summary alone; an error still exits 2, without a word on stdout."""

    def run(*args: str | Path) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [*fleetmap_command(), "build", *map(str, args)],
            stdout=subprocess.PIPE, text=True, timeout=300, preexec_fn=lambda: os.close(2),
        )  # fmt: skip

    out = tmp_path / "out"
    done = run(scene_log(tmp_path / "scene.log"), "--out", out)
    assert done.returncode == 0, done.stdout
    lines = done.stdout.splitlines()
    assert lines[0].startswith("4 scans integrated (0 skipped)"), done.stdout
    assert all(line.startswith("wrote ") for line in lines[1:]) and len(lines) == 10, done.stdout
    assert (out / "map.yaml").is_file() and (out / "meta.json").is_file()
    missing = run(tmp_path / "missing.log", "--out", tmp_path / "out2")
    assert (missing.returncode, missing.stdout) == (2, "")


def test_ctrl_c_while_the_command_starts_is_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Ctrl-C in the second or two the command takes to import its commands' modules (numba's
    among them), before any command runs: Python's traceback of the import in progress, forty
    lines, and an exit by SIGINT. Now one line and exit 130, as Ctrl-C gives while a command runs.
    (A module whose import raises KeyboardInterrupt stands for the key pressed during it.)"""
    (tmp_path / "pressed_during_import.py").write_text("raise KeyboardInterrupt\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(cli.COMMAND_MODULES, "serve", "pressed_during_import")
    assert cli.main(["serve", "--data-dir", str(tmp_path / "out")]) == cli.INTERRUPTED
    assert capsys.readouterr() == ("", "fleetmap: interrupted\n")
    assert not (tmp_path / "out").exists()


def test_a_build_whose_stdout_is_on_a_full_disk_says_so_in_one_line(tmp_path: Path) -> None:
    """`fleetmap build ... > build.log` on a full disk (here /dev/full): the summary's print raised
    OSError, a traceback and exit 1, though the map was written. Now one line says stdout could
    not be written, exit 2; the map is there."""
    log, out = scene_log(tmp_path / "scene.log"), tmp_path / "out"
    with open("/dev/full", "wb") as full:
        done = subprocess.run(
            [*fleetmap_command(), "build", str(log), "--out", str(out), "--quiet"],
            stdout=full, stderr=subprocess.PIPE, text=True, timeout=300,
        )  # fmt: skip
    assert (done.returncode, done.stderr) == (
        2, "fleetmap build: error: cannot write to stdout: No space left on device\n"
    ), done.stderr  # fmt: skip
    assert (out / "map.yaml").is_file() and (out / "meta.json").is_file()
