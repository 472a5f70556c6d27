"""Overlay geometry and drawing, and the summary plot."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from torchface.geometry.camera import Intrinsics
from torchface.model import load_candide3
from torchface.visualise import AXIS_LENGTH_MM, draw_overlay, mesh_edges, overlay_geometry, plot_track


def test_mesh_edges_against_brute_force():
    faces = load_candide3().faces
    ref = {tuple(sorted((int(f[i]), int(f[(i + 1) % 3])))) for f in faces for i in range(3)}
    edges = mesh_edges(faces)
    assert {tuple(e) for e in edges.tolist()} == ref and len(edges) == len(ref)
    with pytest.raises(ValueError, match=r"\(F, 3\)"):
        mesh_edges(torch.zeros(4, 2, dtype=torch.long))


def test_overlay_geometry_known_answer():
    model = load_candide3()
    intr = Intrinsics.default(320, 240)
    R = torch.eye(3).expand(2, 3, 3)
    t = torch.tensor([[0.0, 0.0, 500.0], [10.0, 0.0, 400.0]])
    shape, anim = torch.zeros(2, model.num_shape), torch.zeros(2, model.num_animation)
    verts_px, axes_px = overlay_geometry(model, shape, anim, R, t, intr)
    assert verts_px.shape == (2, model.num_vertices, 2) and axes_px.shape == (2, 4, 2)
    f = intr.fx
    torch.testing.assert_close(axes_px[0, 0], torch.tensor([intr.cx, intr.cy]))
    torch.testing.assert_close(axes_px[0, 1], torch.tensor([intr.cx + f * AXIS_LENGTH_MM / 500.0, intr.cy]))
    torch.testing.assert_close(axes_px[1, 0], torch.tensor([intr.cx + f * 10.0 / 400.0, intr.cy]))


def test_draw_overlay_draws_and_keeps_input():
    img = np.zeros((120, 160, 3), np.uint8)
    verts = np.array([[20.0, 20.0], [140.0, 20.0], [80.0, 100.0], [np.nan, 5.0]])
    edges = np.array([[0, 1], [1, 2], [2, 0], [0, 3]])
    axes = np.array([[80.0, 60.0], [120.0, 60.0], [80.0, 100.0], [1e9, -1e9]])
    out = draw_overlay(img, verts, edges, axes, 0.75, True, "#3")
    assert out.shape == img.shape and out.dtype == np.uint8 and img.max() == 0
    assert out[20, 80].any()  # on the top edge
    assert out[60, 100, 2] > 100  # red x axis (BGR)
    with pytest.raises(ValueError, match="uint8"):
        draw_overlay(img.astype(np.float32), verts, edges, axes, 0.5, True)
    bar = (slice(112, 116), slice(30, 40))  # the confidence bar's right part (full bar: x 4..44)
    assert not (draw_overlay(img, verts, edges, axes, 1.0, True)[bar] == 60).all()  # the bar over the grey track
    assert (draw_overlay(img, verts, edges, axes, float("nan"), True)[bar] == 60).all()  # NaN: no bar (was full)


def test_confidence_bar_is_the_confidences_share_of_its_track():
    """The bar covers round(confidence * (W // 4)) of the track's W // 4 pixels: none at 0 or NaN (a 1-pixel bar
    was drawn) and half at 0.5 (it was one pixel longer than its share)."""
    img = np.zeros((120, 160, 3), np.uint8)
    row = 120 - 7  # a row of the bar (rows H - 10 .. H - 4)
    nothing, axes = np.zeros((0, 2)), np.full((4, 2), np.nan)
    cases = ((0.0, False, 0), (float("nan"), True, 0), (0.5, True, 20), (1.0, True, 40), (0.25, False, 10))
    for conf, ok, want in cases:
        out = draw_overlay(img, nothing, np.zeros((0, 2), np.int64), axes, conf, ok)
        colour = (0, 200, 255) if ok else (0, 0, 255)
        assert int((out[row] == colour).all(-1).sum()) == want, (conf, ok)
        assert int((out[row] == 60).all(-1).sum()) == 40 - want, (conf, ok)  # the track's rest


def test_nothing_behind_the_camera_or_non_finite_is_drawn():
    """A head behind the camera draws no wireframe and no axes (its clamped projection put the head origin at the
    image's centre, with axes and lines across the image), and an edge with a NaN end is not drawn (it became a
    line toward a far corner)."""
    model = load_candide3()
    intr = Intrinsics.default(160, 120)
    shape, anim = torch.zeros(1, model.num_shape), torch.zeros(1, model.num_animation)
    verts_px, axes_px = overlay_geometry(model, shape, anim, torch.eye(3)[None], torch.tensor([[0.0, 0.0, -500.0]]),
                                         intr)  # fmt: skip
    assert torch.isnan(verts_px).all() and torch.isnan(axes_px).all()
    img = np.zeros((120, 160, 3), np.uint8)
    out = draw_overlay(img, verts_px[0].numpy(), mesh_edges(model.faces), axes_px[0].numpy(), 0.5, False)
    assert not out[:90].any()  # only the text and the bar, at the bottom
    front, _ = overlay_geometry(model, shape, anim, torch.eye(3)[None], torch.tensor([[0.0, 0.0, 500.0]]), intr)
    assert torch.isfinite(front).all()  # (in front: as before)
    verts = np.array([[20.0, 60.0], [60.0, 60.0], [np.nan, np.nan]])
    no_axes = np.full((4, 2), np.nan)
    out = draw_overlay(img, verts, np.array([[0, 1], [1, 2]]), no_axes, 0.5, True)
    drawn = out[:90].any(-1)
    assert drawn[60, 40] and drawn.sum() < 200, drawn.sum()  # the finite edge, nothing toward a corner


def test_plot_track_writes_png(tmp_path):
    cols = ("frame", "timestamp", "success", "confidence", "yaw_deg", "pitch_deg", "roll_deg", "AU26_r", "AU2_r")
    T = 20
    rows = np.column_stack([
        np.arange(T), np.arange(T) / 25, np.arange(T) % 7 != 3, np.linspace(0, 1, T),
        np.sin(np.arange(T)), np.zeros(T), np.zeros(T), np.linspace(0, 1, T), np.zeros(T),
    ])  # fmt: skip
    p = plot_track(cols, rows, tmp_path / "plot.png", title="t")
    assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and not list(tmp_path.glob("*.partial*"))
    with pytest.raises(TypeError, match="one string"):  # its characters were taken as nine columns
        plot_track(",".join(cols), rows, tmp_path / "s.png")
    with pytest.raises(ValueError, match="yaw_deg"):
        plot_track(("frame", "timestamp"), np.zeros((2, 2)), tmp_path / "x.png")
    # the suffix names the format (PNG bytes were written whatever it said); none: PNG
    assert plot_track(cols, rows, tmp_path / "plot.pdf").read_bytes()[:5] == b"%PDF-"
    assert b"<svg" in plot_track(cols, rows, tmp_path / "plot.svg").read_bytes()[:1000]
    assert plot_track(cols, rows, tmp_path / "plot").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert plot_track(cols, rows, tmp_path / "plot.run1").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"  # no format
    assert sorted(f.name for f in tmp_path.iterdir()) == ["plot", "plot.pdf", "plot.png", "plot.run1", "plot.svg"]


def test_plot_track_num_aus_zero_shows_none_and_negative_is_refused(tmp_path):
    """``num_aus=0`` plots no AU and warns of nothing (matplotlib warned of an empty legend); a negative count is a
    ValueError (-1 silently plotted every AU but one)."""
    import warnings

    cols = ("timestamp", "success", "confidence", "yaw_deg", "pitch_deg", "roll_deg", "AU26_r", "AU02_r")
    rows = np.column_stack([np.arange(5) / 25, np.ones(5), np.ones(5), *np.zeros((3, 5)), np.arange(5), -np.arange(5)])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert plot_track(cols, rows, tmp_path / "p.png", num_aus=0).is_file()
    with pytest.raises(ValueError, match="num_aus"):
        plot_track(cols, rows, tmp_path / "q.png", num_aus=-1)
    for bad in (1.5, True):  # a wrong type is a TypeError (it was a ValueError)
        with pytest.raises(TypeError, match="num_aus"):
            plot_track(cols, rows, tmp_path / "q.png", num_aus=bad)  # type: ignore[arg-type]
    assert not (tmp_path / "q.png").exists()


def test_plot_track_leaves_the_callers_matplotlib_backend_and_figures_alone(tmp_path):
    """A caller's backend (a notebook's inline one; svg stands for it) and open figures are kept: the plot used
    to switch the process's backend to Agg (``matplotlib.use``), so the caller's later figures were not shown."""
    import matplotlib
    import matplotlib.pyplot as plt

    before = matplotlib.get_backend()
    plt.switch_backend("svg")
    fig = plt.figure()
    try:
        cols = ("timestamp", "success", "confidence", "yaw_deg", "pitch_deg", "roll_deg")
        plot_track(cols, np.zeros((3, len(cols))), tmp_path / "plot.png")
        assert matplotlib.get_backend() == "svg" and plt.get_fignums() == [fig.number]
    finally:
        plt.close(fig)
        plt.switch_backend(before)


def test_a_failed_frame_is_labelled_failed_not_lost():
    """Status 2 (FAILED: no estimate this frame) was labelled " LOST" like status 3: ``unusable_label`` names it;
    a usable frame draws no such word, whatever the label."""
    img = np.zeros((120, 160, 3), np.uint8)
    nothing, axes = np.zeros((0, 2)), np.full((4, 2), np.nan)
    edges = np.zeros((0, 2), np.int64)

    def draw(ok, word):
        return draw_overlay(img, nothing, edges, axes, 0.5, ok, "#1", unusable_label=word)

    assert not np.array_equal(draw(False, "FAILED"), draw(False, "LOST"))
    assert np.array_equal(draw(False, "LOST"), draw_overlay(img, nothing, edges, axes, 0.5, False, "#1"))
    assert np.array_equal(draw(True, "FAILED"), draw(True, "LOST"))


def _small_track():
    cols = ("frame", "timestamp", "success", "confidence", "yaw_deg", "pitch_deg", "roll_deg", "AU26_r")
    T = 5
    rows = np.column_stack([np.arange(T), np.arange(T) / 25, np.ones(T), np.ones(T), *np.zeros((4, T))])
    return cols, rows


def test_plot_track_title_in_a_script_the_font_lacks_warns_nothing(tmp_path):
    """A video named in Chinese or with an emoji (the title): matplotlib warned twice per missing glyph, several
    multi-line warnings on stderr for every ``torchface track`` of such a file."""
    cols, rows = _small_track()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        p = plot_track(cols, rows, tmp_path / "plot.png", title="é 中文 😀 (5 frames)")
    assert p.read_bytes()[:4] == b"\x89PNG"


def test_plot_track_of_an_all_nan_au_column_warns_nothing(tmp_path):
    """An AU column without a finite value (a table from another tool, a unit never measured): numpy's
    ``RuntimeWarning: Degrees of freedom <= 0 for slice`` from ranking the AUs by spread."""
    cols, rows = _small_track()
    cols, rows = (*cols, "AU01_r"), np.column_stack([rows, np.full(len(rows), np.nan)])
    rows[:, cols.index("AU26_r")] = np.linspace(0.0, 1.0, len(rows))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        p = plot_track(cols, rows, tmp_path / "plot.png", num_aus=1)
    assert p.read_bytes()[:4] == b"\x89PNG"


def test_plot_track_leaves_no_partial_file_when_saving_fails(tmp_path, monkeypatch):
    """A full disk mid-save left ``<name>.partial.png`` behind."""
    from matplotlib.figure import Figure

    def full_disk(self, fname, **kwargs):
        open(fname, "wb").close()
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Figure, "savefig", full_disk)
    cols, rows = _small_track()
    with pytest.raises(OSError, match="No space"):
        plot_track(cols, rows, tmp_path / "plot.png")
    assert list(tmp_path.iterdir()) == []


def test_plot_track_draws_the_aus_one_unit_links_as_one_line(tmp_path, monkeypatch):
    """One animation unit links several AUs, whose CSV columns repeat its value (``AU23_r`` = ``AU24_r``, ``AU26_r`` =
    ``AU27_r``): the plot of "the most active AUs" drew each as its own line, one hiding the other, so on the demo
    clip its four lines showed two units (legend: AU24_r, AU23_r, AU27_r, AU26_r). Now a repeated series is one line
    labelled with every column it stands for, and ``num_aus`` counts distinct series."""
    import torchface.visualise.plot as plot_module

    figures = []
    make = plot_module._figure_class()

    def capture(*args, **kwargs):
        figures.append(make(*args, **kwargs))
        return figures[-1]

    monkeypatch.setattr(plot_module, "_figure_class", lambda: capture)
    T = 10
    lip, jaw, brow, lid = np.sin(np.arange(T)), np.linspace(0, 3, T), np.linspace(0, 0.5, T), np.cos(np.arange(T)) / 3
    cols = ("timestamp", "success", "confidence", "yaw_deg", "pitch_deg", "roll_deg",
            "AU04_r", "AU23_r", "AU24_r", "AU26_r", "AU27_r", "AU42_r", "AU43_r")  # fmt: skip
    rows = np.column_stack([np.arange(T) / 25, np.ones(T), np.ones(T), *np.zeros((3, T)),
                            brow, lip, lip, jaw, jaw, lid, lid])  # fmt: skip
    plot_track(cols, rows, tmp_path / "p.png")
    labels = [line.get_label() for line in figures[0].axes[1].get_lines()]
    assert labels == ["AU26_r = AU27_r", "AU23_r = AU24_r", "AU42_r = AU43_r", "AU04_r"]
    assert plot_module.au_groups(cols, rows) == [("AU04_r",), ("AU23_r", "AU24_r"), ("AU26_r", "AU27_r"),
                                                 ("AU42_r", "AU43_r")]
    # the axis said "AU intensity", but the AUxx_r columns are no intensities (OpenFace's 0-5): they are the linked
    # unit's signed change from the first frame (negative for the opposite movement), and the axis says so
    ylabel = figures[0].axes[1].get_ylabel()
    assert "intensity" not in ylabel and "frame 0" in ylabel, ylabel


def _what_does_not_fit(fig) -> list[str]:
    """What of a drawn ``fig`` (matplotlib's own measure: each axes' tight box, its tick and axis labels and offsets,
    and the title) is not wholly inside the figure, or overlaps the axes above it."""
    renderer, (x0, y0), (x1, y1) = fig.canvas.get_renderer(), *fig.bbox.get_points()
    boxes = [("title", fig._suptitle.get_window_extent(renderer))] if fig._suptitle is not None else []
    boxes += [(f"axes {i}", ax.get_tightbbox(renderer)) for i, ax in enumerate(fig.axes)]
    bad = [name for name, e in boxes if not (x0 <= e.x0 and e.x1 <= x1 and y0 <= e.y0 and e.y1 <= y1)]
    return bad + [f"{a} over {b}" for (a, e), (b, f) in zip(boxes, boxes[1:]) if e.y0 < f.y1]


def test_plot_track_lays_out_without_tight_layout_and_everything_fits(tmp_path, monkeypatch):
    """The layout: fixed margins that fit a track's usual labels, not tight_layout on every plot (which drew the
    figure's text once more to measure it: ~0.1 s of the ~0.3 s each video's plot took); where a label does not fit
    them (tick labels of six digits and more, an offset), tight_layout as before. A title wider than the figure
    (a long file name, without a space) was cut at both sides: it is shrunk, then wrapped, to fit."""
    import torchface.visualise.plot as plot_module
    from matplotlib.figure import Figure

    figures, tight = [], []
    make = plot_module._figure_class()

    def capture(*args, **kwargs):
        figures.append(make(*args, **kwargs))
        return figures[-1]

    monkeypatch.setattr(plot_module, "_figure_class", lambda: capture)
    layout = Figure.tight_layout
    monkeypatch.setattr(Figure, "tight_layout", lambda self, *a, **k: tight.append(1) or layout(self, *a, **k))
    cols, rows = _small_track()
    rows[:, cols.index("yaw_deg")] = np.linspace(-40.0, 60.0, len(rows))
    rows[:, cols.index("AU26_r")] = np.linspace(0.0, 0.6, len(rows))
    cases = {
        "usual": (rows, "clip (5 frames)", False),
        "long title": (rows, "a_long_file_name_without_a_space_" * 8 + " (5 frames)", False),
        "tiny AUs": (rows * np.where(np.array(cols) == "AU26_r", 1e-4, 1.0), "t", False),  # a "1e-5" offset
        "wide ticks": (rows * np.where(np.array(cols) == "yaw_deg", 1e4, 1.0), "t", True),  # "-400000"
    }  # fmt: skip
    for name, (table, title, needs_tight) in cases.items():
        n = len(tight)
        plot_module.plot_track(cols, table, tmp_path / f"{name}.png", title=title)
        assert (len(tight) > n) == needs_tight, name
        assert _what_does_not_fit(figures[-1]) == [], name
    assert figures[1]._suptitle.get_text().count("\n") >= 1  # shrunk to 8 pt, then wrapped
    # no AU measured (15 columns of NaN, "equal"): one series labelled "AU01_r = AU02_r = ... = AU15_r", a legend
    # wider than the figure; a series without a value is not drawn
    aus = tuple(f"AU{k:02d}_r" for k in range(1, 16))
    nan = np.column_stack([rows, np.full((len(rows), len(aus)), np.nan)])
    plot_module.plot_track((*cols, *aus), nan, tmp_path / "no AU.png", title="t")
    assert _what_does_not_fit(figures[-1]) == []
    assert [line.get_label() for line in figures[-1].axes[1].get_lines()] == ["AU26_r"]
    # one series of many columns (another tool's table) is labelled with its first two and last
    same = np.column_stack([rows, np.repeat(rows[:, [cols.index("AU26_r")]], len(aus), axis=1)])
    plot_module.plot_track((*cols, *aus), same, tmp_path / "many.png", title="t", num_aus=1)
    assert [line.get_label() for line in figures[-1].axes[1].get_lines()] == [
        "AU26_r = AU01_r = ... = AU15_r (16 columns)"]
    assert _what_does_not_fit(figures[-1]) == []


def test_draw_overlay_refuses_overlay_geometrys_batched_points_naming_the_shape():
    """overlay_geometry's ``(B, V, 2)`` and ``(B, 4, 2)`` passed as they come raised "IndexError: index 1 is out of
    bounds for axis 0 with size 1" (B = 1), or drew edges between the streams' vertices (B > 1)."""
    model = load_candide3()
    intr = Intrinsics.default(160, 120)
    shape, anim = torch.zeros(1, model.num_shape), torch.zeros(1, model.num_animation)
    t = torch.tensor([[0.0, 0.0, 500.0]])
    verts, axes = overlay_geometry(model, shape, anim, torch.eye(3)[None], t, intr)
    img, edges = np.zeros((120, 160, 3), np.uint8), mesh_edges(model.faces)
    with pytest.raises(ValueError, match=r"verts_px must be \(V, 2\).*\(1, 113, 2\).*take \[b\]"):
        draw_overlay(img, verts, edges, axes[0], 0.9, True)
    with pytest.raises(ValueError, match=r"axes_px must be \(4, 2\).*\(1, 4, 2\).*take \[b\]"):
        draw_overlay(img, verts[0], edges, axes, 0.9, True)
    with pytest.raises(ValueError, match=r"axes_px must be \(4, 2\).*\(3, 2\)"):
        draw_overlay(img, verts[0], edges, axes[0, :3], 0.9, True)
    assert draw_overlay(img, verts[0], edges, axes[0], 0.9, True).any()  # one frame's tensors: drawn
    # a one-element confidence (TrackResult.confidence[b:b + 1]) met Tensor.__format__'s TypeError; a batch's is told
    one = draw_overlay(img, verts[0], edges, axes[0], torch.tensor([0.9]), True)
    assert np.array_equal(one, draw_overlay(img, verts[0], edges, axes[0], 0.9, True))
    with pytest.raises(ValueError, match=r"confidence must be one frame's number, got Tensor of shape \(2,\)"):
        draw_overlay(img, verts[0], edges, axes[0], torch.tensor([0.9, 0.8]), True)


