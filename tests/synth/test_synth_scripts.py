"""Smoke tests of scripts/make_sequence.py and scripts/overlay_landmarks.py on a tiny sequence."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/_helpers.py
from _helpers import SCRIPTS, WriteOnlyStream  # noqa: E402
from _helpers import load_script as _load  # noqa: E402


def test_make_sequence_then_overlay(tmp_path, capsys, monkeypatch):
    make = _load("make_sequence")
    out = tmp_path / "seq"
    args = ["--scenario", "expressions", "--width", "64", "--height", "48", "--frames", "3", "--batch", "2"]
    stream = WriteOnlyStream()  # (sys.stdout.isatty() raised AttributeError: torchface track's rule now)
    with monkeypatch.context() as m:
        m.setattr(sys, "stdout", stream)
        assert make.main([*args, "--out", str(out)]) == 0
    text = "".join(stream.parts)
    assert "3/3 frames" in text and "expressions.avi" in text
    # not a terminal: whole progress lines (the first and the last), not \r redraws run together in a log
    assert "\r" not in text and [line.split(" (")[0] for line in text.splitlines()[:2]] == [
        "expressions: 2/3 frames", "expressions: 3/3 frames"]
    overlay = _load("overlay_landmarks")
    assert overlay.main([str(out / "expressions.avi"), "--frames", "0", "2", "--out", str(tmp_path / "ov")]) == 0
    text = capsys.readouterr().out
    assert "max |reprojected - landmarks_px| = 0.00e+00" in text
    img = cv2.imread(str(tmp_path / "ov" / "expressions_0002.png"))
    assert img is not None and img.shape[1] == 640  # upscaled to about 640 px wide


def test_overlay_landmarks_keeps_only_the_picked_frames(tmp_path, capsys):
    """The script holds the frames it draws, not the whole video: it read every frame as float32 (a 3000-frame
    640x480 long run: about 25 GB at its peak; 240 frames: 2 GB). Measured with tracemalloc (numpy's buffers)."""
    import tracemalloc

    from torchface.synth.scenarios import make_scenario
    from torchface.synth.sequence import write_sequence

    files = write_sequence(make_scenario("expressions", 40, 320, 240), tmp_path / "seq")  # 9.2 MB of uint8 frames
    overlay = _load("overlay_landmarks")
    tracemalloc.start()
    try:
        args = [str(files.video), "--frames", "0", "39", "--scale", "1", "--out", str(tmp_path / "ov")]
        assert overlay.main(args) == 0
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 4e6, peak  # (18.6 MB before)
    for f in (0, 39):  # both drawn, at the video's size
        img = cv2.imread(str(tmp_path / "ov" / f"expressions_{f:04d}.png"))
        assert img is not None and img.shape == (240, 320, 3), f
    assert "over 40 frames" in capsys.readouterr().out


def test_make_sequence_writes_a_long_scenario(tmp_path, capsys):
    """The long runs are reachable by name (their timeline needs at least 100 frames)."""
    make = _load("make_sequence")
    out = tmp_path / "long"
    args = ["--scenario", "long_run", "--width", "64", "--height", "48", "--frames", "100", "--out", str(out)]
    assert make.main(args) == 0
    assert "100/100 frames" in capsys.readouterr().out
    assert (out / "long_run.avi").stat().st_size > 0 and (out / "long_run.gt.npz").exists()


def test_script_arguments_that_would_fail_late_are_one_line_errors(tmp_path, capsys):
    """Mistakes found before any work, as argparse's one-line errors (exit 2): they used to run 3000 frames
    (--long-frames 0), crash after the tracking (a --json folder, a missing MediaPipe interpreter, odd sizes) or
    show a traceback (an empty GRID folder)."""
    import pytest

    evaluate = _load("evaluate")
    (tmp_path / "jdir").mkdir()
    base = ["--scenarios", "pose_sweep", "--frames", "4", "--size", "64x48", "--ablations", "none", "--threads", "1",
            "--cache", str(tmp_path / "c"), "--no-auroc"]  # fmt: skip
    cases = [
        (["--long-frames", "0"], "--long-frames must be >= 100"),
        (["--json", str(tmp_path / "jdir")], "not a file path"),
        (["--mediapipe-python", str(tmp_path / "nope")], "no such executable"),
        (["--threads", "0"], "--threads: must be an integer >= 1, got '0'"),  # (_argtypes.add_threads_option)
        (["--plausible-turn-deg", "-1", "0"], "--plausible-turn-deg must be two finite values >= 0"),
        (["--device", "bogus"], "--device bogus: "),  # (tracebacks from load_candide3, as was a CUDA device on a
        (["--device", "meta"], "--device meta: the meta device holds no data"),  # torch without CUDA)
    ]
    for extra, message in cases:
        with pytest.raises(SystemExit) as info:
            evaluate.main(base + extra)
        assert info.value.code == 2 and message in capsys.readouterr().err, extra
    with pytest.raises(SystemExit):
        evaluate.main([*base[:4], "--size", "63x47"])
    assert "even" in capsys.readouterr().err
    grid = _load("track_grid")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SystemExit) as info:
        grid.main(["--grid", str(tmp_path / "empty"), "--out", str(tmp_path / "g")])
    assert info.value.code == 2 and "no .mpg clips" in capsys.readouterr().err
    peers = _load("peers")
    import numpy as np

    assert peers.run_mediapipe(np.zeros((1, 8, 8, 3), np.uint8), str(tmp_path / "nope")) is None


