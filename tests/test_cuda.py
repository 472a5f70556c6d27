"""torchface on a CUDA GPU: the torch code there equals the torch code on the CPU (issue 3, item 4: "any torch device
works").

On a GPU every hot loop runs the torch code (the native kernels are CPU only, :mod:`torchface.backend`), so each
test runs the same thing twice, once on the GPU and once on the CPU with :attr:`Backend.TORCH`, and compares:

- managed tracking of two streams, one clean and one that leaves the frame and comes back (loss, mosaic search,
  recovery), in float64: the same decisions and the same estimates;
- :class:`FaceTracker` with its default settings in float32 on a rendered turn: on track, and close to the CPU;
- the normalised face and its gradient with respect to the frame pixels, and ``NormalisedFaceLayer`` (the training
  use: a layer moved with ``.cuda()``, unrolled iterations, a backward pass);
- ``torchface track --device cuda``: the CSV's poses against the CPU run's;
- CPU frames and landmarks given to a model on the GPU are moved to it, and a batch's CPU confidence and mask to
  a loss on the GPU (``training_hooks.confidence_weighted_loss``);
- the layer inside CUDA's autocast, a ``torch.compile``d network holding the layer, and
  ``torch.use_deterministic_algorithms(True)`` (:mod:`torchface._deterministic`).

All passed on an H200 (session 57, torch 2.11). Session 49 ran the first four there; the others were first run in
session 57, where two tests' expectations were corrected to what CUDA guarantees (see each test).

Skipped without CUDA. ``TORCHFACE_TEST_DEVICE`` names another device to test instead (``cpu`` runs the comparisons
against themselves: a check of the tests' own code on a machine without a GPU).
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from torchface.backend import Backend
from torchface.geometry.camera import Intrinsics
from torchface.geometry.so3 import geodesic_angle_deg
from torchface.model.candide import load_candide3
from torchface.template.management import TemplateConfig
from torchface.tracker import FaceTracker, FitConfig, TrackerConfig, initialise_managed, managed_step

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _helpers import leave_and_return_streams, managed_track  # noqa: E402

DEVICE = os.environ.get("TORCHFACE_TEST_DEVICE", "cuda")
pytestmark = pytest.mark.skipif(
    DEVICE == "cuda" and not torch.cuda.is_available(), reason="needs a CUDA device (TORCHFACE_TEST_DEVICE=cpu "
    "checks these tests' own code)",
)  # fmt: skip

W, H = 320, 240
D = torch.float64
CFG = TrackerConfig(
    num_levels=2, max_points=600, iterations=(6, 4), fit=FitConfig(shape_prior_precision=0.0, held_shape_units=()),
    robust_scale_floor=(0.045, 0.02), template=TemplateConfig(recovery_every=2),
)  # fmt: skip
#: The face moves (0-3), is gone to the right (4-7) and comes back on the left (8-11).
BACK = 8


@pytest.fixture(scope="module")
def streams():
    """Two 12-frame streams ``(2, 12, 3, H, W)``: a gentle turn, and a face that leaves the frame and comes back;
    their first landmarks ``(2, 68, 2)`` and ground truths."""
    return leave_and_return_streams(W, H, 12)


def _finite(res, device):
    for name in ("rotation", "translation", "anim_coeffs", "illumination", "confidence", "cost"):
        value = getattr(res, name)
        assert value.device.type == torch.device(device).type, name
        assert bool(torch.isfinite(value).all()), name


def test_managed_tracking_equals_the_cpu_torch_code(streams):
    """float64, loss and recovery included: the same status, mosaic entry and estimates as the CPU's torch code."""
    frames, lm, (ga, gb) = streams
    config = replace(CFG, backend=Backend.TORCH)
    cpu = managed_track(load_candide3(dtype=D), config, frames, lm)
    dev = managed_track(load_candide3(dtype=D, device=DEVICE), config, frames, lm)
    for i, (c, g) in enumerate(zip(cpu, dev)):
        _finite(g, DEVICE)
        assert torch.equal(c.status, g.status.cpu()), i
        assert torch.equal(c.mosaic_entry, g.mosaic_entry.cpu()), i
        for b in range(2):
            if not bool(c.success[b]) or float(c.confidence[b]) < 0.5:
                continue  # an estimate on the background (the face gone): chaotic, no number to compare
            msg = lambda m: f"stream {b} frame {i}: {m}"  # noqa: E731
            torch.testing.assert_close(g.axis_angle[b].cpu(), c.axis_angle[b], rtol=0, atol=1e-6, msg=msg)
            torch.testing.assert_close(g.translation[b].cpu(), c.translation[b], rtol=0, atol=1e-4, msg=msg)
            torch.testing.assert_close(g.anim_coeffs[b].cpu(), c.anim_coeffs[b], rtol=0, atol=1e-5, msg=msg)
            torch.testing.assert_close(g.illumination[b].cpu(), c.illumination[b], rtol=0, atol=1e-5, msg=msg)
            torch.testing.assert_close(g.confidence[b].cpu(), c.confidence[b], rtol=0, atol=1e-4, msg=msg)
    # the known answers: stream 0 on track, stream 1 lost while the face is gone and found again
    R = torch.stack([r.rotation[0].cpu() for r in dev])
    assert float(geodesic_angle_deg(R @ R[0].mT, ga.rotation @ ga.rotation[0].mT).max()) < 0.5
    assert not all(bool(r.success[1]) for r in dev[4:BACK])
    assert bool(dev[-1].success[1]) and float(dev[-1].confidence[1]) > 0.5


