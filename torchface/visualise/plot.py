"""A PNG summary plot of a track: yaw/pitch/roll, the most active AUs and the confidence over time.

Drawn with matplotlib's object API on its Agg renderer, without pyplot: the caller's matplotlib backend and open
figures are left as they were (a notebook's inline plots go on being shown).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from torchface._names import name_tuple
from torchface.geometry._checks import check_int

__all__ = ["au_groups", "plot_track"]


def _figure_class():
    """matplotlib's ``Figure`` (not pyplot, whose backend is the process's: ``matplotlib.use`` would switch it)."""
    try:
        from matplotlib.figure import Figure
    except ImportError:  # pragma: no cover - matplotlib is a dependency
        raise ImportError("plotting needs matplotlib: pip install matplotlib") from None
    return Figure


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
    rows = np.asarray(rows, dtype=np.float64).reshape(-1, len(columns))
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
    """
    columns = name_tuple(columns, "columns")
    num_aus = check_int(num_aus, "num_aus", 0)  # (-1 showed all AUs but one)
    rows = np.asarray(rows, dtype=np.float64).reshape(-1, len(columns))
    idx = {c: i for i, c in enumerate(columns)}
    for need in ("timestamp", "yaw_deg", "pitch_deg", "roll_deg", "confidence", "success"):
        if need not in idx:
            raise ValueError(f"track table has no {need!r} column")
    t = rows[:, idx["timestamp"]]
    fig = _figure_class()(figsize=(9, 7))
    axes = fig.subplots(3, 1, sharex=True)
    for name in ("yaw_deg", "pitch_deg", "roll_deg"):
        axes[0].plot(t, rows[:, idx[name]], label=name.replace("_deg", ""))
    axes[0].set_ylabel("degrees")
    axes[0].legend(loc="upper right", fontsize=8)
    groups = au_groups(columns, rows)
    if groups and len(rows) and num_aus:  # (0: no legend of nothing, which matplotlib warned about)
        series = [rows[:, idx[g[0]]] for g in groups]  # (an all-NaN one last: nanstd warned "Degrees of freedom")
        spread = np.array([np.nanstd(x) if np.isfinite(x).any() else -1.0 for x in series])
        for k in np.argsort(-spread, kind="stable")[:num_aus]:
            axes[1].plot(t, rows[:, idx[groups[k][0]]], label=" = ".join(groups[k]))
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
    if title:
        fig.suptitle(title)
    p = Path(path)
    tmp = p.with_name(p.stem + ".partial" + p.suffix)
    with warnings.catch_warnings():  # a title in a script the font lacks (a video named in Chinese, an emoji):
        warnings.filterwarnings("ignore", message=r"Glyph \d+ .* missing from", category=UserWarning)  # boxes
        fig.tight_layout()
        # the format from the final name's suffix (it was PNG whatever the name said: PNG bytes in "plot.pdf"); a
        # suffix that names no format matplotlib writes ("track.run1") is PNG, as before
        fmt = p.suffix[1:].lower()
        try:
            fig.savefig(tmp, dpi=100, format=fmt if fmt in fig.canvas.get_supported_filetypes() else "png")
        except BaseException:  # a full disk, an interruption: no partial file left behind
            tmp.unlink(missing_ok=True)
            raise
    os.replace(tmp, p)
    return p