def test_evaluate_takes_an_odd_size_where_no_video_is_written(tmp_path, capsys):
    """An odd ``--size`` was refused even with ``--cache none``, where the standard scenarios render and track in
    memory; only a video needs even sides: the cache's, and the long scenarios' (streamed even with --cache none)."""
    import pytest

    evaluate = _load("evaluate")
    run = ["--scenarios", "pose_sweep", "--frames", "2", "--size", "63x47", "--ablations", "none", "--threads", "1",
           "--no-auroc", "--progress-every", "0"]  # fmt: skip
    assert evaluate.main([*run, "--cache", "none"]) == 0
    assert "pose_sweep (63x47, 2 frames" in capsys.readouterr().out
    long_too = ["--cache", "none", "--scenarios", "pose_sweep,long_run"]
    for extra, message in ((["--cache", str(tmp_path / "c")], "--cache writes one"),
                           (long_too, "the long scenarios (long_run)")):
        with pytest.raises(SystemExit) as info:
            evaluate.main([*run, *extra])
        err = capsys.readouterr().err
        assert info.value.code == 2 and "a video needs an even width and height" in err and message in err, err
    assert not (tmp_path / "c").exists()
    auroc = _load("confidence_auroc")  # the same --size and the same check (its cache is a video too)
    with pytest.raises(SystemExit) as info:
        auroc.main(["--scenarios", "pose_sweep", "--size", "63x47", "--cache", str(tmp_path / "c")])
    assert info.value.code == 2 and "--cache writes one" in capsys.readouterr().err
    assert not (tmp_path / "c").exists()


def test_benchmark_scripts_refuse_bad_counts_in_one_line(capsys):
    """A count of 0, a negative one or a bad worker list gave a traceback after the setup (statistics.median of no
    runs, torch.set_num_threads(0), a video too small to read); now argparse's one-line error, exit 2."""
    import pytest

    cases = {
        "benchmark_raster": (["--runs", "0"], ["--warmup", "-1"], ["--batches", "1", "0"], ["--threads", "0"],
                             ["--runs", "2.5"]),
        "benchmark_render": (["--repeats", "0"], ["--width", "0"], ["--threads", "-1"]),
        "benchmark_dataloader": (["--videos", "0"], ["--frames", "-2"], ["--width", "321"], ["--height", "16"],
                                 ["--face-size", "8"], ["--batch-size", "0"], ["--workers", "0,x"],
                                 ["--workers", "-1"], ["--repeats", "0"]),
        "benchmark_device": (["--steps", "0"], ["--threads", "0"], ["--width", "321"], ["--frames", "3"]),
    }  # fmt: skip
    for name, argvs in cases.items():
        script = _load(name)
        for argv in argvs:
            with pytest.raises(SystemExit) as info:
                script.main(argv)
            err = capsys.readouterr().err
            assert info.value.code == 2 and f"argument {argv[0]}: must be" in err, (name, argv, err)
            assert "Traceback" not in err and ": error: argument " in err.strip().splitlines()[-1], err


def test_benchmark_device_on_the_cpu(tmp_path, capsys):
    """scripts/benchmark_device.py with ``--device cpu`` (the GPU rows' code, run where there is no GPU): a row per
    batch, the ratio where both were run, on-track errors, and its JSON."""
    import json

    script = _load("benchmark_device")
    out = tmp_path / "bench.json"
    argv = ["--device", "cpu", "--batches", "1,3", "--cpu-batches", "1", "--steps", "2", "--width", "160",
            "--height", "120", "--frames", "12", "--threads", "1", "--cache", str(tmp_path), "--json", str(out)]
    assert script.main(argv) == 0
    table = capsys.readouterr().out
    assert "device_batch_3" in table and "cpu_batch_1" in table
    figures = json.loads(out.read_text())
    assert sorted(figures) == ["cpu_batch_1", "device_batch_1", "device_batch_3"]
    assert "ratio_to_cpu" in figures["device_batch_1"] and "ratio_to_cpu" not in figures["device_batch_3"]
    for row in figures.values():
        assert row["success"] == 1.0 and row["mean_error_deg"] < 3.0 and row["fps"] > 0
    for bad in (["--batches", "1,x"], ["--cpu-batches", "0"], ["--device", "gpu0"]):
        with pytest.raises(SystemExit) as info:
            script.main(bad)
        assert info.value.code == 2 and "Traceback" not in capsys.readouterr().err


