"""Tests for the torchface command-line interface."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from torchface.cli import FFMPEG_LOG_QUIET, build_parser, main
from torchface.synth.io import read_video
from torchface.synth.sequence import load_ground_truth

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _helpers import WriteOnlyStream, without_home  # noqa: E402


def test_render_demo_writes_a_sequence(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["render-demo", "--out", str(out), "--frames", "3", "--width", "64", "--height", "48"]) == 0
    text = capsys.readouterr().out
    assert "3/3 frames" in text and "pose_sweep.avi" in text
    assert read_video(out / "pose_sweep.avi").shape == (3, 3, 48, 64)
    assert load_ground_truth(out / "pose_sweep.gt.npz").num_frames == 3


def test_render_demo_writes_a_first_frame_landmarks_file_that_track_takes(tmp_path, capsys):
    """``render-demo``'s clip could not be tracked by ``torchface track`` without writing a landmarks file in Python:
    its ground truth files are no ``--landmarks`` file (``.gt.json`` and ``.gt.npz`` are refused). It writes
    ``<name>_first_frame.csv``, the ground truth's frame-0 landmarks exactly, and prints the command that tracks it;
    the ground truth's files given as ``--landmarks`` are refused naming that file."""
    import numpy as np

    from torchface.io import read_landmarks

    import shlex

    synth = tmp_path / "my synth"  # (the command printed is quoted for a shell)
    assert main(["render-demo", "--out", str(synth), "--frames", "3", "--width", "160", "--height", "120"]) == 0
    text = capsys.readouterr().out
    lm = synth / "pose_sweep_first_frame.csv"
    video = shlex.quote(str(synth / "pose_sweep.avi"))
    command = f"torchface track {video} --out results --landmarks {shlex.quote(str(lm))}"
    assert command in text, text
    truth = load_ground_truth(synth / "pose_sweep.gt.npz").landmarks_px[0].numpy()
    assert np.array_equal(read_landmarks(lm, 160, 120), truth)
    for given in ("pose_sweep.gt.json", "pose_sweep.gt.npz"):  # (refused naming the format alone: now the way)
        rc = main(["track", str(synth / "pose_sweep.avi"), "--out", str(tmp_path / "r"),
                   "--landmarks", str(synth / given)])  # fmt: skip
        err = capsys.readouterr().err
        assert rc == 2 and f"its first frame's landmarks are {lm} (torchface render-demo writes it)" in err, err
    argv = shlex.split(command)[1:]
    argv[argv.index("results")] = str(tmp_path / "results")
    assert main([*argv, "--quiet"]) == 0, capsys.readouterr().err
    assert (tmp_path / "results" / "pose_sweep.csv").is_file()


def test_render_demo_help_lists_the_scenarios(capsys):
    """``render-demo --help`` said "scenario name" without the names (only a wrong one was told them); it lists
    ``torchface.synth.scenarios.SCENARIOS``, which the parser, importing no torch, writes out itself."""
    from torchface.cli import RENDER_SCENARIOS
    from torchface.synth.scenarios import SCENARIOS

    assert RENDER_SCENARIOS == tuple(SCENARIOS)
    with pytest.raises(SystemExit):
        main(["render-demo", "--help"])
    assert f"scenario: {', '.join(SCENARIOS)} (default" in " ".join(capsys.readouterr().out.split())


def test_render_demo_rejects_unknown_scenario(tmp_path, capsys):
    assert main(["render-demo", "--out", str(tmp_path), "--scenario", "nope", "--frames", "2"]) == 2
    assert "unknown scenario" in capsys.readouterr().err


def test_render_demo_rejects_odd_sizes_and_a_file_as_out(tmp_path, capsys):
    """An odd size used to be written cropped to an even one by the video codec while the ground truth kept the
    size asked for; a file as --out used to end in a traceback. Both are one-line errors, nothing written."""
    for w, h in (("65", "48"), ("64", "47"), ("8", "8")):
        assert main(["render-demo", "--out", str(tmp_path / "odd"), "--frames", "2", "--width", w, "--height", h]) == 2
        assert "must be even numbers >= 16" in capsys.readouterr().err
    assert not (tmp_path / "odd").exists()
    (tmp_path / "afile").write_text("x")
    assert main(["render-demo", "--out", str(tmp_path / "afile"), "--frames", "2"]) == 2
    assert "is a file, not a folder" in capsys.readouterr().err


