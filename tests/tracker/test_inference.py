"""Tests of torchface.tracker.inference: the tracking steps run in inference mode and hand back normal tensors
(nothing the caller gets is an inference tensor, unchanged parts of the state are the same objects), give the
same numbers as outside it, and leave inference mode alone where a gradient is wanted."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import NamedTuple

import pytest
import torch

from torchface._compiling import transforms_read_values
from torchface.geometry.camera import Intrinsics
from torchface.model.candide import load_candide3
from torchface.normalise import build_normalised_layout, normalised_face
from torchface.synth.sequence import render_sequence
from torchface.tracker import ParamLayout, initialise, initialise_managed, managed_step, track_step
from torchface.tracker.inference import normal_tensors, run_without_autograd

# The small-sequence settings and renderer of the template management tests (this folder on sys.path, whatever
# pytest's import mode).
sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_managed import CFG, H, W, spec_of  # noqa: E402


# ----------------------------------------------------------------------------- normal_tensors


@dataclasses.dataclass(frozen=True)
class _Box:
    a: torch.Tensor
    b: torch.Tensor
    rest: tuple
    posts = [0]

    def __post_init__(self) -> None:
        _Box.posts[0] += 1


class _Pair(NamedTuple):
    x: torch.Tensor
    y: object


def test_normal_tensors_copies_only_inference_tensors_and_keeps_the_rest():
    kept = torch.arange(3.0)
    untouched = _Box(kept, kept, ("label", 2, None))
    with torch.inference_mode():
        new = torch.ones(2) * 2
    tree = {"box": _Box(new, new, (_Pair(new, kept), [kept, new])), "old": untouched, "n": 1}
    posts = _Box.posts[0]
    out = normal_tensors(tree)
    assert _Box.posts[0] == posts  # copies do not run __init__ / __post_init__ again
    assert out["old"] is untouched and out["n"] == 1  # nothing to copy: the same objects
    box = out["box"]
    assert not box.a.is_inference() and torch.equal(box.a, new)
    assert box.a is box.b and box.rest[0].x is box.a and box.rest[1][1] is box.a  # one copy per tensor
    assert isinstance(box.rest[0], _Pair) and box.rest[0].y is kept and box.rest[1][0] is kept
    box.a.add_(1)  # a normal tensor: in-place outside inference mode is allowed
    assert normal_tensors(untouched) is untouched


def test_run_without_autograd_modes():
    def probe(x):
        return torch.is_inference_mode_enabled(), x * 2

    x = torch.ones(3)
    inside, y = run_without_autograd(probe, (x,), x)
    assert inside and not y.is_inference()
    xg = torch.ones(3, requires_grad=True)
    inside, y = run_without_autograd(probe, (xg,), xg)
    assert not inside and y.requires_grad  # a gradient is wanted: autograd stays
    with torch.no_grad():
        assert run_without_autograd(probe, (xg,), xg)[0]
    with torch.inference_mode():  # a caller's inference mode: run as it is, no copy
        inside, y = run_without_autograd(probe, (x,), x)
    assert inside and y.is_inference()
    # Forward AD's and torch.func's tensors ask for no gradient, but inference mode would drop their tangents.
    with torch.autograd.forward_ad.dual_level():
        dual = torch.autograd.forward_ad.make_dual(x, torch.ones(3))
        inside, y = run_without_autograd(probe, (dual,), dual)
        assert not inside and torch.equal(torch.autograd.forward_ad.unpack_dual(y).tangent, torch.full((3,), 2.0))
    seen = []
    torch.func.jvp(lambda v: seen.append(run_without_autograd(probe, (v,), v)[0]) or v.sum(), (x,), (x,))
    assert seen == [False]


# ----------------------------------------------------------------------------- the tracking steps


@pytest.fixture(scope="module")
def model():
    return load_candide3()


@pytest.fixture(scope="module")
def turn():
    """Yaw 0 -> 27 degrees in 3 degree steps: template management adds a mosaic entry on the way."""
    yaw = [3.0 * i for i in range(10)]
    spec = spec_of("turn", [[y, 0.0, 0.0] for y in yaw], [[0.0, 0.0, 450.0]] * len(yaw))
    frames, gt = render_sequence(spec)
    return frames[None], gt.landmarks_px[:1].float()


def _tensors(tree) -> list[torch.Tensor]:
    found = []

    def walk(x):
        if isinstance(x, torch.Tensor):
            found.append(x)
        elif dataclasses.is_dataclass(x) and not isinstance(x, type):
            for f in dataclasses.fields(x):
                walk(getattr(x, f.name))
        elif isinstance(x, (tuple, list)):
            for v in x:
                walk(v)
        elif isinstance(x, dict):
            for v in x.values():
                walk(v)

    walk(tree)
    return found


def test_managed_step_hands_back_normal_tensors_equal_to_an_outer_inference_mode(model, turn):
    frames, lm = turn
    state, _ = initialise_managed(model, CFG, frames[:, 0], lm, Intrinsics.default(W, H))
    outer = state
    for i in range(1, frames.shape[1]):
        templates = state.templates
        state, res = managed_step(model, CFG, state, frames[:, i])
        with torch.inference_mode():
            outer, res_outer = managed_step(model, CFG, outer, frames[:, i])
        assert not any(t.is_inference() for t in _tensors((state, res))), f"frame {i}"
        if int(res.mosaic_entry[0]) == 0:
            assert state.templates is templates  # unchanged: the same objects, not copies
        for name in ("rotation", "translation", "anim_coeffs", "illumination", "confidence", "status"):
            assert torch.equal(getattr(res, name), getattr(res_outer, name)), (i, name)
        res.rotation.mul_(1.0)  # a caller may modify what it gets in place
    assert int(state.management.mosaic.num_entries[0]) > 1  # an entry was added (made in inference mode) on the way


def test_track_step_results_serve_a_differentiable_normalised_face(model, turn):
    """Parameters from a step (made in inference mode) go into a normalised face whose gradient reaches the
    frame's pixels: autograd would refuse to save an inference tensor."""
    frames, lm = turn
    state, _ = initialise(model, CFG, frames[:, 0], lm, Intrinsics.default(W, H))
    state, _ = track_step(model, CFG, state, frames[:, 1])
    aa, t, alpha, light = ParamLayout(model.num_animation, 5).split(state.params)
    layout = build_normalised_layout(model, 32, 0.1)
    pixels = frames[:, 1].clone().requires_grad_(True)
    face = normalised_face(pixels, model, layout, state.shape_coeffs, alpha, aa, t, light, state.intrinsics)
    face.image.sum().backward()
    assert pixels.grad is not None and float(pixels.grad.abs().sum()) > 0