def test_benchmark_reads_its_batch_lists_as_its_check_does():
    """``--batches 1,8,`` (a trailing comma) passed benchmark.py's argument check, which skips empty items, and then
    failed with int('') after the single-stream runs, which did not: both read the lists through one function."""
    import pytest

    bench = _load("benchmark")
    assert bench.batch_list("1,8,") == [1, 8] and bench.batch_list(" 32 , ,128") == [32, 128]
    assert bench.batch_list("") == []
    with pytest.raises(ValueError):
        bench.batch_list("1,x")
    source = (SCRIPTS / "benchmark.py").read_text()
    assert source.count('.split(",")') == 1  # the lists are parsed in batch_list only


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="Linux's /proc (VmHWM) only")
def test_benchmark_memory_is_the_configurations_own_peak():
    """benchmark.py's configurations run in processes it starts; their peak was ``ru_maxrss``, which Linux keeps
    across ``exec``: each read the benchmark's own peak where that was higher (rendering the frames: 1480 MB in every
    row, 0.0 MB per stream). :func:`peak_rss_mb` reads the process image's own peak: a child of a parent that
    touched 300 MB reads it under 150 MB where ``ru_maxrss`` reads the parent's 300."""
    import inspect
    import subprocess

    bench = _load("benchmark")
    child = ("import resource\n" + inspect.getsource(bench.peak_rss_mb)
             + "\nprint(peak_rss_mb(), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)")  # fmt: skip
    parent = ("import subprocess, sys\nheld = bytearray(300 * 2**20)\nheld[::4096] = b'x' * len(held[::4096])\n"
              f"print(subprocess.run([sys.executable, '-c', {child!r}], check=True, capture_output=True, "
              "text=True).stdout)")  # fmt: skip
    out = subprocess.run([sys.executable, "-c", parent], check=True, capture_output=True, text=True).stdout
    own, inherited = map(float, out.split())
    assert inherited >= 300 and own < 150


def test_every_script_answers_help_without_docstrings():
    """``python -OO`` (``PYTHONOPTIMIZE=2``, set in some container images) strips docstrings: the scripts built
    their description from ``__doc__.splitlines()`` and failed with an AttributeError before printing anything."""
    import subprocess

    code = (
        "import runpy, sys\n"
        "for path in sys.argv[1:]:\n"
        "    sys.argv = [path, '--help']\n"
        "    try:\n"
        "        runpy.run_path(path, run_name='__main__')\n"
        "    except SystemExit as exc:\n"
        "        assert exc.code in (0, None), (path, exc.code)\n"
        "    else:\n"
        "        raise AssertionError(path + ': --help did not exit')\n"
    )
    scripts = sorted(str(p) for p in SCRIPTS.glob("*.py") if "ArgumentParser(" in p.read_text())  # the commands
    out = subprocess.run([sys.executable, "-OO", "-c", code, *scripts], capture_output=True, text=True, timeout=300,
                         cwd=SCRIPTS.parent)  # fmt: skip
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.count("usage:") == len(scripts)


def _usage_error(main, argv, capsys) -> str:
    """``main(argv)``'s one-line usage error (argparse's exit 2): its stderr."""
    import pytest

    with pytest.raises(SystemExit) as info:
        main(argv)
    err = capsys.readouterr().err
    assert info.value.code == 2 and "Traceback" not in err, (argv, err)
    return err


def test_make_sequence_refuses_a_long_run_too_short_before_rendering_anything(tmp_path, capsys):
    """A long run's timeline needs 100 frames: ``--frames 5`` was a ValueError's traceback, and with ``everything``
    only after the five standard scenarios had been rendered."""
    make = _load("make_sequence")
    out = tmp_path / "seq"
    args = ["--scenario", "everything", "--width", "16", "--height", "16", "--frames", "5", "--out", str(out)]
    err = _usage_error(make.main, args, capsys)
    assert "--frames must be >= 100 for long_run, long_run_scan, got 5" in err
    assert not out.exists()  # nothing rendered
    err = _usage_error(make.main, ["--scenario", "long_run_scan", "--frames", "99", "--out", str(out)], capsys)
    assert "for long_run_scan, got 99" in err


def test_synth_scripts_refuse_an_out_under_a_file_and_a_ground_truth_without_its_video(tmp_path, capsys):
    """Tracebacks before (NotADirectoryError from mkdir, FileNotFoundError for the video)."""
    from torchface.synth.scenarios import make_scenario
    from torchface.synth.sequence import write_sequence

    blocker = tmp_path / "file"
    blocker.write_text("x")
    make = _load("make_sequence")
    args = ["--scenario", "pose_sweep", "--width", "16", "--height", "16", "--frames", "2", "--out", str(blocker / "s")]
    assert "not a folder path" in _usage_error(make.main, args, capsys)
    files = write_sequence(make_scenario("pose_sweep", 2, 16, 16), tmp_path / "seq")
    overlay = _load("overlay_landmarks")
    err = _usage_error(overlay.main, [str(files.video), "--out", str(blocker / "o")], capsys)
    assert "not a folder path" in err
    files.video.unlink()
    err = _usage_error(overlay.main, [str(files.video), "--out", str(tmp_path / "o")], capsys)
    assert "no such video file" in err
    assert not (tmp_path / "o").exists()