def test_render_demo_names_a_dangling_link_or_a_file_above_out(tmp_path, capsys):
    """An --out that is, or is under, a symbolic link to nothing said only "<out>: File exists"; one under a file
    "Not a directory". Now the message names the link (and its target) or the file; nothing is written."""
    (tmp_path / "afile").write_text("x")
    (tmp_path / "link").symlink_to(tmp_path / "gone")
    for out, message in (
        (tmp_path / "link", f"{tmp_path / 'link'} is a symbolic link to {tmp_path / 'gone'}, which does not exist"),
        (tmp_path / "link" / "sub", f"{tmp_path / 'link'} is a symbolic link to"),
        (tmp_path / "afile" / "sub", f"{tmp_path / 'afile'} is a file, not a folder"),
    ):
        assert main(["render-demo", "--out", str(out), "--frames", "2", "--width", "16", "--height", "16"]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err
    assert not (tmp_path / "gone").exists() and (tmp_path / "afile").read_text() == "x"


def test_video_sink_refuses_odd_sizes(tmp_path):
    from torchface.synth.io import VideoSink

    with pytest.raises(ValueError, match="even width and height"):
        VideoSink(tmp_path / "odd.avi", 65, 48)
    assert list(tmp_path.iterdir()) == []


def test_parser_requires_a_command():
    with pytest.raises(SystemExit):
        build_parser().parse_args([])
    assert build_parser().parse_args(["demo"]).out.name == "torchface-demo"


def test_version_prints_the_package_version(capsys):
    """``torchface --version`` (a script recording what made its results) was "error: the following arguments are
    required: command", status 2; it prints ``torchface <version>`` and exits with 0."""
    import torchface

    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0
    assert capsys.readouterr().out.strip() == f"torchface {torchface.__version__}"


def test_python_dash_m_torchface_runs_the_command(tmp_path):
    """``python -m torchface`` (a venv's Python without its bin/ on the PATH) was "No module named
    torchface.__main__; 'torchface' is a package and cannot be directly executed"; it is the ``torchface`` command,
    under its name: the version, and a bad input's one-line error with status 2."""
    import torchface

    root = str(Path(torchface.__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")]))}
    run = subprocess.run([sys.executable, "-m", "torchface", "--version"], capture_output=True, text=True, env=env,
                         cwd=tmp_path, timeout=120)  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == f"torchface {torchface.__version__}"
    missing = str(tmp_path / "nope.mp4")
    run = subprocess.run([sys.executable, "-m", "torchface", "track", missing, "--landmarks", missing,
                          "--out", str(tmp_path / "o")],
                         capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120)  # fmt: skip
    assert run.returncode == 2
    assert run.stderr.strip().splitlines() == [f"torchface: error: {missing}: no such file or folder"]


def test_track_threads_sets_torchs_threads_and_rejects_non_positive(monkeypatch, tmp_path, capsys):
    import torch

    import torchface.cli as cli

    seen = []
    monkeypatch.setattr(cli, "_run_track", lambda *a, **k: seen.append(torch.get_num_threads()) or 0)
    before = torch.get_num_threads()
    try:
        assert main(["track", "clip.mp4", "--out", str(tmp_path), "--threads", "1"]) == 0
        assert seen == [1]
    finally:
        torch.set_num_threads(before)
    seen.clear()
    try:
        assert main(["demo", "--out", str(tmp_path), "--threads", "1"]) == 0  # demo takes it too
        assert seen == [1]
    finally:
        torch.set_num_threads(before)
    for bad in ("0", "-2", "two"):
        with pytest.raises(SystemExit):
            main(["track", "clip.mp4", "--out", str(tmp_path), "--threads", bad])
        assert "--threads: must be an integer >= 1" in capsys.readouterr().err


def test_the_command_runs_without_docstrings(tmp_path):
    """Under ``python -OO`` (``PYTHONOPTIMIZE=2``, set in some container images) docstrings are None: the parser's
    description was ``__doc__.splitlines()[0]`` and every ``torchface`` command ended in an AttributeError."""
    root = Path(__file__).resolve().parent.parent
    code = "import sys; from torchface.cli import main; sys.exit(main(sys.argv[1:]))"
    args = ["render-demo", "--out", str(tmp_path), "--frames", "2", "--width", "32", "--height", "32"]
    out = subprocess.run([sys.executable, "-OO", "-c", code, *args], cwd=root, capture_output=True, text=True,
                         timeout=120)  # fmt: skip
    assert out.returncode == 0, out.stderr[-2000:]
    assert (tmp_path / "pose_sweep.avi").is_file()
    help_text = subprocess.run([sys.executable, "-OO", "-c", code, "--help"], cwd=root, capture_output=True,
                               text=True, timeout=120)  # fmt: skip
    assert help_text.returncode == 0 and "usage: torchface" in help_text.stdout, help_text.stderr[-2000:]


def test_help_texts_print_no_rest_markup():
    """``torchface --help`` printed the module docstring's first line as it is written for Sphinx: "The ``torchface``
    command: ``track`` videos, run the ``demo`` ..."."""
    import argparse

    parser = build_parser()
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for text in [parser.format_help(), *(p.format_help() for p in subs.choices.values())]:
        assert "``" not in text and ":func:" not in text and ":mod:" not in text
    assert parser.description.startswith("The torchface command: track videos, run the demo")


def test_summary_lists_the_meshes_folder_when_meshes_were_written(tmp_path):
    """The summary's list of what each video got left out ``<stem>_meshes/`` of a ``--meshes`` run."""
    import io

    from torchface.cli import _print_summary
    from torchface.job import VideoSummary, output_paths

    p = output_paths(tmp_path, "clip")
    files = (p["csv"], p["json"], p["overlay"], p["plot"], p["normalised"])
    for outputs, listed in ((files, False), (files + (p["meshes"],), True)):
        out = io.StringIO()
        _print_summary([VideoSummary("clip", tmp_path / "clip.mp4", outputs, 3, 0, 0.9, 10.0)], out)
        last = out.getvalue().splitlines()[-1]
        assert last.startswith(f"outputs in {tmp_path}/ (per video: .csv, .json, _overlay.mp4, _plot.png")
        assert ("_meshes/" in last) is listed


def test_a_ctrl_c_while_torch_is_imported_is_one_line_and_130(tmp_path):
    """The console script imports ``torchface.cli``, whose package imported torch (seconds) before ``main`` could
    catch anything: a Ctrl-C then printed a long traceback. The package now imports its API on first use, ``main``
    parses first (``--help`` without torch) and a Ctrl-C during torch's import is one line and status 130. The
    Ctrl-C is sent by the process itself when the import of torch begins (a finder on ``sys.meta_path``); the child
    restores Python's own SIGINT handler, which it does not install where it starts with SIGINT ignored (a job
    started with ``&`` from a script)."""
    root = Path(__file__).resolve().parent.parent
    code = (
        "import importlib.abc, os, signal, sys\n"
        "signal.signal(signal.SIGINT, signal.default_int_handler)\n"  # a background shell's SIGINT is ignored
        "class CtrlC(importlib.abc.MetaPathFinder):\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name == 'torch':\n"
        "            os.kill(os.getpid(), signal.SIGINT)\n"
        "        return None\n"
        "sys.meta_path.insert(0, CtrlC())\n"
        "from torchface.cli import main\n"
        "sys.exit(main(sys.argv[1:]))\n"
    )
    for args in (["demo", "--out", str(tmp_path / "demo")], ["track", "v.mp4", "--out", str(tmp_path / "t"),
                                                             "--landmarks", "lm.csv", "--threads", "1"]):  # fmt: skip
        out = subprocess.run([sys.executable, "-c", code, *args], cwd=root, capture_output=True, text=True,
                             timeout=120)  # fmt: skip
        assert out.returncode == 130, (out.returncode, out.stderr[-2000:])
        assert out.stderr.strip() == "torchface: interrupted before it started; run it again", out.stderr[-2000:]
    help_text = subprocess.run([sys.executable, "-c", code, "track", "--help"], cwd=root, capture_output=True,
                               text=True, timeout=120)  # fmt: skip
    assert help_text.returncode == 0 and "usage: torchface track" in help_text.stdout, help_text.stderr[-2000:]


@pytest.mark.skipif(os.name != "posix", reason="a process ends by a signal on POSIX systems only")
def test_a_ctrl_c_stops_a_shell_loop_over_videos(tmp_path):
    """``for v in *.mp4; do torchface track "$v" ...; done``: a Ctrl-C (SIGINT to the shell and the command, its
    foreground process group) stopped the video being tracked, and the loop went on to the next one: the command
    exited with 130 itself, which bash takes for a program that handled the Ctrl-C ("wait and cooperative exit"),
    where a program that dies of SIGINT (as Python does after an uncaught Ctrl-C) stops the loop. The command
    (``main()``, its arguments ``sys.argv``') now ends by SIGINT after its lines; ``main(argv)`` from Python still
    returns 130 (test above). The Ctrl-C is sent to the process group by the command as the import of torch
    begins."""
    bash = shutil.which("bash")
    if bash is None:
        pytest.skip("no bash")
    root = Path(__file__).resolve().parent.parent
    code = (
        "import importlib.abc, os, signal, sys\n"
        "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
        "class CtrlC(importlib.abc.MetaPathFinder):\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name == 'torch':\n"
        "            os.killpg(os.getpgrp(), signal.SIGINT)\n"  # (the terminal's Ctrl-C: the shell's too)
        "        return None\n"
        "sys.meta_path.insert(0, CtrlC())\n"
        "from torchface.cli import main\n"
        "sys.argv[0] = 'torchface'\n"
        "sys.exit(main())\n"
    )
    loop = 'for i in 1 2; do "$PY" -c "$CODE" demo --out "$OUT/$i"; echo "after $i: $?"; done; echo "loop ended"'
    env = {**os.environ, "PY": sys.executable, "CODE": code, "OUT": str(tmp_path)}
    run = subprocess.run([bash, "-c", loop], cwd=root, env=env, capture_output=True, text=True, timeout=240,
                         start_new_session=True)  # fmt: skip
    assert run.stdout == "" and run.returncode == -signal.SIGINT, (run.returncode, run.stdout, run.stderr[-2000:])
    assert run.stderr.strip() == "torchface: interrupted before it started; run it again", run.stderr[-2000:]
    alone = subprocess.run([sys.executable, "-c", code, "demo", "--out", str(tmp_path / "alone")], cwd=root,
                           capture_output=True, text=True, timeout=120, start_new_session=True)  # fmt: skip
    assert alone.returncode == -signal.SIGINT, (alone.returncode, alone.stderr[-2000:])
    # the atexit functions run before the end by SIGINT, as Python runs them before its own (the signal's default
    # action ran none: a multiprocessing finalizer, a private native-kernel folder's removal were skipped)
    mark = tmp_path / "atexit ran"
    exiting = code.replace("sys.exit(main())\n", f"import atexit; atexit.register(open, {str(mark)!r}, 'w')\n"
                                                  "sys.exit(main())\n")  # fmt: skip
    assert exiting != code
    ended = subprocess.run([sys.executable, "-c", exiting, "demo", "--out", str(tmp_path / "exit")], cwd=root,
                           capture_output=True, text=True, timeout=120, start_new_session=True)  # fmt: skip
    assert ended.returncode == -signal.SIGINT and mark.is_file(), (ended.returncode, ended.stderr[-2000:])


def test_an_empty_path_is_a_usage_error_not_the_current_folder(tmp_path, capsys, monkeypatch):
    """``Path("")`` is ``.``: ``torchface track "$VIDEO" --out "$OUT"`` with a variable unset tracked the current
    folder's images as a video (its own outputs among them) and wrote its outputs there. An empty video, ``--out``
    or ``--landmarks`` (also a video after ``--landmarks``) is now a one-line usage error, before anything is read."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "a.npy").write_bytes(b"")
    for argv in (["track", "", "--out", "o"], ["track", "a.npy", "--out", ""], ["render-demo", "--out", ""],
                 ["track", "a.npy", "--landmarks", "", "--out", "o"],
                 ["track", "a.npy", "--landmarks", "l.csv", "", "--out", "o"]):  # fmt: skip
        with pytest.raises(SystemExit) as info:
            main(argv)
        err = capsys.readouterr().err
        assert info.value.code == 2 and "an empty path (an unset shell variable?)" in err, (argv, err)
        assert err.endswith("give a file or folder\n") and "Traceback" not in err  # (argparse: usage, one error line)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npy"]  # nothing written


def test_a_path_starting_with_tilde_is_a_usage_error_not_a_folder_named_tilde(tmp_path, capsys, monkeypatch):
    """The shell leaves ``~`` as it is after ``=`` and in quotes: ``--out=~/res`` wrote the outputs to a folder ``~``
    in the working folder, without a word. Now a one-line usage error saying why (any path option, the inputs too),
    nothing made."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "a.npy").write_bytes(b"")
    for argv in (["track", "a.npy", "--out=~/res", "--landmarks", "l.csv"], ["render-demo", "--out", "~/synth"],
                 ["track", "~/a.npy", "--out", "o", "--landmarks", "l.csv"]):  # fmt: skip
        with pytest.raises(SystemExit) as info:
            main(argv)
        err = capsys.readouterr().err
        assert info.value.code == 2 and "Traceback" not in err, (argv, err)
        assert err.splitlines()[-1].endswith("starts with '~', which the shell did not expand (quoted, or after '=' "
                                             "as in --out=~/...): give the path after a space, unquoted, or with $HOME")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npy"]  # nothing written
    # with HOME unset and the user not in the password database, nothing expands '~' (a shell neither): it was taken,
    # os.path.expanduser leaving it as it was, and the outputs went to a folder '~'
    with monkeypatch.context() as m:
        without_home(m)
        with pytest.raises(SystemExit) as info:
            main(["track", "a.npy", "--out", "~/res", "--landmarks", "l.csv"])
    err = capsys.readouterr().err
    assert info.value.code == 2 and err.splitlines()[-1].endswith(
        "'~/res' starts with '~', which nothing expanded (HOME is not set and the password database has no entry for "
        "this user): give the home folder's path"), err  # fmt: skip
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npy"]
    # a name that no user's home expands ('~draft.npy', as editors name their copies) is a name as any other
    with pytest.raises(SystemExit) as info:
        main(["track", "~torchface-no-such-user.npy", "--out", "~torchface-no-such-user-out", "--landmarks", "l.csv",
              "--no-such-option"])  # fmt: skip
    assert info.value.code == 2 and "unrecognized arguments: --no-such-option" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:  # "." (a path of no parts) is the working folder, as before
        main(["track", "a.npy", "--out", ".", "--landmarks", "l.csv", "--no-such-option"])
    assert info.value.code == 2 and "unrecognized arguments: --no-such-option" in capsys.readouterr().err


@pytest.mark.skipif(sys.platform != "linux", reason="a file name that is not UTF-8 needs a Linux file system")
def test_render_demo_and_video_sink_refuse_a_name_that_is_not_utf8_not_a_crash(tmp_path):
    """``render-demo --out`` / ``VideoSink`` with a name that is not valid UTF-8 (Latin-1 bytes) crashed the process in
    OpenCV's writer (a segmentation fault), ``render-demo`` after making the folder. Now a one-line error, nothing
    made. In child processes, so that a crash fails this test, not the session."""
    import os

    bad = os.fsdecode(b"bad\xff")
    runs = {
        "render-demo": "from torchface.cli import main; "
        f"sys.exit(main(['render-demo', '--out', {bad!r}, '--frames', '2', '--width', '32', '--height', '32']))",
        "VideoSink": f"import os, torch; from torchface.synth.io import write_video; os.mkdir({'sink' + bad!r}); "
        f"write_video(os.path.join({'sink' + bad!r}, 'v.avi'), torch.zeros(2, 3, 16, 16))",
    }
    for what, code in runs.items():
        done = subprocess.run([sys.executable, "-c", "import sys; " + code], cwd=tmp_path, capture_output=True,
                              text=True, errors="replace", timeout=120)  # fmt: skip
        err = done.stderr.strip().splitlines()
        assert done.returncode in (1, 2) and err and "the name is not valid UTF-8" in err[-1], (what, done)
    assert not (tmp_path / bad).exists() and os.listdir(tmp_path / f"sink{bad}") == []


def test_a_landmarks_file_among_the_videos_is_named_as_such(tmp_path, capsys, monkeypatch):
    """``clips/*.mp4 --landmarks lm/*.csv`` (a glob after ``--landmarks``, which takes one file) gave ``--landmarks``
    the first file and took the others as videos: the error was "give one landmarks file per video: 3 videos, 1
    files" for 2 videos and 2 files. A landmarks file among the inputs is now a usage error naming it, saying how
    to give one file per video (or, without ``--landmarks``, to give it with ``--landmarks``); nothing is read."""
    monkeypatch.chdir(tmp_path)
    for name in ("a.mp4", "b.mp4", "a.csv", "b.csv"):
        (tmp_path / name).write_bytes(b"")
    for argv, said in ((["a.mp4", "b.mp4", "--landmarks", "a.csv", "b.csv"], "--landmarks takes one file"),
                       (["a.mp4", "b.csv"], "give it with --landmarks FILE")):  # fmt: skip
        with pytest.raises(SystemExit) as info:
            main(["track", *argv, "--out", "o"])
        err = capsys.readouterr().err
        assert info.value.code == 2 and "argument videos: b.csv is a landmarks file, not a video" in err, (argv, err)
        assert said in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()
    (tmp_path / "frames.json").mkdir()  # (an image folder of any name is an input)
    assert main(["track", "frames.json", "--out", "o"]) == 2  # (refused for want of landmarks, not as a landmarks file)
    err = capsys.readouterr().err
    assert "no initialisation: give --landmarks FILE" in err and "is a landmarks file" not in err


def test_the_summary_is_written_in_one_piece():
    """docs/cli.md: with ``| head -1`` the summary, "written at the end in one piece", reaches the pipe before its
    reader goes (status 0). It was written a line at a time: with Python's output unbuffered (``PYTHONUNBUFFERED=1``,
    as many containers and CI set it) ``torchface track ... | head -1`` exited with 141 after the first lines."""
    from torchface.cli import _print_summary
    from torchface.job import VideoSummary

    done = [VideoSummary(n, Path(f"{n}.mp4"), (Path(f"o/{n}.csv"),), 30, 1, 0.9, 12.0, False, 40) for n in "abc"]
    out = WriteOnlyStream()
    _print_summary(done, out, ("d",), ("stopped at a frame that could not be read",))  # type: ignore[arg-type]
    assert len(out.parts) == 1, out.parts
    lines = out.parts[0].splitlines()
    assert lines[:3] == ["", "summary", "  a: 30 frames, 12.0 fps, mean confidence 0.90, 1 lost frame"]
    assert lines[3] == "    warning: a.mp4 declares 40 frames, 30 could be decoded (truncated or damaged?)"
    assert lines[-2] == ("  d: stopped at a frame that could not be read, not completed (its rows so far are kept in "
                         "d.csv.partial)")
    assert lines[-1].startswith("outputs in o/ (per video: .csv") and out.parts[0].endswith("\n")
    # one of a thing is said in the singular ("1 frames" was printed), none and many in the plural
    one = [VideoSummary("e", Path("e.mp4"), (Path("o/e.csv"),), 1, 0, 0.9, 12.0, False, 1),
           VideoSummary("f", Path("f.mp4"), (Path("o/f.csv"),), 1, 1, 0.9, 12.0, skipped=True),
           VideoSummary("g", Path("g.mp4"), (Path("o/g.csv.partial"),), 1, 0, 0.9, 0.0, stopped="a bad frame")]
    out = WriteOnlyStream()
    _print_summary(one, out)  # type: ignore[arg-type]
    lines = out.parts[0].splitlines()
    assert lines[2:5] == ["  e: 1 frame, 12.0 fps, mean confidence 0.90, 0 lost frames",
                          "    warning: e.mp4 declares 1 frame, 1 could be decoded (truncated or damaged?)",
                          "  f: already complete (1 frame), skipped"], lines  # fmt: skip
    # (f's one row is lost: a video of no tracked frame, said under its line; the run exits with 3)
    assert lines[5] == ("    warning: no tracked frame, every row unusable (success 0): the face was lost at every "
                        "frame; its outputs are written")  # fmt: skip
    assert lines[6] == "  g: stopped partway, not completed (its 1 row so far is kept in g.csv.partial): a bad frame"
    # no_tracked_frame: every row lost of a complete video; not a stopped one, nor one of no frames (refused earlier)
    assert [s.no_tracked_frame for s in one] == [False, True, False]
    assert not VideoSummary("h", Path("h.mp4"), (Path("o/h.csv"),), 0, 0, 0.0, 0.0).no_tracked_frame


def test_a_damaged_videos_error_is_one_line_without_ffmpegs_log(tmp_path):
    """docs/cli.md: bad input is a one-line ``torchface: error: ...``. An empty ``.mp4`` also printed FFmpeg's own
    log line above it (``[mov,mp4,m4a,3gp,3g2,mj2 @ 0x...] moov atom not found``; a damaged frame's, ``[mjpeg @
    0x...] overread 8``, went between the progress bars). The command leaves FFmpeg's log out unless
    ``OPENCV_FFMPEG_LOGLEVEL`` asks for it. (A process of its own: OpenCV reads the variable once, when its FFmpeg
    backend is first used.)"""
    root = Path(__file__).resolve().parent.parent
    (tmp_path / "empty.mp4").write_bytes(b"")
    (tmp_path / "lm.csv").write_text("".join(f"{10 + k},{20 + k % 7}\n" for k in range(68)))
    argv = ["track", "empty.mp4", "--landmarks", "lm.csv", "--out", "o", "--quiet"]
    code = "import sys\nfrom torchface.cli import main\nsys.exit(main(sys.argv[1:]))\n"
    env = {k: v for k, v in os.environ.items() if k != "OPENCV_FFMPEG_LOGLEVEL"}
    env["PYTHONPATH"] = os.pathsep.join([str(root), env.get("PYTHONPATH", "")])
    out = subprocess.run([sys.executable, "-c", code, *argv], cwd=tmp_path, capture_output=True, text=True, env=env,
                         timeout=120)  # fmt: skip
    assert out.returncode == 2, (out.returncode, out.stderr[-2000:])
    assert out.stderr.splitlines() == [f"torchface: error: {Path('empty.mp4')}: not a video OpenCV can open "
                                       "(unreadable, corrupt or an unknown format)"], out.stderr[-2000:]  # fmt: skip
    asked = subprocess.run([sys.executable, "-c", code, *argv], cwd=tmp_path, capture_output=True, text=True,
                           env={**env, "OPENCV_FFMPEG_LOGLEVEL": "16"}, timeout=120)  # fmt: skip
    said = asked.stdout + asked.stderr  # (OpenCV's logger writes FFmpeg's lines to stdout where the level is set)
    assert asked.returncode == 2 and len(said) > len(out.stdout + out.stderr), said[-2000:]  # (FFmpeg's, asked for)


def test_main_leaves_the_ffmpeg_log_variable_as_it_found_it(tmp_path, monkeypatch):
    """``main`` sets ``OPENCV_FFMPEG_LOGLEVEL`` (FFmpeg's log left out) for its run only: called in a notebook or a
    test, it left it set for the rest of the process and every process started from it; one the caller set is
    kept."""
    argv = ["track", str(tmp_path / "missing.mp4"), "--landmarks", str(tmp_path / "lm.csv"), "--out",
            str(tmp_path / "o"), "--quiet"]  # fmt: skip
    seen = []
    monkeypatch.setattr("torchface.cli._dispatch", lambda args: seen.append(os.environ.get("OPENCV_FFMPEG_LOGLEVEL"))
                        or 0)  # fmt: skip
    monkeypatch.delenv("OPENCV_FFMPEG_LOGLEVEL", raising=False)
    assert main(argv) == 0 and seen == [FFMPEG_LOG_QUIET]  # (set while it runs)
    assert "OPENCV_FFMPEG_LOGLEVEL" not in os.environ
    monkeypatch.setattr("torchface.cli._dispatch", lambda args: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        main(argv)
    assert "OPENCV_FFMPEG_LOGLEVEL" not in os.environ
    monkeypatch.setenv("OPENCV_FFMPEG_LOGLEVEL", "16")
    monkeypatch.setattr("torchface.cli._dispatch", lambda args: seen.append(os.environ.get("OPENCV_FFMPEG_LOGLEVEL"))
                        or 0)  # fmt: skip
    assert main(argv) == 0 and seen[-1] == "16" and os.environ["OPENCV_FFMPEG_LOGLEVEL"] == "16"