def test_face_tracker_defaults_float32(streams):
    """The default settings (float32, CANDIDE-3) as a module moved with ``.to``: stream 0 on track within 0.5
    degrees, and within 0.05 degrees of the CPU's run (the native kernels there)."""
    frames, lm, (ga, _) = streams
    runs = []
    for device in ("cpu", DEVICE):
        tracker = FaceTracker().to(device)
        results = [tracker.initialise(frames[:1, 0].to(device), lm[:1].to(device))]
        results += [tracker(frames[:1, i].to(device)) for i in range(1, frames.shape[1])]
        for r in results:
            _finite(r, device)
            assert bool(r.success.all())
        runs.append(torch.stack([r.rotation[0].double().cpu() for r in results]))
    cpu, dev = runs
    assert float(geodesic_angle_deg(dev @ dev[0].mT, ga.rotation @ ga.rotation[0].mT).max()) < 0.5
    assert float(geodesic_angle_deg(dev, cpu).max()) < 0.05


def test_cpu_inputs_to_a_model_on_the_device(streams):
    """Frames and landmarks left on the CPU are moved to the model's device: the same estimates."""
    frames, lm, _ = streams
    model = load_candide3(dtype=D, device=DEVICE)
    state_a, a = initialise_managed(model, CFG, frames[:, 0], lm, Intrinsics.default(W, H))
    state_b, b = initialise_managed(model, CFG, frames[:, 0].to(DEVICE), lm.to(DEVICE), Intrinsics.default(W, H))
    torch.testing.assert_close(a.axis_angle, b.axis_angle, rtol=0, atol=1e-9)
    _, a = managed_step(model, CFG, state_a, frames[:, 1])
    _, b = managed_step(model, CFG, state_b, frames[:, 1].to(DEVICE))
    assert a.axis_angle.device.type == torch.device(DEVICE).type
    torch.testing.assert_close(a.axis_angle, b.axis_angle, rtol=0, atol=1e-9)