def test_scripts_refuse_a_dangling_symbolic_link_as_output_folder(tmp_path, capsys, monkeypatch):
    """An --out (or --cache) that is, or is under, a symbolic link to nothing passed the "not a folder path" check
    (``exists()`` is False) and was a FileExistsError's traceback from mkdir (make_sequence.py, and
    overlay_landmarks.py after reading the whole video); now the usage error naming the link, exit 2."""
    from torchface.synth.scenarios import make_scenario
    from torchface.synth.sequence import write_sequence

    dangling = tmp_path / "dangling"
    dangling.symlink_to(tmp_path / "gone")
    make = _load("make_sequence")
    overlay = _load("overlay_landmarks")
    files = write_sequence(make_scenario("pose_sweep", 2, 16, 16), tmp_path / "seq")
    for out in (dangling, dangling / "sub"):
        args = ["--scenario", "pose_sweep", "--width", "16", "--height", "16", "--frames", "2", "--out", str(out)]
        err = _usage_error(make.main, args, capsys)
        assert f"{dangling} is a symbolic link to {tmp_path / 'gone'}, which does not exist" in err, err
        err = _usage_error(overlay.main, [str(files.video), "--out", str(out)], capsys)
        lines = err.splitlines()  # the usage (its wrapping depends on the program's name) and the error, one line
        assert lines[0].startswith("usage:") and ": error: " in lines[-1] and "is a symbolic link to" in lines[-1], err
        assert sum(": error: " in line for line in lines) == 1 and "Traceback" not in err, err
    auroc = _load("confidence_auroc")
    monkeypatch.setattr(auroc, "load_candide3", lambda: (_ for _ in ()).throw(AssertionError("the run started")))
    args = ["--scenarios", "pose_sweep", "--frames", "3", "--size", "16x16", "--cache", str(dangling / "c")]
    assert "is a symbolic link to" in _usage_error(auroc.main, args, capsys)
    evaluate = _load("evaluate")
    args = ["--scenarios", "pose_sweep", "--frames", "4", "--size", "64x48", "--cache", str(dangling), "--no-auroc"]
    assert "is a symbolic link to" in _usage_error(evaluate.main, args, capsys)
    assert not (tmp_path / "gone").exists()


def test_scripts_refuse_a_file_path_under_a_dangling_symbolic_link_before_the_run(tmp_path, capsys, monkeypatch):
    """A --json, --save or --save-series under a symbolic link to nothing passed the check (``exists()`` False) and
    failed only when the file was written, after the whole run (mkdir's FileExistsError); now a usage error first."""
    dangling = tmp_path / "dangling"
    dangling.symlink_to(tmp_path / "gone")
    target = str(dangling / "f.json")
    evaluate = _load("evaluate")
    base = ["--scenarios", "pose_sweep", "--frames", "4", "--size", "64x48", "--cache", "none", "--no-auroc"]
    for option in ("--json", "--save-series"):
        assert "is a symbolic link to" in _usage_error(evaluate.main, [*base, option, target], capsys), option
    auroc = _load("confidence_auroc")
    monkeypatch.setattr(auroc, "load_candide3", lambda: (_ for _ in ()).throw(AssertionError("the run started")))
    args = ["--scenarios", "pose_sweep", "--frames", "3", "--size", "16x16", "--cache", "none", "--save", target]
    assert "is a symbolic link to" in _usage_error(auroc.main, args, capsys)
    dataloader = _load("benchmark_dataloader")
    monkeypatch.setattr(dataloader, "render_videos", lambda *a: (_ for _ in ()).throw(AssertionError("rendering")))
    assert "is a symbolic link to" in _usage_error(dataloader.main, ["--json", target], capsys)
    raster = _load("benchmark_raster")
    monkeypatch.setattr(raster, "_candide_mesh", lambda: (_ for _ in ()).throw(AssertionError("timing")))
    assert "is a symbolic link to" in _usage_error(raster.main, ["--json", target], capsys)
    assert not (tmp_path / "gone").exists()


def test_benchmark_checks_its_cache_folder_before_rendering(tmp_path, capsys):
    """benchmark.py's --cache, a file, under one or a symbolic link to nothing, was mkdir's traceback once the
    frames had been rendered; now one of the checks made before any work."""
    import argparse

    bench = _load("benchmark")
    blocker = tmp_path / "file"
    blocker.write_text("x")
    dangling = tmp_path / "dangling"
    dangling.symlink_to(tmp_path / "gone")
    parser = argparse.ArgumentParser(prog="benchmark.py")
    ok = argparse.Namespace(frames=150, width=640, height=480, management_only=True, batches="", malloc_batches="",
                            repeats=3, json=None, mediapipe_python=None, cache=str(tmp_path / "cache"))  # fmt: skip
    bench._check_arguments(parser, ok)
    for cache, message in ((blocker, "not a folder path"), (blocker / "c", "not a folder path"),
                           (dangling, "is a symbolic link to"), (dangling / "c", "is a symbolic link to")):
        args = argparse.Namespace(**{**vars(ok), "cache": str(cache)})
        assert message in _usage_error(lambda argv: bench._check_arguments(parser, args), [], capsys), cache
    assert not (tmp_path / "cache").exists()


