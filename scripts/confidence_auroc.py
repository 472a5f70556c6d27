#!/usr/bin/env python
"""How well do the tracker's confidences separate good frames from bad ones? (issue 5, AUROC)

For each scenario (read from evaluate.py's sequence cache, rendered there when missing) the tracker runs with
the default TrackerConfig, template management included (torchface.tracker.managed_step), from frame 0's
noisy ground-truth landmarks, as evaluate.py does. Every frame gets

* the geodesic rotation error relative to frame 0 (torchface.synth.metrics.relative_rotation_error_deg),
* (a) the solver's residual confidence (TrackResult.residual_confidence),
* (b) the dissimilarity confidence the tracker reports (TrackResult.confidence): the frame's normalised face
  against that of the mosaic entry nearest the estimate (torchface.tracker.managed.estimate_confidence).

(scripts/evaluate.py's section (b) measures the tracker's own confidence, pooled over every scenario including
the long ones; this script keeps the variants below, among them the injected pose errors.)

Positives are frames with error < --good (2 deg), negatives frames with error > --bad (5 deg); frames in
between and frame 0 are left out. The AUROC of each confidence (probability that a random positive scores
above a random negative, ties counting one half) is printed pooled over the scenarios and per scenario.

Variants (--variants, comma list):
  standard      the scenarios as they are.
  no_illum      light_switch tracked with use_illumination=False (a weaker tracker on the hardest light).
  inject        the standard tracks (the same run), but on every third frame from frame 1 the pose used for
                scoring and for the normalised face is rotated by a random axis and an angle uniform in
                [0, 10] deg (seeded); the tracker itself continues from its own estimate. The residual
                confidence cannot see this corruption, so (a) is meaningless there and printed only for
                completeness.

Examples:
    python scripts/confidence_auroc.py --scenarios pose_sweep --frames 40 --size 320x240
    python scripts/confidence_auroc.py                      # all scenarios, full size and length
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

# _argtypes first (run as a command, it makes a Ctrl-C during the heavy imports below one line, status 130)
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _argtypes import add_threads_option, checkout_out, comma_items, file_problem, folder_problem  # noqa: E402
from _argtypes import frame_size, integer, output_file, set_threads  # noqa: E402
from _argtypes import written_whole  # noqa: E402
from _argtypes import run_command  # noqa: E402

import numpy as np
import torch
from torch import Tensor

import evaluate as ev  # noqa: E402

from torchface.geometry.so3 import axis_angle_to_matrix, matrix_to_axis_angle  # noqa: E402
from torchface.model.candide import load_candide3  # noqa: E402
from torchface.synth.metrics import auroc, relative_rotation_error_deg  # noqa: E402
from torchface.synth.scenarios import SCENARIOS, scenario_size  # noqa: E402
from torchface.template.management import TemplateConfig  # noqa: E402
from torchface.tracker.params import ParamLayout  # noqa: E402
from torchface.tracker.managed import estimate_confidence, initialise_managed, managed_step  # noqa: E402
from torchface.tracker.step import TrackerConfig  # noqa: E402

VARIANTS = ("standard", "no_illum", "inject")
INJECT_EVERY = 3
INJECT_MAX_DEG = 10.0


def _perturb(axis_angle: Tensor, g: torch.Generator) -> tuple[Tensor, float]:
    """Rotate ``(1, 3)`` axis-angle by a random axis and angle in [0, INJECT_MAX_DEG] degrees (camera side)."""
    axis = torch.randn(1, 3, generator=g, dtype=torch.float64)
    axis = axis / axis.norm()
    angle = float(torch.rand(1, generator=g, dtype=torch.float64)) * INJECT_MAX_DEG
    delta = axis_angle_to_matrix((axis * math.radians(angle)).to(axis_angle))
    return matrix_to_axis_angle(delta @ axis_angle_to_matrix(axis_angle)), angle


def run(
    name: str, seq: ev.Sequence, model, config: TrackerConfig, seed: int, inject: bool, progress_every: int = 0
) -> dict[str, dict[str, np.ndarray]]:
    """Track one sequence with template management; per frame: rotation error, the residual confidence, the
    dissimilarity and its confidence (TrackResult.confidence). Every ``progress_every`` frames (and at the last; 0:
    never) a progress line on stderr, as evaluate.py's: the frame, its rotation error, status, confidence and
    frames/s (nothing was said while a scenario was tracked: minutes at full size and length).

    Returns ``{"standard": series}`` and, with ``inject``, also ``{"inject": series}`` from the same track
    (only the scored pose of every third frame differs; its dissimilarity is measured as managed_step does).
    """
    dev, dt = model.device, model.dtype
    layout = ParamLayout(model.num_animation, 5)
    T = seq.frames.shape[0]
    g = torch.Generator().manual_seed(seed + 1)

    def frame(i: int) -> Tensor:
        return seq.frames[i : i + 1].to(device=dev).to(dt) / 255.0

    landmarks = ev.initial_landmarks(seq.gt, seed).to(device=dev, dtype=dt)
    state, res = initialise_managed(model, config, frame(0), landmarks, seq.gt.intrinsics)
    keys = ("standard", "inject") if inject else ("standard",)
    rot0 = res.rotation.detach().cpu().to(torch.float64)
    series = {k: {"rot": [rot0], "conf_tracker": [float(res.residual_confidence[0])], "diss": [0.0],
                  "conf_diss": [float(res.confidence[0])], "injected": [0.0]} for k in keys}  # fmt: skip
    start = time.perf_counter()
    for i in range(1, T):
        state, res = managed_step(model, config, state, frame(i))
        s = series["standard"]
        s["rot"].append(res.rotation.detach().cpu().to(torch.float64))
        s["conf_tracker"].append(float(res.residual_confidence[0]))
        s["diss"].append(float(res.dissimilarity[0]))
        s["conf_diss"].append(float(res.confidence[0]))
        s["injected"].append(0.0)
        if progress_every and (i % progress_every == 0 or i == T - 1):
            R_pair = torch.cat([rot0, s["rot"][-1]])
            err = float(relative_rotation_error_deg(R_pair, seq.gt.rotation[[0, i]].to(torch.float64))[1])
            fps = i / max(time.perf_counter() - start, 1e-9)
            ev.log(f"  {name}: frame {i}/{T - 1} rot err {err:.2f} deg, status {int(res.status[0])}, "
                   f"confidence {float(res.confidence[0]):.2f}, {fps:.1f} frames/s")  # fmt: skip
        if not inject:
            continue
        k = series["inject"]
        if i % INJECT_EVERY == 1:
            aa, t, alpha, light = layout.split(state.params)
            aa_bad, angle = _perturb(aa, g)
            bad = replace(state, params=torch.cat([aa_bad, t, alpha, light], -1))
            with torch.no_grad():
                conf_bad, diss_bad = estimate_confidence(model, config, bad, frame(i))
            k["rot"].append(axis_angle_to_matrix(aa_bad).detach().cpu().to(torch.float64))
            k["conf_tracker"].append(s["conf_tracker"][-1])
            k["diss"].append(float(diss_bad[0]))
            k["conf_diss"].append(float(conf_bad[0]))
            k["injected"].append(angle)
        else:
            for f in ("rot", "conf_tracker", "diss", "conf_diss", "injected"):
                k[f].append(s[f][-1])
    ms_frame = 1e3 * (time.perf_counter() - start) / max(T - 1, 1)
    result = {}
    for k in keys:
        err = relative_rotation_error_deg(torch.cat(series[k].pop("rot")), seq.gt.rotation.to(torch.float64))
        result[k] = {"err": err.numpy(), **{f: np.array(x) for f, x in series[k].items()}}
    ev.log(f"{name}: {T} frames, {ms_frame:.0f} ms/frame, {int(state.management.mosaic.num_entries[0])} mosaic "
           f"entries, max err {float(result['standard']['err'].max()):.2f} deg")  # fmt: skip
    return result


def report(label: str, data: dict[str, np.ndarray], good: float, bad: float) -> str:
    err = data["err"][1:]
    pos = err < good
    neg = err > bad
    cells = [f"{label:28s} frames {err.size:4d}  <{good:g}: {int(pos.sum()):4d}  >{bad:g}: {int(neg.sum()):4d}"]
    for key in ("conf_tracker", "conf_diss"):
        c = torch.from_numpy(data[key][1:])
        a = auroc(c[torch.from_numpy(pos)], c[torch.from_numpy(neg)])
        cells.append(f"AUROC {key:12s} {'  n/a' if math.isnan(a) else f'{a:.3f}'}")
    return "  ".join(cells)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    parser.add_argument("--scenarios", default="all", help=f"comma list from {', '.join(SCENARIOS)} (default all)")
    parser.add_argument("--variants", default="standard,no_illum,inject", help=f"comma list from {', '.join(VARIANTS)} (default all three)")
    parser.add_argument("--frames", type=int, help="frames per scenario (default: full length)")
    parser.add_argument("--size", type=frame_size, default=None, help="WxH (default 640x480)")
    parser.add_argument("--cache", default=checkout_out("sequences"),
                        help="sequence cache folder, evaluate.py's (default: out/sequences of this checkout, "
                        "%(default)s, from any working folder; 'none': in memory)")
    parser.add_argument("--good", type=float, default=2.0, help="positives: error below this (deg)")
    parser.add_argument("--bad", type=float, default=5.0, help="negatives: error above this (deg)")
    parser.add_argument("--seed", type=int, default=0,
                        help="seed of the landmark noise (evaluate.py's --seed) and of the injected errors (default 0)")
    parser.add_argument("--save", type=output_file, help="write the per-frame series here (.npz)")
    parser.add_argument("--progress-every", type=integer(0), default=20,
                        help="a progress line on stderr every N frames of a scenario's run (0: none; default 20)")
    add_threads_option(parser)
    args = parser.parse_args(argv)
    # (each once, empty items skipped, as evaluate.py reads its lists: a scenario given twice was tracked twice, a
    # variant given twice had its tables printed twice, and a trailing comma was an "unknown scenario ''")
    names = list(SCENARIOS) if args.scenarios == "all" else comma_items(args.scenarios)
    variants = comma_items(args.variants)
    for v in variants:
        if v not in VARIANTS:
            parser.error(f"unknown variant {v!r}; choose from {', '.join(VARIANTS)}")
    for name in names:
        if name not in SCENARIOS:
            parser.error(f"unknown scenario {name!r}; choose from {', '.join(SCENARIOS)} or all")
    if not variants:
        parser.error(f"--variants: none given; choose from {', '.join(VARIANTS)}")
    if not names:
        parser.error(f"--scenarios: none given; choose from {', '.join(SCENARIOS)} or all")
    if variants == ["no_illum"] and "light_switch" not in names:  # (rendered, then nothing run nor printed: exit 0)
        parser.error("--variants no_illum runs on light_switch only, which --scenarios leaves out")
    if args.frames is not None and args.frames < 2:
        parser.error(f"--frames must be >= 2, got {args.frames}")
    ev.check_size_for_video(parser, args.size, args.cache, names)
    # A frame is a positive below --good and a negative above --bad: with --good above --bad (or NaN) frames in
    # between counted as both and the AUROC compared them with themselves.
    if not (math.isfinite(args.good) and math.isfinite(args.bad) and 0.0 < args.good <= args.bad):
        parser.error(f"--good and --bad must be numbers with 0 < --good <= --bad, got {args.good:g} and {args.bad:g}")
    cache = None if args.cache.lower() == "none" else Path(args.cache)
    if cache is not None and (problem := folder_problem(cache)) is not None:
        parser.error(f"--cache {cache}: {problem}")
    save = args.save
    if save is not None:  # checked before the run, not after it (numpy adds .npz to a name without it)
        save = save if save.suffix == ".npz" else save.with_name(save.name + ".npz")
        if (problem := file_problem(save)) is not None:
            parser.error(f"--save {args.save}: {problem}")
    set_threads(args.threads)
    model = load_candide3()
    base = TrackerConfig(template=TemplateConfig())
    results: dict[str, dict[str, dict[str, np.ndarray]]] = {v: {} for v in variants}
    for name in names:
        w, h, t = scenario_size(name, "full")
        if args.size is not None:
            w, h = args.size
        t = args.frames if args.frames is not None else t
        if variants == ["no_illum"] and name != "light_switch":  # nothing of this scenario's to run
            continue
        seq = ev.load_sequence(name, w, h, t, cache)
        if "standard" in variants or "inject" in variants:
            out = run(name, seq, model, base, args.seed, "inject" in variants, args.progress_every)
            for v, d in out.items():
                if v in variants:
                    results[v][name] = d
                    print(report(f"{v}/{name}", d, args.good, args.bad), flush=True)
        if "no_illum" in variants and name == "light_switch":
            out = run(f"{name} no_illum", seq, model, replace(base, use_illumination=False), args.seed, False,
                      args.progress_every)  # fmt: skip
            results["no_illum"][name] = out["standard"]
            print(report(f"no_illum/{name}", out["standard"], args.good, args.bad), flush=True)
    print()
    for v in variants:
        if not results[v]:
            continue
        pooled = {k: np.concatenate([d[k][1:] for d in results[v].values()]) for k in next(iter(results[v].values()))}
        pooled = {k: np.concatenate([[0.0], x]) for k, x in pooled.items()}  # report() drops element 0
        print(report(f"{v}/POOLED", pooled, args.good, args.bad))
        for name, d in results[v].items():
            print(report(f"{v}/{name}", d, args.good, args.bad))
    if "standard" in results and "no_illum" in results and results["no_illum"]:
        both = [*results["standard"].values(), *results["no_illum"].values()]
        pooled = {k: np.concatenate([[0.0]] + [d[k][1:] for d in both]) for k in both[0]}
        print(report("standard+no_illum/POOLED", pooled, args.good, args.bad))
    if save is not None:
        save.parent.mkdir(parents=True, exist_ok=True)
        flat = {f"{v}/{n}/{k}": x for v, r in results.items() for n, d in r.items() for k, x in d.items()}
        with written_whole(save) as tmp:  # renamed when complete: no half-written file under its name
            np.savez(tmp, **flat)
        print(f"wrote {save}")
    return 0


if __name__ == "__main__":
    run_command(main)
