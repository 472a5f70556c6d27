"""A PNG summary plot of a track: yaw/pitch/roll, the most active AUs and the confidence over time.

Drawn with matplotlib's object API on its Agg renderer, without pyplot: the caller's matplotlib backend and open
figures are left as they were (a notebook's inline plots go on being shown).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from torchface._names import name_tuple
from torchface.geometry._checks import check_int
from torchface.io.errors import OutputError

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.backend_bases import RendererBase
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.text import Text

__all__ = ["au_groups", "plot_track"]

#: Figure size (inches; 100 dots per inch: 900 x 700 pixels).
_SIZE_IN = (9.0, 7.0)
#: Subplot margins (figure fractions) and the gap between the axes (of an axes' height) that fit the usual labels:
#: tight_layout's on a track's plot (left 0.084 with tick labels up to "-100" or "0.00", right 0.983, bottom 0.084,
#: hspace 0.107), a little wider. :func:`plot_track` checks that everything fit (:func:`_fits`) and lays the figure
#: out with tight_layout where it did not (which cost ~0.1 s on every plot: it draws the figure's text to measure it).
_LEFT, _RIGHT, _BOTTOM, _HSPACE = 0.09, 0.98, 0.085, 0.12
#: Space above the axes without a title, and around a title (pixels).
_TOP_PX, _TITLE_PAD_PX = 15.0, 14.0
#: Title font size (points; matplotlib's ``large``) and the least it is shrunk to for a long title (wrapped below it).
_TITLE_PT, _TITLE_MIN_PT = 12.0, 8.0
#: zlib level of the PNG (1: fastest): encoding a 200-frame track's plot took 21 ms, 30 ms at PIL's default (6), a
#: 5000-frame one's 24 ms, 43 ms, for 8 % (149 against 138 KiB) and 11 % (225 against 202 KiB) larger files.
_PNG_COMPRESS_LEVEL = 1


def _figure_class():
    """matplotlib's ``Figure`` (not pyplot, whose backend is the process's: ``matplotlib.use`` would switch it)."""
    try:
        from matplotlib.figure import Figure
    except ImportError:  # pragma: no cover - matplotlib is a dependency
        raise ImportError("plotting needs matplotlib: pip install matplotlib") from None
    return Figure


def _agg_canvas(fig: Figure) -> FigureCanvasAgg:
    """An Agg canvas for ``fig`` (matplotlib's object API: no pyplot)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    return FigureCanvasAgg(fig)


def _title(fig: Figure, title: str, renderer: RendererBase) -> tuple[float, Text | None]:
    """Set ``fig``'s title ``title`` (none where empty) so that it fits the figure's width (a long one in a smaller
    font, down to :data:`_TITLE_MIN_PT`, then wrapped onto more lines). Returns the top of the subplots below it (a
    figure fraction) and the title's text (None where there is none)."""
    W, H = fig.bbox.width, fig.bbox.height
    if not title:
        return 1.0 - _TOP_PX / H, None
    text = fig.suptitle(title, fontsize=_TITLE_PT)
    room = W - 2 * _TITLE_PAD_PX
    width = text.get_window_extent(renderer).width
    if width > room:
        size = max(_TITLE_PT * room / width, _TITLE_MIN_PT)
        text.set_fontsize(size)
        width = text.get_window_extent(renderer).width
        if width > room:  # (characters, not words: a file name may have no space)
            per_line = max(int(len(title) * room / width), 1)
            text.set_text("\n".join(title[i:i + per_line] for i in range(0, len(title), per_line)))
    box = text.get_window_extent(renderer)
    return (box.y0 - _TITLE_PAD_PX) / H, text


def _fits(fig: Figure, axes: list[Axes], title: Text | None, renderer: RendererBase) -> bool:
    """Whether ``fig``'s ``axes`` (drawn: their labels placed) have every label, tick label, offset (``1e-5``) and
    legend, and the ``title``, inside the figure, none over the axes above it (or the title)."""
    W, H = fig.bbox.width, fig.bbox.height
    boxes = []  # (box, the height it must stay under: the axes above it, or the title)
    ceiling = H if title is None else title.get_window_extent(renderer).y0
    if title is not None:
        boxes.append((title.get_window_extent(renderer), H))
    for i, ax in enumerate(axes):
        above = ceiling if i == 0 else axes[i - 1].get_window_extent(renderer).y0
        texts = [ax.yaxis.label, ax.yaxis.offsetText, ax.xaxis.label, ax.xaxis.offsetText]
        for axis in (ax.xaxis, ax.yaxis):
            lo, hi = sorted(axis.get_view_interval())
            locs = axis.get_majorticklocs()
            span = (hi - lo) * 1e-9
            texts += [t.label1 for t, x in zip(axis.get_major_ticks(len(locs)), locs) if lo - span <= x <= hi + span]
        boxes += [(t.get_window_extent(renderer), above) for t in texts if t.get_visible() and t.get_text()]
        if (legend := ax.get_legend()) is not None:
            boxes.append((legend.get_window_extent(renderer), H))
    return all(b.x0 >= 0 and b.x1 <= W and b.y0 >= 0 and b.y1 <= top for b, top in boxes)


def _table(columns: tuple[str, ...], rows: object) -> np.ndarray:
    """``rows`` as a float64 ``(T, C)`` array with ``C = len(columns)`` (one row may come as ``(C,)``), or a
    ``ValueError``: a reshape to ``(-1, C)`` took a table of other columns or a transposed one whenever the sizes
    divided, and read its values under the wrong names (linked AUs told apart, others joined)."""
    table = np.asarray(rows, dtype=np.float64)
    if table.ndim == 1 and table.shape[0] in (0, len(columns)):  # (one row, or none: [])
        return table.reshape(-1, len(columns))
    if table.ndim != 2 or table.shape[1] != len(columns):
        raise ValueError(f"rows must be (T, C) with C = len(columns) = {len(columns)}, got shape {table.shape}")
    return table


def au_groups(columns: tuple[str, ...], rows: np.ndarray) -> list[tuple[str, ...]]:
    """The ``AUxx_r`` columns of a track table, those holding the same values joined: one animation unit links
    several AUs, whose columns repeat its value (CANDIDE-3: ``AU13_r`` = ``AU15_r``, ``AU42_r`` ... ``AU45_r``).

    Args:
        columns: CSV header; rows: ``(T, C)`` values.

    Returns:
        One tuple of column names per distinct series, in column order.

    Example:
        >>> au_groups(("AU23_r", "AU24_r", "AU26_r"), np.array([[0.1, 0.1, 0.3], [0.2, 0.2, 0.0]]))
        [('AU23_r', 'AU24_r'), ('AU26_r',)]
    """
    rows = _table(columns, rows)
    groups: list[list[int]] = []
    for i, c in enumerate(columns):
        if not (c.startswith("AU") and c.endswith("_r")):
            continue
        for g in groups:
            if np.array_equal(rows[:, g[0]], rows[:, i], equal_nan=True):
                g.append(i)
                break
        else:
            groups.append([i])
    return [tuple(columns[i] for i in g) for g in groups]


def plot_track(
    columns: tuple[str, ...], rows: np.ndarray, path: str | os.PathLike[str], title: str = "", num_aus: int = 4
) -> Path:
    """Plot a track table (:func:`torchface.io.read_track_csv`) to a PNG (or the format ``path``'s suffix names).

    Args:
        columns: CSV header; rows: ``(T, C)`` values.
        path: the image, PNG unless its suffix names another format matplotlib writes (``.pdf``, ``.svg``, ...;
            written to ``<stem>.partial<suffix>`` then renamed).
        title: figure title.
        num_aus: how many ``AUxx_r`` series to show (those that vary most; 0 for none). Columns that repeat one
            animation unit's value are one series, labelled ``AU23_r = AU24_r`` (:func:`au_groups`): they were
            drawn as separate lines, one hiding the other, so the four lines of the plot showed two units.

    Raises:
        TypeError: ``columns`` is one string, or ``num_aus`` is not an int.
        ValueError: a column the plot needs is missing, or ``num_aus`` is negative.
        OutputError: the file cannot be written (its folder missing, a full disk; an ``OSError``), naming ``path``.
    """
    columns = name_tuple(columns, "columns")
    num_aus = check_int(num_aus, "num_aus", 0)  # (-1 showed all AUs but one)
    rows = _table(columns, rows)
    idx = {c: i for i, c in enumerate(columns)}
    for need in ("timestamp", "yaw_deg", "pitch_deg", "roll_deg", "confidence", "success"):
        if need not in idx:
            raise ValueError(f"track table has no {need!r} column")
    t = rows[:, idx["timestamp"]]
    fig = _figure_class()(figsize=_SIZE_IN, dpi=100)  # (the margins' pixels are at 100 dpi)
    axes = fig.subplots(3, 1, sharex=True)
    for name in ("yaw_deg", "pitch_deg", "roll_deg"):
        axes[0].plot(t, rows[:, idx[name]], label=name.replace("_deg", ""))
    axes[0].set_ylabel("degrees")
    axes[0].legend(loc="upper right", fontsize=8)
    # (an all-NaN series is not drawn: nothing to draw, and the columns without a value were one "linked" series,
    # labelled with every AU's name, a legend wider than the figure; nanstd warned "Degrees of freedom" of it)
    groups = [g for g in au_groups(columns, rows) if np.isfinite(rows[:, idx[g[0]]]).any()]
    if groups and num_aus:  # (0: no legend of nothing, which matplotlib warned about)
        spread = np.array([np.nanstd(rows[:, idx[g[0]]]) for g in groups])
        for k in np.argsort(-spread, kind="stable")[:num_aus]:
            g = groups[k]  # (more than 4 columns of one series, a table of another tool's: the first two, the last)
            label = " = ".join(g) if len(g) <= 4 else f"{g[0]} = {g[1]} = ... = {g[-1]} ({len(g)} columns)"
            axes[1].plot(t, rows[:, idx[g[0]]], label=label)
        axes[1].legend(loc="upper right", fontsize=8)
    # (it read "AU intensity": these are not OpenFace's 0-5 intensities but the linked animation unit's signed change
    # from the first frame, dimensionless, docs/cli.md "Differences from OpenFace's per-frame CSV")
    axes[1].set_ylabel("AU change from frame 0")
    measured = "dissimilarity" in idx and bool(np.isfinite(rows[:, idx["dissimilarity"]]).any())
    kind = "dissimilarity" if measured else "residual"
    axes[2].plot(t, rows[:, idx["confidence"]], color="k", label=f"confidence ({kind})")
    lost = rows[:, idx["success"]] < 0.5
    if lost.any():
        axes[2].plot(t[lost], np.zeros(int(lost.sum())), "rx", label="lost")
    axes[2].set_ylim(-0.05, 1.05)
    axes[2].set_ylabel("confidence")
    axes[2].set_xlabel("time (s)")
    axes[2].legend(loc="lower right", fontsize=8)
    p = Path(path)
    tmp = p.with_name(p.stem + ".partial" + p.suffix)
    canvas = _agg_canvas(fig)  # (its renderer measures the text; savefig to PNG draws with it)
    # the format from the final name's suffix (it was PNG whatever the name said: PNG bytes in "plot.pdf"); a suffix
    # that names no format matplotlib writes ("track.run1") is PNG, as before
    fmt = p.suffix[1:].lower()
    fmt = fmt if fmt in canvas.get_supported_filetypes() else "png"
    kwargs: dict = {"pil_kwargs": {"compress_level": _PNG_COMPRESS_LEVEL}} if fmt == "png" else {}
    with warnings.catch_warnings():  # a title in a script the font lacks (a video named in Chinese, an emoji):
        warnings.filterwarnings("ignore", message=r"Glyph \d+ .* missing from", category=UserWarning)  # boxes
        top, text = _title(fig, title, canvas.get_renderer())
        fig.subplots_adjust(left=_LEFT, right=_RIGHT, bottom=_BOTTOM, top=top, hspace=_HSPACE)
        try:
            fig.savefig(tmp, dpi=100, format=fmt, **kwargs)
            # the fixed margins suit the usual labels; where one did not fit (wide tick labels, an offset such as
            # "1e-5" over the axes above), the figure is laid out as it always was before (tight_layout) and saved
            # again
            if not _fits(fig, list(axes), text, canvas.get_renderer()):
                fig.tight_layout()
                fig.savefig(tmp, dpi=100, format=fmt, **kwargs)
            os.replace(tmp, p)
        except OSError as exc:  # a full disk, a folder not made yet, a folder at the name: the error named the
            tmp.unlink(missing_ok=True)  # temporary file alone ("No such file or directory: '.../plot.partial.png'")
            raise OutputError(f"{p}: cannot write the plot ({exc.strerror or exc})") from None
        except BaseException:  # an interruption: no partial file left behind
            tmp.unlink(missing_ok=True)
            raise
    return p