def test_confidence_auroc_checks_its_thresholds_and_paths_before_the_run(tmp_path, capsys, monkeypatch):
    """--good above --bad counted the frames in between as positives and negatives at once (``<5: 1  >2: 2`` of 2
    frames) and --good nan none; --save and --cache under a file were tracebacks, --save's after the whole run;
    an empty --variants rendered and tracked for nothing."""
    auroc = _load("confidence_auroc")
    monkeypatch.setattr(auroc, "load_candide3", lambda: (_ for _ in ()).throw(AssertionError("the run started")))
    blocker = tmp_path / "file"
    blocker.write_text("x")
    (tmp_path / "d.npz").mkdir()
    base = ["--scenarios", "pose_sweep", "--frames", "3", "--size", "16x16", "--cache", "none"]
    cases = [
        (["--good", "5", "--bad", "2"], "0 < --good <= --bad"),
        (["--good", "nan"], "0 < --good <= --bad"),
        (["--save", str(blocker / "s.npz")], "--save"),
        (["--save", str(tmp_path / "d.npz")], "--save"),  # a folder
        (["--cache", str(blocker)], "--cache"),
        (["--cache", str(blocker / "c")], "--cache"),
        (["--variants", ","], "--variants"),
    ]
    for extra, message in cases:
        assert message in _usage_error(auroc.main, base + extra, capsys), extra


def test_confidence_auroc_saves_its_series_whole(tmp_path, capsys, monkeypatch):
    """The .npz is written under a temporary name and renamed: a write that fails half-way (a full disk, an
    interrupt) left a truncated series.npz under the final name."""
    import numpy as np
    import pytest

    auroc = _load("confidence_auroc")
    save = tmp_path / "series"
    args = ["--scenarios", "pose_sweep", "--frames", "3", "--size", "64x48", "--cache", "none", "--variants",
            "standard", "--save", str(save)]  # fmt: skip
    real_savez = np.savez

    def failing_savez(file, **arrays):
        path = file if str(file).endswith(".npz") else f"{file}.npz"
        with open(path, "wb") as f:
            f.write(b"PK\x03\x04 half")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savez", failing_savez)
    with pytest.raises(OSError):
        auroc.main(args)
    assert list(tmp_path.iterdir()) == []
    monkeypatch.setattr(np, "savez", real_savez)
    assert auroc.main(args) == 0
    assert f"wrote {save}.npz" in capsys.readouterr().out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["series.npz"]
    with np.load(f"{save}.npz") as z:
        assert z["standard/pose_sweep/err"].shape == (3,)


def test_benchmark_scripts_refuse_bad_options_before_any_work(tmp_path, capsys, monkeypatch):
    """Tracebacks before: --repeats/--runs 0 (after the warm-up, or after the tracking epoch), --threads 0,
    --batches 0, --workers x, an unknown --device, a --json folder (after every row was timed)."""
    blocker = tmp_path / "file"
    blocker.write_text("x")
    dataloader = _load("benchmark_dataloader")
    monkeypatch.setattr(dataloader, "render_videos", lambda *a: (_ for _ in ()).throw(AssertionError("rendering")))
    for extra, message in [
        (["--repeats", "0"], "--repeats: must be an integer >= 1"),
        (["--workers", "x"], "--workers: must be"),
        (["--workers", "0,-1"], "--workers: must be"),
        (["--videos", "0"], "--videos: must be an integer >= 1"),
        (["--batch-size", "0"], "--batch-size: must be an integer >= 1"),
        (["--width", "63"], "--width: must be an even integer"),
        (["--face-size", "4"], "--face-size"),
        (["--json", str(tmp_path)], "--json"),
        (["--json", str(blocker / "j.json")], "--json"),
    ]:
        assert message in _usage_error(dataloader.main, extra, capsys), extra
    render = _load("benchmark_render")
    monkeypatch.setattr(render, "get_subject", lambda *a: (_ for _ in ()).throw(AssertionError("timing")))
    for extra, message in [(["--repeats", "0"], "--repeats"), (["--threads", "-1"], "--threads"),
                           (["--width", "0"], "--width")]:  # fmt: skip
        assert message in _usage_error(render.main, extra, capsys), extra
    raster = _load("benchmark_raster")
    monkeypatch.setattr(raster, "_candide_mesh", lambda: (_ for _ in ()).throw(AssertionError("timing")))
    for extra, message in [(["--runs", "0"], "--runs"), (["--threads", "0"], "--threads"),
                           (["--batches", "0"], "--batches"), (["--device", "bogus"], "--device bogus"),
                           (["--json", str(tmp_path)], "--json")]:  # fmt: skip
        assert message in _usage_error(raster.main, extra, capsys), extra


def test_benchmark_dataloader_judges_its_target_on_full_runs_only(capsys, monkeypatch):
    """A smoke run (2 videos of 6 frames: 12 faces) printed "target ... NOT met (median 22)": the workers' start
    was most of its epoch. Now not judged under the default run's 192 faces; judged from them on, a miss exiting with
    3 (_argtypes.EXIT_TARGET_MISSED: 0 before, as a run that met it)."""
    dataloader = _load("benchmark_dataloader")
    monkeypatch.setattr(dataloader, "render_videos", lambda root, count, frames, w, h: ([root] * count, [None] * count))

    def throughput(data, workers, batch_size):  # 50 faces/s, the cache read from the second pass on; a float
        # count, as loader_throughput gives it (printed "not judged on 12.0 faces")
        data["passes"] += 1
        return {"faces": float(data["faces"]), "seconds": data["faces"] / 50, "faces_per_s": 50.0,
                "cached_fraction": float(data["passes"] > 1)}  # fmt: skip

    monkeypatch.setattr(dataloader, "loader_throughput", throughput)
    for videos, frames, verdict, status in ((2, 6, "not judged on 12 faces", 0), (8, 24, "NOT met (median 50)", 3)):
        monkeypatch.setattr(dataloader, "VideoDataset", lambda v, lm, c: {"faces": len(v) * frames, "passes": 0})
        argv = ["--videos", str(videos), "--frames", str(frames), "--workers", "2", "--repeats", "1"]
        assert dataloader.main(argv) == status
        line = [t for t in capsys.readouterr().out.splitlines() if t.startswith("target")]
        assert len(line) == 1 and verdict in line[0], line