def test_plot_track_into_a_folder_not_made_is_an_output_error_naming_the_plot(tmp_path):
    """A folder not made yet raised FileNotFoundError naming ``<stem>.partial.png``, a file the caller never named;
    an OutputError (an OSError) names the plot asked for, as write_json names its file."""
    from torchface.io import OutputError

    cols, rows = _small_track()
    target = tmp_path / "no such folder" / "my plot.png"
    with pytest.raises(OutputError, match=r"my plot\.png: cannot write the plot \(No such file or directory\)") as e:
        plot_track(cols, rows, target)
    assert "partial" not in str(e.value) and not list(tmp_path.rglob("*partial*"))
    (tmp_path / "folder.png").mkdir()  # a folder at the plot's name: its renaming failed, the temporary file left
    with pytest.raises(OutputError, match=r"folder\.png: cannot write the plot"):
        plot_track(cols, rows, tmp_path / "folder.png")
    assert not list(tmp_path.glob("*partial*"))


def test_overlay_arguments_are_checked_by_name():
    """overlay_geometry posed the mesh with its own matmul: a float64 pose of a float32 model was "expected scalar
    type Double but found Float" (axes_geometry promoted it), an unbatched rotation an IndexError, a (3,)
    translation a broadcast error. mesh_edges told a numpy array "must be an (F, 3) tensor, got (1, 3)" and truncated
    float indices. draw_overlay told a tensor image "must be (H, W, 3) uint8, got torch.Size([H, W, 3]) torch.uint8",
    met float edges or out-of-range ones with numpy's IndexError (a negative one wrapped), points that require grad
    with "Can't call numpy() on Tensor that requires grad", and drew success="no" green."""
    from torchface.visualise import axes_geometry

    model = load_candide3()
    intr = Intrinsics.default(160, 120)
    shape, anim = torch.zeros(1, model.num_shape), torch.zeros(1, model.num_animation)
    R, t = torch.eye(3)[None], torch.tensor([[0.0, 0.0, 500.0]])
    verts, axes = overlay_geometry(model, shape, anim, R, t, intr)
    verts64, axes64 = overlay_geometry(model, shape, anim, R.double(), t.double(), intr)
    assert verts64.dtype == axes64.dtype == torch.float64
    torch.testing.assert_close(verts64, verts.double(), rtol=0, atol=1e-4)
    torch.testing.assert_close(axes64, axes_geometry(R.double(), t.double(), intr), rtol=0, atol=0)
    with pytest.raises(ValueError, match=r"rotation must be \(B, 3, 3\), got shape \(3, 3\)"):
        overlay_geometry(model, shape, anim, R[0], t, intr)
    with pytest.raises(ValueError, match=r"translation must be \(B, 3\), got shape \(3,\)"):
        overlay_geometry(model, shape, anim, R, t[0], intr)
    with pytest.raises(ValueError, match=r"batch sizes of rotation \(2\) and translation \(3\) must match or be 1"):
        overlay_geometry(model, shape, anim, R.expand(2, 3, 3), t.expand(3, 3), intr)
    with pytest.raises(TypeError, match="rotation must be a torch.Tensor, got ndarray"):
        axes_geometry(R.numpy(), t, intr)
    with pytest.raises(TypeError, match=r"faces must be an integer torch.Tensor \(F, 3\), got ndarray"):
        mesh_edges(model.faces.numpy())
    with pytest.raises(TypeError, match="faces must be an integer torch.Tensor .* got dtype torch.float32"):
        mesh_edges(model.faces.float())
    img, edges = np.zeros((120, 160, 3), np.uint8), mesh_edges(model.faces)
    with pytest.raises(TypeError, match=r"image_bgr must be a numpy array \(H, W, 3\) uint8, got Tensor \(a tensor: "):
        draw_overlay(torch.from_numpy(img), verts[0], edges, axes[0], 0.9, True)
    with pytest.raises(ValueError, match=r"edges must be \(E, 2\) integer vertex pairs .* float64"):
        draw_overlay(img, verts[0], edges.astype(np.float64), axes[0], 0.9, True)
    for bad in (np.array([[0, 113]]), np.array([[-1, 2]])):
        with pytest.raises(ValueError, match=r"edges must index the 113 vertices of verts_px, got indices in"):
            draw_overlay(img, verts[0], bad, axes[0], 0.9, True)
    with pytest.raises(TypeError, match="success must be a bool, got str 'no'"):
        draw_overlay(img, verts[0], edges, axes[0], 0.9, "no")  # type: ignore[arg-type]
    want = draw_overlay(img, verts[0], edges, axes[0], 0.9, False)
    tracked = verts[0].clone().requires_grad_()
    assert np.array_equal(draw_overlay(img, tracked, edges, axes[0], 0.9, torch.tensor(False)), want)