def _record_inference_mode(monkeypatch, module, name: str) -> list[bool]:
    """Wrap ``module.name`` so that each call appends whether inference mode was on; returns that list."""
    seen: list[bool] = []
    real = getattr(module, name)
    monkeypatch.setattr(module, name, lambda *a, **k: seen.append(torch.is_inference_mode_enabled()) or real(*a, **k))
    return seen


def test_track_step_keeps_autograd_when_the_frames_require_grad(model, turn, monkeypatch):
    import torchface.tracker.step as step_module

    frames, lm = turn
    state, _ = initialise(model, CFG, frames[:, 0], lm, Intrinsics.default(W, H))
    seen = _record_inference_mode(monkeypatch, step_module, "_track_step_fast")
    track_step(model, CFG, state, frames[:, 1])
    frame = frames[:, 1].clone().requires_grad_(True)
    _, result = track_step(model, CFG, state, frame)
    assert seen == [True, False]
    # The gradient of the unrolled solve reaches the frame (the solver's step was negated in place, which
    # autograd refuses for cholesky_solve's output).
    (grad,) = torch.autograd.grad(result.translation.sum(), frame)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0


@pytest.mark.parametrize("managed", [False, True])
def test_torch_func_grad_and_jacrev_of_a_step_equal_autograd(model, turn, managed):
    """``torch.func.grad`` / ``jacrev`` through a step with the default backend give autograd's gradients. Before,
    the step handed the transform's wrapped frames (detached, so asking for no gradient) to the native rasterizer:
    "Cannot access data pointer of Tensor that doesn't have storage". On a torch before 2.10 the transforms are
    refused with one line (torchface._compiling.transforms_read_values)."""
    frames, lm = turn
    init, step = (initialise_managed, managed_step) if managed else (initialise, track_step)
    state, _ = init(model, CFG, frames[:, 0], lm, Intrinsics.default(W, H))
    frame = frames[:, 1].clone()

    def translation(x):
        return step(model, CFG, state, x)[1].translation[0]

    pixels = frame.clone().requires_grad_(True)
    (want,) = torch.autograd.grad(translation(pixels).sum(), pixels)
    if not transforms_read_values():  # (torch < 2.10 cannot read a transform's values as a step does: refused)
        with pytest.raises(RuntimeError, match=r"^a tracking step cannot run under a torch.func transform on this"):
            torch.func.grad(lambda x: translation(x).sum())(frame)
        return
    got = torch.func.grad(lambda x: translation(x).sum())(frame)
    assert want.abs().sum() > 0
    torch.testing.assert_close(got, want, rtol=0, atol=1e-6)
    jac = torch.func.jacrev(translation)(frame)  # (3, 1, 3, H, W)
    torch.testing.assert_close(jac.sum(0), want, rtol=0, atol=1e-5)