def test_build_synth_data_refuses_incomplete_assets_before_writing(tmp_path, monkeypatch):
    """A James folder without its files was a traceback, and one without james.jpg only after james.npz of the
    package data had been rewritten. A missing folder stays one line too (../shared absent)."""
    import pytest

    build = _load("build_synth_data")
    monkeypatch.setattr(build, "build_james_data", lambda *a: (_ for _ in ()).throw(AssertionError("writing")))
    with pytest.raises(SystemExit, match="no James assets at"):
        build.main(["--assets", str(tmp_path / "absent")])
    (tmp_path / "james").mkdir()
    (tmp_path / "james" / "james.obj").write_text("v 0 0 0\n")
    with pytest.raises(SystemExit, match="lacks james.jpg, james.ljson, LICENSE.txt"):
        build.main(["--assets", str(tmp_path)])


def test_track_grid_refuses_negative_overlay_frames(tmp_path, capsys):
    """``--frames -1`` matched no frame: the overlay PNG was saved without it and nothing said so."""
    grid = _load("track_grid")
    (tmp_path / "g").mkdir()
    (tmp_path / "g" / "clip.mpg").write_bytes(b"")
    args = ["--grid", str(tmp_path / "g"), "--detector", "dlib", "--frames", "0", "-1", "--out", str(tmp_path / "o")]
    assert "--frames must be frame indices >= 0" in _usage_error(grid.main, args, capsys)


def test_evaluate_truth_fit_starts_from_the_ground_truth_and_refuses_other_subjects(capsys):
    """--truth-fit (a diagnostic of docs/limitations.md's eyes-closed analysis) starts the tracker from frame 0's true pose,
    shape and expression: the first result is the truth; the James scan (not the tracker's model) is refused, and so
    is --lookahead beside it (both choose the first fit)."""
    import pytest
    import torch

    from torchface.model.candide import load_candide3
    from torchface.synth.scenarios import make_scenario
    from torchface.synth.sequence import render_sequence
    from torchface.tracker.module import FaceTracker

    evaluate = _load("evaluate")
    model = load_candide3()
    frames, gt = render_sequence(make_scenario("expressions", 2, 160, 120))
    fit = evaluate.truth_fit(model, gt)
    assert torch.equal(fit.shape_coeffs[0], gt.shape_coeffs.to(model.dtype))
    assert fit.shape_coeffs.abs().max() > 0  # the subject's shape is not the mean face, so this checks something
    res = FaceTracker(model=model).initialise(frames[:1].to(model.dtype), gt.landmarks_px[:1].to(model.dtype),
                                              gt.intrinsics, fit=fit)  # fmt: skip
    assert torch.allclose(res.rotation[0].double(), gt.rotation[0], atol=1e-5)
    assert torch.allclose(res.translation[0].double(), gt.translation[0], atol=1e-3)
    _, james = render_sequence(make_scenario("scan_motion", 2, 64, 48))
    with pytest.raises(ValueError, match="CANDIDE-3"):
        evaluate.truth_fit(model, james)
    base = ["--frames", "2", "--size", "64x48", "--cache", "none", "--ablations", "none", "--no-auroc"]
    for extra, message in ((["--scenarios", "long_run_scan", "--truth-fit"], "long_run_scan show james, not"),
                           (["--scenarios", "expressions", "--truth-fit", "--lookahead"], "give one")):
        with pytest.raises(SystemExit) as info:
            evaluate.main([*base, *extra])
        assert info.value.code == 2 and message in capsys.readouterr().err