def test_au_groups_and_plot_track_refuse_rows_of_other_columns(tmp_path):
    """Both read ``rows.reshape(-1, len(columns))``: a table of other columns, or a transposed one, was taken whenever
    the sizes divided, and its values read under the wrong names (AUs of one unit told apart: two AU columns over a
    3-column table grouped nothing). Now a ValueError saying the shape; one row as (C,) and none as [] still go."""
    from torchface.visualise import au_groups

    cols = ("AU23_r", "AU24_r", "AU26_r")
    rows = np.array([[0.1, 0.1, 0.3], [0.2, 0.2, 0.0]])
    assert au_groups(cols, rows) == [("AU23_r", "AU24_r"), ("AU26_r",)]
    assert au_groups(cols, rows[0]) == [("AU23_r", "AU24_r"), ("AU26_r",)]
    assert au_groups(cols, []) == [cols]  # (no values: every series the same)
    with pytest.raises(ValueError, match=r"rows must be \(T, C\) with C = len\(columns\) = 2, got shape \(2, 3\)"):
        au_groups(cols[:2], rows)
    with pytest.raises(ValueError, match=r"rows must be \(T, C\) with C = len\(columns\) = 3, got shape \(3, 2\)"):
        au_groups(cols, rows.T)
    with pytest.raises(ValueError, match=r"rows must be \(T, C\) with C = len\(columns\) = 3, got shape \(3, 2\)"):
        plot_track(cols, rows.T, tmp_path / "plot.png")
    assert not (tmp_path / "plot.png").exists()