def test_normalised_face_and_its_gradient_equal_the_cpus(streams):
    """``NormalisedFace`` of a tracked frame on the device: the image equals the CPU's torch code, and its gradient
    w.r.t. the frame pixels too."""
    from torchface.normalise import NormalisedFace

    frames, lm, _ = streams
    out = []
    for device in ("cpu", DEVICE):
        model = load_candide3(dtype=D, device=device)
        config = replace(CFG, backend=Backend.TORCH)
        state, _ = initialise_managed(model, config, frames[:1, 0].to(device), lm[:1].to(device),
                                      Intrinsics.default(W, H))  # fmt: skip
        state, _ = managed_step(model, config, state, frames[:1, 1].to(device))
        frame = frames[:1, 1].to(device=device, dtype=D).requires_grad_()
        image, mask = NormalisedFace(model, size=48)(frame, state)
        weight = torch.linspace(0, 1, image.numel(), dtype=D, device=device).reshape(image.shape)
        (image * weight).sum().backward()
        assert frame.grad is not None and bool(torch.isfinite(frame.grad).all())
        out.append((image.detach().cpu(), mask.cpu(), frame.grad.cpu()))
    (ic, mc, gc), (ig, mg, gg) = out
    assert float(mc.mean()) > 0.3
    torch.testing.assert_close(mg, mc, rtol=0, atol=0)
    torch.testing.assert_close(ig, ic, rtol=0, atol=1e-9)
    torch.testing.assert_close(gg, gc, rtol=0, atol=1e-9)


def test_normalised_face_layer_moved_with_cuda_trains(streams):
    """The training use: ``NormalisedFaceLayer(UNROLLED)`` moved to the device, a backward pass from a small
    network's loss to the frame pixels; the faces and the gradient equal the CPU's (float64, torch code)."""
    from training_hooks.layer import LayerConfig, LayerMode, NormalisedFaceLayer

    frames, lm, _ = streams
    out = []
    for device in ("cpu", DEVICE):
        config = LayerConfig(mode=LayerMode.UNROLLED, size=32, tracker=replace(CFG, backend=Backend.TORCH))
        layer = NormalisedFaceLayer(config).double().to(device)
        state, _ = layer.initialise(frames[:, 0].to(device), lm.to(device))
        frame = frames[:, 1].to(device=device, dtype=D).requires_grad_()
        res = layer(frame, state)
        assert res.image.device.type == torch.device(device).type
        net = torch.nn.Conv2d(3, 2, 3).double().to(device)
        torch.nn.init.constant_(net.weight, 0.01)
        torch.nn.init.zeros_(net.bias)
        net(res.image).square().mean().backward()
        assert frame.grad is not None and bool(torch.isfinite(frame.grad).all()) and float(frame.grad.abs().sum()) > 0
        out.append((res.image.detach().cpu(), frame.grad.cpu()))
    (ic, gc), (ig, gg) = out
    torch.testing.assert_close(ig, ic, rtol=0, atol=1e-8)
    torch.testing.assert_close(gg, gc, rtol=1e-5, atol=1e-8)


def test_track_command_on_the_device(tmp_path):
    """``torchface track --device cuda``: rc 0 and the CSV's poses within 0.1 degrees of the CPU run's."""
    from torchface.cli import main
    from torchface.io import read_track_csv
    from torchface.synth.scenarios import make_scenario
    from torchface.synth.sequence import load_ground_truth, write_sequence

    files = write_sequence(make_scenario("expressions", 12, 160, 120), tmp_path / "clip")
    gt = load_ground_truth(files.ground_truth)
    lm = tmp_path / "first_frame.csv"
    np.savetxt(lm, gt.landmarks_px[0].numpy(), delimiter=",", header="x,y", comments="")
    poses = []
    for device in ("cpu", DEVICE):
        out = tmp_path / device
        rc = main(["track", str(files.video), "--landmarks", str(lm), "--out", str(out), "--device", device,
                   "--quiet"])  # fmt: skip
        assert rc == 0
        cols, rows = read_track_csv(out / f"{files.video.stem}.csv")
        R = rows[:, [cols.index(f"r{i}{j}") for i in range(3) for j in range(3)]]
        poses.append(torch.from_numpy(R).reshape(-1, 3, 3).double())
    assert poses[0].shape == poses[1].shape and poses[0].shape[0] == 12
    assert float(geodesic_angle_deg(poses[1], poses[0]).max()) < 0.1