@pytest.mark.parametrize("managed", [False, True])
def test_forward_mode_and_vmap_of_a_step_are_refused_in_one_line(model, turn, managed):
    """A step has no forward-mode derivative (torch's ``grid_sample`` has none) and cannot be vmapped (its decisions
    read each stream's values): both are refused with what works instead. Before, forward AD's dual frames ran in
    inference mode and the results came back without a tangent (a zero derivative without a sign), and
    ``torch.func.jvp`` failed on "Cannot set version_counter for inference tensor"."""
    frames, lm = turn
    init, step = (initialise_managed, managed_step) if managed else (initialise, track_step)
    state, _ = init(model, CFG, frames[:, 0], lm, Intrinsics.default(W, H))
    frame = frames[:, 1].clone()

    def moved(x):
        return step(model, CFG, state, x)[1].translation.sum()

    with torch.autograd.forward_ad.dual_level():
        with pytest.raises(RuntimeError, match="no forward-mode derivative.*use reverse mode"):
            moved(torch.autograd.forward_ad.make_dual(frame, torch.ones_like(frame)))
    with pytest.raises(RuntimeError, match="no forward-mode derivative"):
        torch.func.jvp(moved, (frame,), (torch.ones_like(frame),))
    with pytest.raises(RuntimeError, match="cannot run under torch.func.vmap.*one batch"):
        torch.func.vmap(moved)(frame[None])
    with pytest.raises(RuntimeError, match="cannot run under torch.func.vmap"):
        torch.func.vmap(torch.func.grad(moved))(frame[None])
    step(model, CFG, state, frame)  # and a plain step after them runs


@pytest.mark.parametrize("managed, solver", [(False, "fast"), (True, "fast"), (False, "reference")])
def test_missing_frame_pixels_give_finite_gradients_that_equal_finite_differences(turn, managed, solver):
    """Frames that require grad with missing (NaN) pixels on the face: the points whose samples touch them are left
    out as without gradients (the same estimate), and the gradient is finite, 0 at the missing pixels and equal to
    central differences (float64). Before, the fast solver's sampler multiplied those points' zero gradient by the
    NaN pixels in its backward: every pixel's gradient was NaN (690 of 696 on a 32x32 frame with half its columns
    missing). The reference solver failed the frame at the first point that sampled a NaN pixel (the fast solver
    leaves such points out), and its estimates carried no gradient at all."""
    from torchface.backend import Backend
    from torchface.tracker.step import TrackSolver

    frames, lm = turn
    model = load_candide3(dtype=torch.float64)
    cam = Intrinsics.default(W, H)
    init, step = (initialise_managed, managed_step) if managed else (initialise, track_step)
    CFG = dataclasses.replace(globals()["CFG"], solver=TrackSolver(solver))
    state, _ = init(model, CFG, frames[:, 0].double(), lm.double(), cam)
    frame = frames[:, 1].double().clone()
    frame[..., 165:] = float("nan")  # the right part of the face (columns 120-200) is missing
    _, want = step(model, dataclasses.replace(CFG, backend=Backend.TORCH), state, frame)
    pixels = frame.clone().requires_grad_(True)
    _, got = step(model, CFG, state, pixels)
    assert int(got.status[0]) == int(want.status[0]) in (0, 1)  # converged, or at its iteration limit: not FAILED
    torch.testing.assert_close(got.translation, want.translation, rtol=0, atol=1e-9)
    (grad,) = torch.autograd.grad(got.translation[0, 0], pixels)
    assert torch.isfinite(grad).all() and bool((grad[..., 165:] == 0).all())
    assert int((grad != 0).sum()) > 1000
    for i in grad.flatten().abs().topk(3).indices:  # the pixels that move the estimate most
        e = torch.zeros_like(frame).flatten().index_fill_(0, i, 1e-5).view_as(frame)
        plus, minus = (step(model, CFG, state, frame + s * e)[1].translation[0, 0] for s in (1, -1))
        torch.testing.assert_close(grad.flatten()[i], (plus - minus) / 2e-5, rtol=1e-5, atol=1e-8)