def test_doc_figures_measures_on_tiny_runs(capsys):
    """scripts/doc_figures.py, the command that measures the figures README.md, TrackerConfig.min_face_width_px and
    lookahead.VIEW_TURN_FRACTION quote, runs its rendered experiments (face-width, small-frames, hard-cuts, lid-fit) on
    one clip of a few frames and refuses bad arguments in one line (grid-pan, which needs the GRID clips of
    ../shared/assets, is run by hand)."""
    figures = _load("doc_figures")
    assert figures.main(["face-width", "--widths", "27", "--clips", "1", "--frames", "3"]) == 0
    row = capsys.readouterr().out.splitlines()[-1].split()
    assert row[0] == "27.0" and row[3] == "0/1"
    assert figures.main(["small-frames", "--sizes", "160x120", "--photos", "james", "--frames", "10"]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines()[2:]]
    assert [r[:4] for r in rows] == [["james", "160x120", "3", "40x30"], ["james", "160x120", "2", "80x60"]]
    assert figures.main(["hard-cuts", "--size", "160x120", "--dx", "45", "--dz", "0", "--dyaw", "0,12",
                         "--frames", "2"]) == 0
    rows = [line.split("|") for line in capsys.readouterr().out.splitlines()[2:]]
    assert [r[0].split() for r in rows] == [["45", "0", "0"], ["45", "0", "12"]] and all(len(r) == 3 for r in rows)
    assert figures.main(["lid-fit", "--size", "small", "--cache", "none", "--draws", "3"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "3 draws of 2 px landmark noise" in lines[-4] and [r.split()[0] for r in lines[-2:]] == ["default", "no"]
    medians = [float(r.split("|")[0].split()[-5]) for r in lines[-2:]]
    assert all(0 < m < 5 for m in medians)  # the lids land off the truth, by pixels rather than millimetres
    for argv, message in ((["face-width", "--clips", "0"], "--clips must be >= 1"),
                          (["hard-cuts", "--dx", "1,x"], "expected numbers"),
                          (["face-width", "--widths", "20,x"], "widths must be numbers"),
                          (["small-frames", "--sizes", "160"], "sizes must be WxH"),
                          (["small-frames", "--frames", "9"], "--frames must be >= 10"),
                          (["grid-pan", "--clip", "nosuchclip"], "no GRID clip nosuchclip.mpg")):  # fmt: skip
        assert message in _usage_error(figures.main, argv, capsys)


def test_doc_figures_resume_sweep_runs_on_a_tiny_sweep(capsys):
    """doc_figures.py resume-sweep (docs/cli.md's figures of a sweep interrupted and resumed) on a 14-frame sweep,
    a checkpoint every 4 rows from row 4, interrupted after 10 rows: alone and as a batch of two, each resumed from
    its checkpoint (that of 8 rows, which it reads back) and from its rows; the rows before the interruption are
    never among those that part (the first differing frame, where one differs, is 10 or later)."""
    figures = _load("doc_figures")
    argv = ["resume-sweep", "--frames", "14", "--starts", "0,2", "--stop", "10", "--every", "4", "--max-frames", "4",
            "--variants", "plain"]  # fmt: skip
    assert figures.main(argv) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("pose_sweep 160x120, 14 frames (the batch: from frames 0, 2); interrupted after 10")
    rows = [[cell.split() for cell in line.split("|")] for line in lines[2:]]
    assert [r[0] for r in rows] == [["alone", "plain"], ["batch", "plain"]]
    assert all(r[1][0] == "8" for r in rows)  # the checkpoint resumed from
    assert all(r[2][3] == "none" or int(r[2][3]) >= 10 for r in rows)
    assert all(len(r[3]) == 3 and all(float(v) > 0 for v in r[3]) for r in rows)  # frames/s


def test_evaluate_eyelids_sets_the_eyelid_configuration(monkeypatch):
    """--eyelids (docs/limitations.md, eyes closed) tracks with expression quota 0.06, sparsity 0.03, the
    conservative prior on unconfident frames and an online start that keeps the landmark fit's eyelids; a quota or
    sparsity given beside it wins; without it every setting is the default."""
    import pytest

    from torchface.tracker.lookahead import LookaheadConfig
    from torchface.tracker.step import TrackerConfig

    evaluate = _load("evaluate")
    seen = []

    class Stop(Exception):
        pass

    def spy(model, config, *args, **kwargs):
        seen.append((config, evaluate.ONLINE_REFINE))
        raise Stop

    monkeypatch.setattr(evaluate, "track_sequence", spy)
    base = ["--scenarios", "expressions", "--frames", "2", "--size", "64x48", "--cache", "none", "--ablations",
            "none", "--no-auroc"]  # fmt: skip
    for flags in ([], ["--eyelids"], ["--eyelids", "--expression-quota", "0.02"]):
        with pytest.raises(Stop):
            evaluate.main([*base, *flags])
    (plain, plain_start), (eyes, eyes_start), (quota, _) = seen
    assert plain == TrackerConfig() and plain_start == LookaheadConfig()
    assert (eyes.expression_quota, eyes.expression_sparsity, eyes.template.conservative_when_unconfident) == (
        0.06, 0.03, True)
    assert eyes_start.kept_shape_units == ("Eyes vertical position",) and not eyes_start.fit_expression
    assert (quota.expression_quota, quota.expression_sparsity) == (0.02, 0.03)


@pytest.mark.parametrize(
    "flag, value, field, expected, bad, message",
    [
        # (inf passed --search-step-px: the first recovery's search raised a RuntimeError)
        ("--search-step-px", ["1.5"], "search_step_px", 1.5, [["0"], ["-2"], ["inf"], ["nan"]], "must be positive"),
        ("--recover-min-patches", ["3"], "recover_min_patches", 3, [["-1"]], "must be >= 0"),
        ("--plausible-turn-deg", ["15", "1"], "plausible_turn_deg", (15.0, 1.0), [["-1", "0"], ["inf", "1"]],
         "must be two finite values >= 0"),
    ],
)  # fmt: skip
def test_evaluate_template_flags_set_every_runs_setting(monkeypatch, capsys, flag, value, field, expected, bad,
                                                        message):  # fmt: skip
    """--search-step-px, --recover-min-patches and --plausible-turn-deg set their TemplateConfig field of every run
    (nothing else); without the flag the default; a bad value is a one-line error before any work."""
    from dataclasses import replace

    from torchface.tracker.step import TrackerConfig

    evaluate = _load("evaluate")
    seen = []

    class Stop(Exception):
        pass

    def spy(model, config, *args, **kwargs):
        seen.append(config)
        raise Stop

    monkeypatch.setattr(evaluate, "track_sequence", spy)
    base = ["--scenarios", "expressions", "--frames", "2", "--size", "64x48", "--cache", "none", "--ablations",
            "none", "--no-auroc"]  # fmt: skip
    for flags in ([], [flag, *value]):
        with pytest.raises(Stop):
            evaluate.main([*base, *flags])
    plain, given = seen
    assert plain == TrackerConfig()
    assert getattr(given.template, field) == expected
    assert given == replace(TrackerConfig(), template=replace(TrackerConfig().template, **{field: expected}))
    for values in bad:
        with pytest.raises(SystemExit) as info:
            evaluate.main([*base, flag, *values])
        assert info.value.code == 2 and f"{flag} {message}" in capsys.readouterr().err


def test_evaluate_smoothing_restarts_where_the_online_smoother_does():
    """scripts/evaluate.py --smoothing filters each run's pose offline (smoothed_run): on a short tracked clip that
    the online start re-anchors (the `expressions` scenario turns past 10 degrees at frame 2), the series is the one
    ResultSmoother gives online, given the tracker's state, the stream started afresh after the re-anchoring frame
    (before, the offline path missed that start and smeared the re-anchored estimate's step)."""
    import torch

    from torchface.model.candide import load_candide3
    from torchface.synth.scenarios import make_scenario
    from torchface.synth.sequence import render_sequence
    from torchface.tracker import FaceTracker, ResultSmoother, SmoothingConfig, TrackerConfig

    evaluate = _load("evaluate")
    model, config = load_candide3(), TrackerConfig()
    frames, gt = render_sequence(make_scenario("expressions", 8, 160, 120))
    frames = (frames.clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)  # (as evaluate reads its cached video)
    landmarks = gt.landmarks_px[:1].to(model.dtype)
    out = evaluate.track_frames(model, config, (f[None] for f in frames), gt, landmarks, "clip", 0)
    assert out.reanchored.dtype == torch.bool and int(out.reanchored.sum()) == 1
    at = int(out.reanchored.nonzero()[0, 0])
    assert at + 1 < gt.num_frames
    tracker = FaceTracker(config, model=model, refine_first=evaluate.ONLINE_REFINE)
    smoother = ResultSmoother(SmoothingConfig(), fps=gt.fps)
    x = frames.to(model.dtype) / 255.0
    online = [smoother(tracker.initialise(x[:1], landmarks, gt.intrinsics), tracker_state=tracker.state)]
    online += [smoother(tracker(x[k : k + 1]), tracker_state=tracker.state) for k in range(1, gt.num_frames)]
    R_online = torch.cat([r.rotation for r in online]).double()
    t_online = torch.cat([r.translation for r in online]).double()
    assert torch.equal(torch.cat([r.status for r in online]), out.status)  # (the same tracking)
    smooth = evaluate.smoothed_run(out, gt.fps, SmoothingConfig())
    # (offline in float64 from the float32 results, online in float32: equal to float32's rounding)
    torch.testing.assert_close(smooth.rotation, R_online, rtol=0, atol=1e-6)
    torch.testing.assert_close(smooth.translation, t_online, rtol=0, atol=1e-4)
    assert torch.equal(smooth.rotation[at + 1], out.rotation[at + 1])  # afresh at the re-anchored estimate
    before = evaluate.smooth_pose_series(out.rotation[None], out.translation[None], out.success[None],
                                         torch.arange(gt.num_frames, dtype=torch.float64)[None] / gt.fps,
                                         SmoothingConfig())[0][0]  # fmt: skip
    assert (before[at + 1] - R_online[at + 1]).abs().max() > 1e-4  # (what the offline path gave without the start)


def test_evaluate_json_holds_the_last_scenarios_smoothing_rows(tmp_path, capsys):
    """--json with --smoothing and --no-auroc: the last scenario's smoothed rows, which the table prints, are in the
    JSON too (they came after its last write, which only section (b) followed)."""
    import json

    evaluate = _load("evaluate")
    out = tmp_path / "eval.json"
    assert evaluate.main(["--scenarios", "pose_sweep", "--frames", "3", "--size", "64x48", "--ablations", "none",
                          "--cache", "none", "--threads", "1", "--no-auroc", "--progress-every", "0",
                          "--smoothing", "default", "--json", str(out)]) == 0  # fmt: skip
    assert "smooth default" in capsys.readouterr().out
    figures = json.loads(out.read_text())
    assert set(figures) == {"pose_sweep", "pose_sweep/smooth default"}
    assert figures["pose_sweep/smooth default"]["num_frames"] == 3