def _amp_dtype() -> torch.dtype:
    return torch.float16 if torch.device(DEVICE).type == "cuda" else torch.bfloat16


@contextlib.contextmanager
def _deterministic_algorithms() -> Iterator[None]:
    previous = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(previous)


def _check_cublas_config() -> None:
    """cuBLAS's condition for deterministic products, set from the process's start (tests/conftest.py sets it where
    the environment does not): torch sizes a stream's cuBLAS workspace at its first product and keeps it, so a test
    that set it itself came too late once an earlier test's products had run."""
    value = os.environ.get("CUBLAS_WORKSPACE_CONFIG")
    if torch.device(DEVICE).type == "cuda" and value not in (":4096:8", ":16:8"):
        pytest.fail(f"CUBLAS_WORKSPACE_CONFIG={value!r}: deterministic cuBLAS products need :4096:8 or :16:8 from the "
                    "process's start (tests/conftest.py sets :4096:8 unless the environment sets it)")  # fmt: skip


def test_layer_inside_the_devices_autocast_equals_full_precision(streams):
    """A training step's ``torch.autocast`` on the device (float16 on CUDA): the float32 layer tracks, unrolls and
    resamples in float32, bit-identical to the run outside it, while the caller's own products still autocast.

    Both runs use deterministic algorithms: without them two plain runs on CUDA differ in the last bits (session 57,
    H200: atomic sums such as ``index_add``'s come in no fixed order; the parameters of two runs up to 3e-5 apart),
    and bit identity would say nothing."""
    from training_hooks.layer import LayerConfig, LayerMode, NormalisedFaceLayer

    frames, lm, _ = streams
    frames, lm = frames.to(DEVICE), lm.to(DEVICE)
    device_type = torch.device(DEVICE).type
    _check_cublas_config()
    for mode in (LayerMode.DETACHED, LayerMode.UNROLLED):
        with _deterministic_algorithms():
            layer = NormalisedFaceLayer(LayerConfig(mode=mode, size=32, tracker=CFG)).to(DEVICE)
            state, _ = layer.initialise(frames[:, 0], lm)
            ref = layer(frames[:, 1], state)
            with torch.autocast(device_type, dtype=_amp_dtype()):
                state_amp, _ = layer.initialise(frames[:, 0], lm)
                out = layer(frames[:, 1], state_amp)
                ones = torch.ones(32 * 32 * 3, 1, device=DEVICE)
                assert (out.image.flatten(1) @ ones).dtype == _amp_dtype()
            assert torch.equal(state_amp.params, state.params), mode
        assert torch.equal(out.params, ref.params) and torch.equal(out.image, ref.image), mode