def test_the_reference_solver_carries_gradients_like_the_fast_one(model, turn):
    """``TrackSolver.REFERENCE`` with frames that require grad: its estimates are in the graph (the solve unrolled),
    equal to those without gradients. Before, its solve ran under ``no_grad`` whatever the caller wanted: the
    estimates were constants and ``autograd.grad`` of them raised "does not require grad"."""
    from torchface.tracker.step import TrackSolver

    frames, lm = turn
    cfg = dataclasses.replace(CFG, solver=TrackSolver.REFERENCE)
    state, _ = initialise(model, cfg, frames[:, 0], lm, Intrinsics.default(W, H))
    _, want = track_step(model, cfg, state, frames[:, 1])
    frame = frames[:, 1].clone().requires_grad_(True)
    new_state, got = track_step(model, cfg, state, frame)
    assert torch.equal(got.translation, want.translation) and torch.equal(got.status, want.status)
    assert got.translation.requires_grad and new_state.params.requires_grad
    (grad,) = torch.autograd.grad(got.translation.sum(), frame)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0


@pytest.mark.parametrize("managed", [False, True])
def test_a_state_made_in_a_callers_inference_mode_serves_frames_that_require_grad(model, turn, managed):
    """A state initialised and stepped inside the caller's ``torch.inference_mode`` (a validation pass) holds
    inference tensors; a later step of frames that require grad from it gives the gradient, and the estimate of the
    same frames without grad. Before: "Inference tensors cannot be saved for backward" from the fast solver."""
    frames, lm = turn
    init, step = (initialise_managed, managed_step) if managed else (initialise, track_step)
    with torch.inference_mode():
        state, _ = init(model, CFG, frames[:, 0], lm, Intrinsics.default(W, H))
        state, _ = step(model, CFG, state, frames[:, 1])
    assert state.params.is_inference() and state.templates[0].intensity.is_inference()
    frame = frames[:, 2].clone().requires_grad_(True)
    new_state, got = step(model, CFG, state, frame)  # (first: a step without grad would cache normal tensors)
    _, want = step(model, CFG, state, frames[:, 2])
    # (the torch solver, which gives the gradient, and the native one agree to float32's rounding: 3e-5 mm is one
    # unit in the last place of a depth of 450 mm)
    torch.testing.assert_close(got.translation, want.translation, rtol=0, atol=1e-4)
    (grad,) = torch.autograd.grad(got.translation.sum(), frame)
    assert torch.isfinite(grad).all() and grad.abs().sum() > 0
    step(model, CFG, new_state.detach(), frames[:, 3].clone().requires_grad_(True))  # and on from there


def test_a_step_after_initialise_from_first_frames_that_require_grad_carries_their_gradient(model, turn):
    """The templates ``initialise`` makes from first frames that require grad carry their graph; the next step of a
    frame that asks for none went into inference mode (only the frames and the state's parameters were looked at)
    and its estimates held no gradient: "element 0 of tensors does not require grad". Now it gives the gradient
    w.r.t. the first frame, the torch code's."""
    from torchface.backend import Backend

    frames, lm = turn
    grads = []
    for cfg in (CFG, dataclasses.replace(CFG, backend=Backend.TORCH)):
        first = frames[:, 0].clone().requires_grad_(True)
        state, _ = initialise(model, cfg, first, lm, Intrinsics.default(W, H))
        assert state.templates[0].intensity.requires_grad
        _, result = track_step(model, cfg, state, frames[:, 1])
        grads.append(torch.autograd.grad(result.translation.sum(), first)[0])
    assert torch.isfinite(grads[0]).all() and grads[0].abs().sum() > 0
    torch.testing.assert_close(grads[0], grads[1], rtol=0, atol=1e-4)


