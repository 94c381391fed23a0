"""Usage errors of the `sss` command: a short message and exit code 2, never a traceback.

Run as a user runs it (a separate process through the installed entry module), so that the error
path itself is exercised with exactly the packages the install declares.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from sss_process import run_sss


def _sss(*args: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "SSS_DEBUG"}
    env["COLUMNS"] = "200"
    return run_sss(args, env=env)


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["capture", "--object", "apple", "--view", "2"], "No such option"),
        (["relight", "some_session"], "--pattern"),
        (["capture", "--object", "apple", "--views", "two"], "--views"),
        (["capture", "--object", "apple", "--views", "100000"], "turntable takes at most 3600 views, got 100000"),
        (["capture", "--version"], "No such option"),
        (["sim", "--object", "apple", "--views", "-"], "--views"),
        (["relight", "no_session", "--pattern", "checkerboard", "--format", "tiff"], "choose png, exr"),
        (["capture", "--object", "apple", "--transport", "photon_beams"], "unknown transport model 'photon_beams'"),
        (["geometry", "no_session", "--backend", "measured"], "placed by the decoded correspondences"),
        (["capture", "--object", "apple", "--hdr-exposures", "0.25,1,x"], "--hdr-exposures takes comma-separated"),
        (["capture", "--object", "apple", "--hdr-exposures", "1,1"], "HDR exposures must be 2 to 8 distinct"),
        (["eval", "relight", "s", "--backend", "none,torch"], "the torch backend needs --checkpoint"),
        (["eval", "relight", "s", "--backend", "none,nonsense"], "unknown backend 'nonsense'; available: analytic, blend"),
        (["eval", "relight", "s", "--backend", "blend", "--checkpoint", "/nonexistent/ck.pt"], "no checkpoint at /nonexistent/ck.pt"),
        (["eval", "relight", "s", "--checkpoint", "/nonexistent/run"], "no checkpoint at /nonexistent/run"),  # was a note
        (["eval", "relight", "/nonexistent/sessions", "--backend", "none"], "/nonexistent/sessions does not exist"),
        (["eval", "knn", "--checkpoint", "/nonexistent/enc.pt"], "no checkpoint at /nonexistent/enc.pt"),  # before simulating
        (["eval", "knn", "--checkpoint", "root=/", "--n-views", "1"], "views 0,1,2,3 need --n-views above 3"),
        (["train", "pretrain", "--batch-size", "0"], "--batch-size"),
        (["train", "decoder", "--epochs", "0", "--end-to-end"], "--epochs"),
        (["relight", "s", "--pattern", "checkerboard", "--chunk", "0"], "--chunk"),
        (["patterns", "--projector", "100000x100000", "--out", "p"], "larger than any projector"),
        (["import", "f", "--object", "o", "--projector", "19x10x1"], "projector size must look like 1920x1080"),
        (["bench", "gpu", "--device", "nonsense"], "unknown device 'nonsense': use auto, cpu, cuda or cuda:N"),
        (["patterns", "--projector", "64x48", "--out", "/proc/version/x"], "/proc/version/x: Not a directory"),
        (["bench", "relight", "--radii", "-4,abc", "--backends", "none"], "--radii expects comma-separated integers"),
        (["bench", "relight", "--backends", "torch"], "--backends torch needs --checkpoint"),  # had measured nothing
        (["bench", "stability", "--cases", ","], "--cases ',' names nothing"),  # had run every case
        (["bench", "learn", "--repeats", "0"], "--repeats"),  # had averaged nothing into NaN
        (["bench", "learn", "--device", "tpu"], "unknown device 'tpu': use auto"),  # was torch's internal error
        (["capture", "--object", "leaf", "--hdr-exposures", "0.001,64"], "HDR exposures 0.001 and 64 are 64000x apart"),
        (["repro", "paper", "--preset", "tiny", "--budget", "0"], "--budget must be a number of seconds in (0, 2.592e+06], got 0"),
        (["repro", "paper", "--preset", "tiny", "--budget", "1e308"], "--budget must be a number of seconds in"),  # overflowed
        (["repro", "paper", "--preset", "tiny", "--timeout", "inf"], "--timeout must be a number of seconds in"),
        (["train", "decoder", "--end-to-end", "--device", "tpu"], "unknown device 'tpu'"),  # after the data was read
        (["bench", "daemon", "--frames", "0", "--out", "d.json"], "--frames"),  # had left its daemon running
        (["bench", "psp", "--out", "/proc/version/x.json", "--quick"], "/proc/version is a file"),  # after the work
        (["repro", "paper", "--preset", "tiny", "--timeout", "0"], "--timeout must be a number of seconds in (0, 86400]"),
        (["demo", "--out", "/proc/version"], "--out /proc/version is a file: give a folder"),  # every step had failed
        (["daemon", "keys", "--dir", "/proc/version"], "--dir /proc/version is a file"),  # was "[Errno 17] File exists"
        (["capture", "--object", "nosuchthing", "--views", "1"], "unknown object 'nosuchthing'; the catalogue has"),
        (["demo", "--preset", "bogus"], "unknown demo preset 'bogus'"),  # had started a daemon first
        (["eval", "knn", "--checkpoint", "psp="], "--checkpoint takes NAME=PATH"),  # had loaded ./last.pt
        (["eval", "knn", "--checkpoint", "psp=/", "--checkpoint", "psp=/tmp"], "the name 'psp' is given twice"),
        (["eval", "relight", "s", "--out", "ev/imp.json"], "--out ev/imp.json: sss eval relight writes a folder"),  # it
        # made a folder named imp.json
        (["bench", "relight-cache", "s", "--first", "checkerboard", "--new", "checkerboard"], "--new checkerboard is the --first"),
        (["demo", "--transport", "bogus"], "unknown transport model 'bogus'"),
        (["demo", "--training-rigs", "lab"], "unknown training rigs 'lab'; choose one of nominal, camera, randomised"),
        (["capture", "--object", "soap", "--views", "1", "--anisotropy", "0.5"], "give it with --transport radiative"),
        (["capture", "--object", "soap", "--transport", "radiative", "--anisotropy", "0.9"], "anisotropy must be a number in [0, 0.85]"),
        (["capture", "--object", "soap", "--views", "1", "--backdrop", "30"], "backdrop must be a number in [60, 1000]"),
        (["sim", "--object", "soap", "--out", "x", "--anisotropy", "0.5"], "give it with --transport radiative"),
        (["capture", "--object", "a" * 300], "(300 characters)"),  # the name is not echoed whole
    ],
)
def test_usage_errors_are_one_message_not_a_traceback(args: list[str], expected: str) -> None:
    res = _sss(*args)
    out = res.stdout + res.stderr
    assert res.returncode == 2, out
    assert "Traceback" not in out and "ModuleNotFoundError" not in out, out
    assert expected in out
    assert len(out.strip().splitlines()) <= 12, out
    assert "started a local one" not in out, out  # refused before a daemon is started for nothing
    assert "\u2501" not in out and not out.startswith("\n"), out  # ... and before any progress display starts


def test_a_runtime_folder_others_can_read_is_one_message(tmp_path) -> None:
    shared = tmp_path / "rt"
    shared.mkdir(mode=0o755)
    shared.chmod(0o755)
    env = {k: v for k, v in os.environ.items() if k != "SSS_DEBUG"} | {"SSS_RUNTIME_DIR": str(shared), "COLUMNS": "200"}
    res = run_sss(["daemon", "status"], timeout=120, env=env)
    out = res.stdout + res.stderr
    assert res.returncode == 2 and "Traceback" not in out and "internal error" not in out, out
    assert "must be owned by you with mode 0700" in out and f"chmod 700 {shared}" in out, out


def test_bare_group_prints_help_and_exits_cleanly() -> None:
    res = _sss("train")
    out = res.stdout + res.stderr
    assert "Traceback" not in out, out
    assert "pretrain" in out and "decoder" in out
    assert res.returncode in (0, 2)


def test_user_errors_keep_square_brackets() -> None:
    """Rich markup must not eat text such as ``pip install sssphase[depthai]`` from an error message."""
    res = _sss("relight", "no/such/session[depthai]", "--pattern", "checker.png")
    out = res.stdout + res.stderr
    assert res.returncode == 2, out
    assert "Traceback" not in out
    assert "no/such/session[depthai]" in out, out


def test_version_prints_the_package_version() -> None:
    from sssphase_core import __version__

    res = _sss("--version")
    assert res.returncode == 0 and res.stdout.strip() == f"sss (sssphase) {__version__}", res.stdout + res.stderr


def _all_commands(group, path=()):  # noqa: ANN001, ANN202 - click objects
    yield path
    for name, sub in getattr(group, "commands", {}).items():
        yield from _all_commands(sub, (*path, name))


def test_no_help_page_shows_a_type_for_a_flag() -> None:
    """Flags take no value: ``--help`` lists them without ``<bool>``, on every command."""
    import typer.main
    from typer.testing import CliRunner

    from sssphase_cli.main import app

    runner = CliRunner()
    paths = list(_all_commands(typer.main.get_command(app)))
    assert len(paths) > 20
    for path in paths:
        res = runner.invoke(app, [*path, "--help"], env={"COLUMNS": "200"})
        assert res.exit_code == 0, (path, res.output)
        assert "<bool>" not in res.output, (path, res.output)


def test_sigterm_says_interrupted_like_ctrl_c(tmp_path) -> None:
    """`kill` of a long command ends with the same "interrupted" line as Ctrl-C, not silence."""
    import signal
    import time

    env = {**os.environ, "COLUMNS": "200"}
    proc = subprocess.Popen([sys.executable, "-m", "sssphase_cli.main", "sim", "--object", "apple", "--views", "4",
                             "--preset", "paper", "--out", str(tmp_path)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    time.sleep(6)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, out + err
    assert "interrupted" in err and "Traceback" not in err, err


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["capture", "--object", "apple", "--timeout", "nan"], "--timeout must be a number of seconds in (0, 86400], got nan"),
        (["capture", "--object", "apple", "--seed", "99999999999999999999999"],
         "--seed must be 0 to 9223372036854775807 (2**63 - 1, what the sim rig takes), got 99999999999999999999999"),
        *((["capture", "--object", "apple", "--hdr-exposures", v],
           f"--hdr-exposures takes comma-separated numbers, e.g. 0.25,1,4,16; got {v!r}") for v in ("", ",", "1,,2")),
        (["capture", "--object", "apple", "--hdr-exposures", ",".join(["1"] * 1000)],
         "HDR exposures must be 2 to 8 distinct numbers in [0.001, 256], got 1000: 1, 1, 1, 1, 1, 1, 1, 1, 1, ..."),
        (["capture", "--object", "apple", "--reference", " .png"],
         "--reference ' .png': the file name ' ' cannot name a capture: use letters, digits, '_', '-', '.' "
         "(it is stored as ref/<name>)"),
        *((["capture", "--object", "apple", "--footprints", "--dot-spacing", v],
           f"dot spacing must be 1 to 256 projector px (the projector's side at most; the plan holds spacing^2 dot "
           f"frames), got {v}") for v in ("0", "1000000000000")),
        (["patterns", "--footprints", "--projector", "64x48", "--dot-spacing", "100", "--out", "never_written"],
         "dot spacing must be 1 to 48 projector px (the projector's side at most; the plan holds spacing^2 dot frames), got 100"),
    ],
)
def test_capture_options_out_of_range_are_one_line_before_a_daemon_starts(args: list[str], expected: str) -> None:
    res = _sss(*args)
    out = res.stdout + res.stderr
    assert res.returncode == 2 and "Traceback" not in out and "internal error" not in out, out
    assert out.strip().splitlines() == [f"error: {expected}"], out  # nothing else: no daemon was started


def test_an_eof_error_that_escapes_a_command_is_one_line_not_aborted(monkeypatch, capsys, tmp_path) -> None:
    """Click turns an EOFError (numpy's, reading an empty .npy) into a bare "Aborted"; `sss` names it."""
    import signal

    import sssphase_core.capture.pattern_files as pattern_files  # where `sss patterns` reads the projector size
    from sssphase_cli.main import main

    def cut_short(*args: object) -> None:
        raise EOFError("No data left in file")

    monkeypatch.setattr(pattern_files, "parse_projector_size", cut_short)
    monkeypatch.setattr(signal, "signal", lambda *args: None)  # leave pytest's SIGTERM handler alone
    monkeypatch.setattr(sys, "argv", ["sss", "patterns", "--out", str(tmp_path / "p")])
    with pytest.raises(SystemExit) as exc:
        main()
    err = capsys.readouterr().err
    assert exc.value.code == 2, err
    assert err.strip().splitlines() == ["error: an input file ended early (EOFError: No data left in file): an empty or "
                                        "truncated file?"], err


@pytest.mark.parametrize(("args", "expected"), [
    (["train", "decoder", "--encoder", "e", "--sessions", "s", "--pixels-per-view", "0"],
     "error: Invalid value for '--pixels-per-view': Input should be greater than or equal to 1 "
     "(see 'sss train decoder --help')"),
    (["train", "decoder", "--encoder", "e", "--sessions", "s", "--camera-augment", "1.5"],
     "error: Invalid value for '--camera-augment': Input should be less than or equal to 1 "
     "(see 'sss train decoder --help')"),
    (["relight"], "error: Missing argument 'session'. (see 'sss relight --help')"),
    (["no-such-command"], "error: No such command 'no-such-command'. (see 'sss --help')"),
])
def test_click_usage_errors_are_one_line_naming_where_help_is(args: list[str], expected: str) -> None:
    """Run as the installed ``sss`` script, so help is named as the user typed the command."""
    from pathlib import Path

    script = Path(sys.executable).parent / "sss"
    env = {k: v for k, v in os.environ.items() if k != "SSS_DEBUG"}
    res = subprocess.run([str(script), *args], capture_output=True, text=True, timeout=120, env=env)
    out = res.stdout + res.stderr
    assert res.returncode == 2, out
    assert out.strip().splitlines() == [expected], out


@pytest.mark.parametrize(("args", "expected"), [
    (["relight", "no_session", "--pattern", ""],
     "error: --pattern is empty: give an image file or a named pattern (checkerboard, stripes_x, ...)"),
    (["relight", "no_session", "--pattern", "checkerboard", "--backend", "bogus"],
     "error: unknown backend 'bogus'; available: analytic, blend, exact, measured, none, torch"),
    (["relight", "no_session", "--pattern", "checkerboard"],  # "backend: analytic" was said first
     "error: no_session does not exist"),
    (["relight", "no_session", "--pattern", "checkerboard", "--device", "tpu"],
     "error: unknown device 'tpu': use auto, cpu, cuda or cuda:N"),
    (["eval", "relight", "no_session", "--backend", "none", "--device", "tpu"],
     "error: unknown device 'tpu': use auto, cpu, cuda or cuda:N"),
    # an empty path was the current folder: relight and export wrote their images, cache and sources.json there
    *(([*cmd, flag, ""], f"error: {flag.removesuffix('=')} is empty: give a path (an empty one would be the current folder)")
      for cmd, flag in ((["relight", "no_session", "--pattern", "checkerboard"], "--out"),
                        (["export", "no_session"], "--out"), (["eval", "relight", "no_session"], "--checkpoint"),
                        (["daemon", "keys"], "--dir"), (["udev", "install"], "--rules-dir"))),  # (groups in groups)
    (["relight", "no_session", "--pattern", "checkerboard", "--out="],
     "error: --out is empty: give a path (an empty one would be the current folder)"),
])
def test_relight_options_are_checked_before_the_session_is_read(args: list[str], expected: str) -> None:
    """One line, before any progress bar is drawn (an empty one preceded the device error)."""
    res = _sss(*args)
    out = res.stdout + res.stderr
    assert res.returncode == 2, out
    assert out.strip().splitlines() == [expected], out


def test_a_warning_that_escapes_a_command_is_one_line_without_its_source(monkeypatch, capsys) -> None:
    """numpy's RuntimeWarnings (an overflow on extreme input) printed their file, line and source line."""
    import warnings

    import numpy as np

    from sssphase_cli import main as cli_main

    def noisy(standalone_mode: bool = False) -> int:
        np.float32(3e38) * np.float32(10)  # overflow: a RuntimeWarning
        warnings.warn("two\nlines", stacklevel=1)
        for _ in range(2):  # the same warning again (each backend of `sss relight` re-read a pattern): shown once
            warnings.warn("two lines", stacklevel=1)
        return 0

    monkeypatch.delenv("SSS_DEBUG", raising=False)
    monkeypatch.setattr(cli_main, "app", noisy)
    monkeypatch.setattr(warnings, "showwarning", warnings.showwarning)  # restored after the test
    monkeypatch.setattr(cli_main, "_WARNED", set())
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        with pytest.raises(SystemExit) as done:
            cli_main.main()
    assert done.value.code == 0
    err = capsys.readouterr().err
    assert err.splitlines() == ["warning: overflow encountered in scalar multiply (RuntimeWarning)", "warning: two lines"], err


RIG_HEAD = '[devices]\ncamera = "sim:camera0"\nprojector = "sim:projector0"\n'


@pytest.mark.parametrize(("text", "expected"), [
    (RIG_HEAD + "[processing]\npatch = -5\n", "[processing] patch must be a whole number in [9, 256], got -5"),
    (RIG_HEAD + "[processing]\nsaturation = nan\n", "[processing] saturation must be a number in [1e-06, 1e+12], got nan"),
    (RIG_HEAD + "[processing]\nmedian = 3\n", "[processing] median must be true or false, got 3"),
    (RIG_HEAD + "[processing]\nblack_level = 64\nwhite_scale = 0.000434\n",  # its inverse, as HARDWARE.md once said
     "white_scale is the DN above black that one linear camera unit gives (a white at 2,300 DN: 2300), got 0.000434"),
    ("options = 5\n" + RIG_HEAD, "options must be a [options] table, got int"),
    (b"\xff\xfe\x00binary", "is not UTF-8 text"),
])
def test_rig_files_are_checked_before_a_daemon_starts(tmp_path, text, expected):
    """A negative patch or a NaN saturation failed only after capturing (and wrote NaN into the manifest);
    a top-level `options = 5` or a binary file were internal errors."""
    rig = tmp_path / "rig.toml"
    rig.write_bytes(text if isinstance(text, bytes) else text.encode())
    res = _sss("capture", "--object", "apple", "--rig", str(rig), "--out", str(tmp_path / "s"))
    out = (res.stdout + res.stderr).strip()
    assert res.returncode == 2 and len(out.splitlines()) == 1 and expected in out, out
    assert not (tmp_path / "s").exists()


def test_calibrate_never_overwrites_a_file_that_is_not_a_rig_file(tmp_path):
    victim = tmp_path / "victim.py"
    victim.write_text('print("important")\n')
    res = _sss("calibrate", "projector", "--levels", "4", "--out", str(victim))
    out = (res.stdout + res.stderr).strip()
    assert res.returncode == 2 and out.splitlines() == [f"error: --out {victim} exists and is not a rig file: choose a "
                                                        "new file, or the rig file itself"], out
    assert victim.read_text() == 'print("important")\n'


@pytest.mark.parametrize(("args", "expected"), [
    (["--views", "1000000000000"], "--views: the sim rig's turntable takes at most"),
    (["--seed", "-1"], "--seed must be 0 to 9223372036854775807"),
])
def test_sim_options_are_ranged_like_capture(tmp_path, args, expected):
    res = _sss("sim", "--out", str(tmp_path / "o"), *args)
    out = (res.stdout + res.stderr).strip()
    assert res.returncode == 2 and len(out.splitlines()) == 1 and expected in out, out
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(("endpoint", "expected"), [
    ("tcp://127.0.0.1:99999", "the port must be a number from 1 to 65535"),  # ZeroMQ bound 99999 - 65536
    ("tcp://127.0.0.1:abc", "the port must be a number from 1 to 65535"),
    ("tcp://127.0.0.1", "give a port"),
    ("ipc:///nonexistent/dir/x.sock", "the folder /nonexistent/dir does not exist"),
])
def test_daemon_endpoints_that_cannot_be_bound_are_one_line_before_starting(endpoint: str, expected: str, tmp_path,
                                                                           monkeypatch) -> None:
    """They started a daemon that bound another port, or exited with "status 1 (see log)"."""
    monkeypatch.setenv("SSS_RUNTIME_DIR", str(tmp_path))  # no daemon of another test or session is asked
    res = _sss("daemon", "start", "--endpoint", endpoint)
    out = (res.stdout + res.stderr).strip()
    assert res.returncode == 2 and len(out.splitlines()) == 1 and expected in out, out


@pytest.mark.parametrize("runtime", ["relative_rt", "{tmp}/afile", "{tmp}/afile/rt"])
def test_a_runtime_folder_that_is_relative_or_a_file_is_one_message(runtime, tmp_path) -> None:
    """A relative SSS_RUNTIME_DIR named another folder from every working folder (`status` elsewhere said "no
    daemon running" and made the folder there); a file there was "[Errno 17] File exists"."""
    (tmp_path / "afile").write_text("x")
    env = {k: v for k, v in os.environ.items() if k != "SSS_DEBUG"} | {
        "SSS_RUNTIME_DIR": runtime.format(tmp=tmp_path), "COLUMNS": "200"}
    res = run_sss(["daemon", "status"], timeout=120, env=env, cwd=tmp_path)
    out = (res.stdout + res.stderr).strip()
    assert res.returncode == 2 and len(out.splitlines()) == 1, out
    assert ("must be an absolute path, got relative_rt" if runtime == "relative_rt" else
            f"but {tmp_path / 'afile'} is a file") in out, out
    assert not (tmp_path / "relative_rt").exists()


def test_an_error_naming_a_path_with_a_newline_stays_one_line(tmp_path) -> None:
    """The path was printed raw, so the error ran over two lines."""
    folder = tmp_path / "nl\nx"
    folder.mkdir()
    res = _sss("relight", str(folder), "--pattern", "checkerboard", "--out", str(tmp_path / "o"))
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [f"error: {tmp_path}/nl\\nx is not a session (no manifest.json)"], res.stderr


def test_a_folder_of_sessions_given_for_a_session_names_the_sessions_in_it(tmp_path) -> None:
    """`sss relight SESSIONS_ROOT` said only "is not a session (no manifest.json)"."""
    from sssphase_core.store.session import Session

    for name in ("soap", "apple"):
        Session.create(tmp_path / "sessions", name)
    res = _sss("relight", str(tmp_path / "sessions"), "--pattern", "checkerboard", "--out", str(tmp_path / "o"))
    assert res.returncode == 2 and res.stderr.strip().splitlines() == [
        f"error: {tmp_path}/sessions is not a session (no manifest.json); it holds the sessions apple, soap: give one "
        f"of them ({tmp_path}/sessions/apple)"], res.stderr


def test_the_rig_presets_read_whole_in_an_80_column_terminal() -> None:
    """`sss rigs` cut the camera's and projector's sizes to "256x1…" and "1920x…" at 80 columns."""
    res = run_sss(["rigs"], env={**os.environ, "COLUMNS": "80"})
    assert res.returncode == 0 and max(len(line) for line in res.stdout.splitlines()) <= 90, res.stdout
    rows = {line.split("│")[1].strip(): [c.strip() for c in line.split("│")[2:-1]] for line in res.stdout.splitlines()
            if line.startswith("│")}
    assert rows["camera"][:2] == ["256x192", "1920x1080"] and rows["projector"][:2] == ["256x192", "1920x1080"], rows


def test_progress_written_to_a_file_is_said_as_the_work_goes() -> None:
    """`sss demo > log` showed "[pretrain] running" for minutes, then the finished bars all at once: where no bar can
    be drawn, a line per tenth of a task (or every 30 s) is printed as it comes."""
    import io

    from rich.console import Console

    from sssphase_cli.progress import step_bar

    buf = io.StringIO()
    with step_bar(Console(file=buf, width=200)) as progress:  # (a file: no terminal)
        for done in range(101):
            progress("pretrain", done, 100, "loss 0.5")
        progress("decoder", 0, 7, "")
        progress("decoder", 7, 7, "")
        progress("decoder", 7, 7, "")
    lines = buf.getvalue().splitlines()
    assert lines == [f"pretrain: {n}/100 loss 0.5" for n in range(0, 101, 10)] + ["decoder: 0/7", "decoder: 7/7"], lines