def test_a_compiled_network_holding_the_layer(streams):
    """``torch.compile`` (its default backend: Triton kernels on CUDA) of a network that holds the layer: the tracking
    runs eagerly inside it (a graph break), the rest compiled; the faces, the network's output and the gradient
    w.r.t. the frame pixels equal the eager network's to float32 rounding."""
    from training_hooks.layer import LayerConfig, LayerMode, NormalisedFaceLayer

    frames, lm, _ = streams

    class Net(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.layer = NormalisedFaceLayer(LayerConfig(mode=LayerMode.UNROLLED, size=32, tracker=CFG))
            self.head = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 3), torch.nn.ReLU(), torch.nn.Flatten(),
                                            torch.nn.LazyLinear(2))  # fmt: skip

        def forward(self, frame, state):
            out = self.layer(frame, state)
            return out.image, self.head(out.image)

    torch.manual_seed(0)
    net = Net().to(DEVICE)
    state, _ = net.layer.initialise(frames[:, 0].to(DEVICE), lm.to(DEVICE))
    net(frames[:, 1].to(DEVICE), state)  # the lazy layer's shape
    outs = []
    for run in (net, torch.compile(net)):
        frame = frames[:, 1].to(DEVICE).clone().requires_grad_(True)
        image, logits = run(frame, state)
        logits.square().sum().backward()
        outs.append((image.detach(), logits.detach(), frame.grad))
    (ie, le, ge), (ic, lc, gc) = outs
    assert bool(torch.isfinite(gc).all()) and float(ge.abs().sum()) > 0
    torch.testing.assert_close(ic, ie, rtol=0, atol=1e-5)
    torch.testing.assert_close(lc, le, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(gc, ge, rtol=1e-3, atol=1e-6)


def test_deterministic_algorithms_on_the_device(streams):
    """``torch.use_deterministic_algorithms(True)`` (a reproducible training run): torch's CUDA ``nanmedian`` and the
    image backward of ``grid_sample`` and of the reflected pad raise there, so the tracker could not track a frame
    nor the layer train; torchface._deterministic's substitutes run instead. Two runs are bit-identical, and equal
    the run without the mode to float32 rounding."""
    from training_hooks.layer import LayerConfig, LayerMode, NormalisedFaceLayer

    frames, lm, _ = streams
    _check_cublas_config()

    def run():
        torch.manual_seed(0)
        results = managed_track(load_candide3(device=DEVICE), CFG, frames, lm)
        layer = NormalisedFaceLayer(LayerConfig(mode=LayerMode.UNROLLED, size=32, tracker=CFG)).to(DEVICE)
        state, _ = layer.initialise(frames[:, 0].to(DEVICE), lm.to(DEVICE))
        frame = frames[:, 1].to(DEVICE).requires_grad_()
        out = layer(frame, state)
        out.image.square().sum().backward()
        poses = torch.stack([r.axis_angle for r in results]).cpu()
        return poses, torch.stack([r.status for r in results]).cpu(), out.image.detach().cpu(), frame.grad.cpu()

    free = run()
    previous = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(True)
    try:
        first, second = run(), run()
    finally:
        torch.use_deterministic_algorithms(previous)
    for a, b in zip(first, second):
        assert torch.equal(a, b)
    assert torch.equal(first[1], free[1])
    torch.testing.assert_close(first[0], free[0], rtol=0, atol=1e-4)
    torch.testing.assert_close(first[2], free[2], rtol=0, atol=1e-4)
    # The frame's gradient through the unrolled iterations: without the mode the atomic adds sum in another order, the
    # pose moves by float rounding, and a sample near a pixel's edge can cross it, so a few pixels differ by more than
    # rounding, the whole not. Session 57, H200, two runs (the free run differs from run to run): 5 of 460800 pixels
    # at most 2.8e-5 apart against a largest gradient of about 1.7, the difference's norm 2e-6 of the gradient's; then
    # 1.4e-5 of it (4.9e-4 against 34.5). A wrong sample (a corner's weight, a pixel off) moves it by its own size.
    diff = first[3] - free[3]
    assert float(diff.norm()) <= 1e-4 * float(free[3].norm())
    assert float(diff.abs().max()) <= 1e-3 * float(free[3].abs().max())


def test_confidence_weighted_loss_takes_a_cpu_confidence_to_the_loss_device():
    """A training loop that moves its images alone to the GPU hands ``confidence_weighted_loss`` a loss there and the
    batch's confidence and mask on the CPU: the weights go to the loss's device (it was torch's device error)."""
    from training_hooks import confidence_weighted_loss

    loss = torch.tensor([1.0, 3.0, 5.0], device=DEVICE, requires_grad=True)
    out = confidence_weighted_loss(loss, torch.tensor([0.75, 0.25, 1.0]), torch.tensor([True, True, False]))
    assert out.device == loss.device and abs(float(out) - 1.5) < 1e-6
    out.backward()
    assert loss.grad is not None and loss.grad.device == loss.device