def test_a_graph_carried_over_two_steps_of_more_than_eight_streams_back_propagates(model, turn):
    """A state whose parameters carry a graph (the recurrent use docs/python-api.md describes), more than
    ``_PYRAMID_CHUNK`` (8) streams: the steps built their pyramids in the state's shared workspace, so the second
    step wrote over the levels the first one's backward reads: "one of the variables needed for gradient
    computation has been modified by an inplace operation". Each of 9 identical streams now gets the same gradient,
    the one-stream gradient to float32's rounding through two solves (0.5% of its largest entry)."""
    frames, lm = turn
    cam = Intrinsics.default(W, H)
    grads = []
    for B in (1, 9):
        state, _ = initialise(model, CFG, frames[:, 0].expand(B, -1, -1, -1), lm.expand(B, -1, -1), cam)
        start = state.params.clone().requires_grad_(True)
        state = dataclasses.replace(state, params=start)
        state, first = track_step(model, CFG, state, frames[:, 1].expand(B, -1, -1, -1))
        state, second = track_step(model, CFG, state, frames[:, 2].expand(B, -1, -1, -1))
        grads.append(torch.autograd.grad(first.translation.sum() + second.translation.sum(), start)[0])
    assert torch.isfinite(grads[0]).all() and grads[0].abs().sum() > 0
    torch.testing.assert_close(grads[1], grads[1][:1].expand(9, -1), rtol=0, atol=1e-5)
    torch.testing.assert_close(grads[1][:1], grads[0], rtol=0, atol=0.01 * float(grads[0].abs().max()))


def test_managed_step_runs_in_inference_mode(model, turn, monkeypatch):
    """managed_step, like track_step, runs its work in inference mode when the state and frames ask for no
    gradient (``without_autograd``), and the caller's mode is as it was afterwards."""
    import torchface.tracker.managed as managed_module

    frames, lm = turn
    state, _ = initialise_managed(model, CFG, frames[:, 0], lm, Intrinsics.default(W, H))
    seen = _record_inference_mode(monkeypatch, managed_module, "_confidence")
    managed_step(model, CFG, state, frames[:, 1])
    assert seen == [True] and not torch.is_inference_mode_enabled(), seen


def test_managed_step_tracks_frames_that_require_grad(model, turn):
    """Frames that require grad (a caller's differentiable preprocessing upstream) run through the whole turn,
    mosaic entries added on the way: the estimates equal those of the same frames without grad and carry
    gradients to the frames, and what template management keeps (mosaic, confident parameters, templates) holds
    no graph. Before, the dissimilarity's Lucas-Kanade failed on an ``out=`` argument under autograd."""
    from torchface.backend import Backend

    frames, lm = turn
    cam = Intrinsics.default(W, H)
    cfg = dataclasses.replace(CFG, backend=Backend.TORCH)  # the native kernels run only where no gradient is asked
    plain, _ = initialise_managed(model, cfg, frames[:, 0], lm, cam)
    graded, _ = initialise_managed(model, cfg, frames[:, 0], lm, cam)
    for i in range(1, frames.shape[1]):
        plain, want = managed_step(model, cfg, plain, frames[:, i])
        frame = frames[:, i].clone().requires_grad_(True)
        graded, got = managed_step(model, cfg, graded, frame)
        torch.testing.assert_close(got.rotation, want.rotation, rtol=0, atol=1e-5)
        torch.testing.assert_close(got.confidence, want.confidence, rtol=0, atol=1e-4)
        assert torch.equal(got.status, want.status) and torch.equal(got.mosaic_entry, want.mosaic_entry)
        assert got.translation.requires_grad and not got.confidence.requires_grad
        (grad,) = torch.autograd.grad(got.translation.sum() + got.expression.sum(), frame)
        assert torch.isfinite(grad).all() and grad.abs().sum() > 0
        kept = graded.management
        assert not any(t.requires_grad for t in _tensors((kept.mosaic, kept.confident_params, graded.templates)))
    assert int(graded.management.mosaic.num_entries[0]) >= 2  # entries were added from the detached frames


@pytest.mark.parametrize("managed", [False, True])
def test_a_detached_state_lets_each_frame_back_propagate_alone(model, turn, managed):
    """``TrackerState.detach()`` between frames that require grad: each frame's ``backward()`` works and gives
    the gradient to that frame of the state carrying the graph on. Without it the graph ran from frame to frame
    through the state's parameters (and, after ``initialise`` from first frames that require grad, its
    templates): the second frame's ``backward()`` raised "Trying to backward through the graph a second time"."""
    from torchface.backend import Backend

    frames, lm = turn
    cam = Intrinsics.default(W, H)
    cfg = dataclasses.replace(CFG, backend=Backend.TORCH)
    init, step = (initialise_managed, managed_step) if managed else (initialise, track_step)
    first = frames[:, 0].clone().requires_grad_(True)
    state, _ = init(model, cfg, first, lm, cam)
    chained, _ = init(model, cfg, first, lm, cam)
    for i in range(1, 4):
        frame = frames[:, i].clone().requires_grad_(True)
        state, got = step(model, cfg, state, frame)
        got.translation.sum().backward()
        frame_ = frames[:, i].clone().requires_grad_(True)
        chained, want = step(model, cfg, chained, frame_)
        (grad,) = torch.autograd.grad(want.translation.sum(), frame_)
        torch.testing.assert_close(got.translation, want.translation, rtol=0, atol=0)
        torch.testing.assert_close(frame.grad, grad)
        state = state.detach()
        assert not any(t.requires_grad for t in _tensors((state.params, state.shape_coeffs, state.templates)))
    assert chained.params.requires_grad  # the state that was not detached carries the graph on
    same = state.detach()
    assert same.templates is state.templates  # nothing to detach: the same templates (and visibility masks)


def test_state_pieces_made_in_inference_mode_are_normal_tensors(model, turn):
    """The mosaic with a new entry and the templates of a switched entry persist in the state: made in a step's
    inference mode they are normal tensors already, so handing the state back copies none of them."""
    from torchface.template.management import add_entries
    from torchface.tracker.managed import _scatter_templates

    frames, lm = turn
    state, first = initialise_managed(model, CFG, frames[:, 0], lm, Intrinsics.default(W, H))
    ms = state.management
    streams = torch.zeros(1, dtype=torch.int64)
    with torch.inference_mode():
        mosaic, slot = add_entries(ms.mosaic, streams, state.templates, first.rotation, torch.zeros(1, 2, dtype=torch.int64),
                                   ms.mosaic.references.select(streams))  # fmt: skip
        templates = _scatter_templates(state.templates, streams, tuple(t.select(streams) for t in state.templates))
    assert int(slot[0]) == 1 and int(mosaic.num_entries[0]) == 2
    assert not any(t.is_inference() for t in _tensors((mosaic, templates)))
    out = normal_tensors((mosaic, templates))
    assert out[0] is mosaic and out[1] is templates  # nothing to copy


def _storages(tree) -> set[int]:
    return {t.untyped_storage().data_ptr() for t in _tensors(tree) if t.numel()}


@pytest.mark.parametrize("mode", ["default", "inference_mode", "grad"])
def test_results_share_no_memory_with_the_state(model, turn, mode):
    """docs/python-api.md: what the steps hand back is "modifiable in place". No tensor of a result may share memory
    with the state the next step starts from (the results' pose, expression and light were views of the state's
    ``params``, ``managed_step``'s ``ypr_deg`` the state's ``params_ypr``, ``initialise_managed``'s ``rotation``
    the mosaic's first entry's: ``result.translation += offset`` moved the tracked head), whether the step runs in
    its own inference mode, in the caller's, or with autograd (frames that require grad)."""
    frames, lm = turn
    f0, f1 = frames[:, 0].clone(), frames[:, 1].clone()
    if mode == "grad":
        f0.requires_grad_(True), f1.requires_grad_(True)
    with torch.inference_mode(mode == "inference_mode"):
        for start, step in ((initialise, track_step), (initialise_managed, managed_step)):
            state, first = start(model, CFG, f0, lm, Intrinsics.default(W, H))
            assert not _storages(first) & _storages(state), (start.__name__, mode)
            state, res = step(model, CFG, state, f1)
            assert not _storages(res) & _storages(state), (step.__name__, mode)


def test_face_tracker_results_modified_in_place_leave_the_tracking_alone(model, turn):
    """A caller shifting the results it gets in place (``result.translation += offset``, a unit change of
    ``ypr_deg``) changes nothing the tracker does next: its first result's pose and light were its state's
    parameters, a step's ``ypr_deg`` the yaw/pitch/roll the next step's template choice starts from."""
    from torchface.tracker import FaceTracker

    frames, lm = turn
    T = 4

    def track(scribble: bool) -> list[torch.Tensor]:
        tracker, out = FaceTracker(CFG, model=model, refine_first=None), []
        res = tracker.initialise(frames[:, 0], lm)
        for t in range(1, T + 1):
            out.append(torch.cat([res.axis_angle, res.translation, res.ypr_deg, res.anim_coeffs, res.illumination], -1))
            if scribble:
                for name in ("rotation", "axis_angle", "translation", "ypr_deg", "anim_coeffs", "illumination"):
                    getattr(res, name).add_(10.0)
            if t < T:
                res = tracker(frames[:, t])
        return out

    clean = [x.clone() for x in track(False)]
    for t, (got, want) in enumerate(zip(track(True), clean)):
        assert torch.equal(got, want), f"frame {t}"
