"""Tests for torchface.tracker.fast (the default per-frame solver): its local-twist Jacobian against autograd,
its residuals against the reference objective (:func:`frame_residuals`) on a crop, the exponential map, and
known answers of :func:`solve_level` (exact recovery, robust rejection of corrupted points), each for both of its
backends (the torch code and the native solver; tests/tracker/test_native.py compares the two directly)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

from torchface.appearance import image_with_gradients
from torchface.geometry.so3 import axis_angle_to_matrix, geodesic_angle_deg, matrix_to_axis_angle
from torchface.solver.robust import RobustKind, RobustLoss
from torchface.template import Template
from torchface.tracker import frame_residuals
from torchface import _native
from torchface.backend import Backend
from torchface.tracker.fast import (
    BOUND_MARGIN,
    FUNCTION_TOLERANCE,
    STEP_TOLERANCE,
    LevelCamera,
    linearise,
    solve_level,
)

# The synthetic template, images and parameters of the objective tests (this folder on sys.path, whatever
# pytest's import mode).
sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_objective import (  # noqa: E402
    A,
    CAM,
    GROUPS,
    LAYOUT,
    _autograd_jacobian,
    _light_basis,
    bilinear_image,
    make_template,
    params,
    rotation_reference,
    smooth_image,
)

D = torch.float64

requires_native = pytest.mark.skipif(
    _native.library() is None, reason=f"native solver unavailable: {_native.unavailable_reason()}"
)
BACKENDS = [Backend.TORCH, pytest.param(Backend.NATIVE, marks=requires_native)]


@pytest.fixture(params=BACKENDS, ids=lambda b: b.value)
def backend(request):
    """Each :func:`solve_level` test runs with the torch code and with the native solver."""
    return request.param


def gray(image: torch.Tensor) -> torch.Tensor:
    """The intensity channel of the objective tests' ``(B, 3, H, W)`` images: the fast solver takes the gray image
    and finds the gradients itself, by sampling either side of each point."""
    return image[:, :1].contiguous()


def full_camera(B: int = 2, offset: tuple[int, int] = (0, 0)) -> LevelCamera:
    off = torch.tensor([offset], dtype=D).expand(B, 2)
    return LevelCamera(CAM.fx, CAM.fy, CAM.cx, CAM.cy, off, CAM.height - offset[1], CAM.width - offset[0])


def split(x: torch.Tensor):
    return axis_angle_to_matrix(x[:, 0:3]), x[:, 3:6], x[:, LAYOUT.animation], x[:, LAYOUT.illumination]


@pytest.mark.parametrize("kind", ["zero", "nonzero"])
def test_local_twist_jacobian_equals_autograd(kind):
    """Columns of ``linearise`` are the derivatives for the increment that turns the head about its origin,
    ``R <- exp(d_omega) R``, ``t <- t + d_t``, ``alpha += d_alpha``, ``lambda += d_lambda`` (exact with the
    bilinear image: its central differences are its derivatives)."""
    tpl, x, image = make_template(), params(kind), gray(bilinear_image())
    light_basis = _light_basis(tpl, params("nonzero"))
    R0, t0, a0, l0 = split(x)
    cam = full_camera()
    r, J, valid, _ = linearise(tpl, image, cam, R0, t0, a0, l0, light_basis, tpl.valid)
    assert bool(valid.all()) and J.shape == (2, 40, LAYOUT.size)
    # inputs that require grad take the differentiable path (no out= arguments): the same values
    r_d, J_d, _, _ = linearise(tpl, image, cam, R0.clone().requires_grad_(), t0, a0, l0, light_basis, tpl.valid)
    assert J_d.requires_grad and torch.equal(J_d.detach(), J) and torch.equal(r_d.detach(), r)

    def fn(d):
        dR = rotation_reference(d[:, 0:3])
        t = t0 + d[:, 3:6]
        return linearise(tpl, image, cam, dR @ R0, t, a0 + d[:, LAYOUT.animation], l0 + d[:, LAYOUT.illumination],
                         light_basis, tpl.valid)[0]

    J_auto = _autograd_jacobian(fn, torch.zeros_like(x))
    for name, cols in GROUPS.items():
        scale = float(J_auto[..., cols].abs().max())
        assert scale > 0
        torch.testing.assert_close(J[..., cols], J_auto[..., cols], rtol=1e-9, atol=1e-12 * scale,
                                   msg=lambda m, name=name: f"{name} columns: {m}")


@pytest.mark.parametrize("kind", ["zero", "nonzero"])
def test_crop_residuals_equal_the_reference_objective(kind):
    """On a crop of the frame (offset subtracted after projection) the residuals, validity and the additive
    columns (translation, expression, light) equal those of ``frame_residuals`` on the full frame, whose image
    gradients are the central-difference images of ``image_with_gradients`` (the fast path's sampled differences
    either side of each point are the same values)."""
    tpl, x, image = make_template(seed=2), params(kind), gray(smooth_image())
    light_basis = _light_basis(tpl, params("nonzero"))
    r_ref, J_ref, valid_ref = frame_residuals(x, LAYOUT, tpl, image_with_gradients(image), CAM, light_basis, tpl.valid)
    ox, oy = 40, 24
    crop = image[:, :, oy:, ox:].contiguous()
    R0, t0, a0, l0 = split(x)
    r, J, valid, sampled = linearise(tpl, crop, full_camera(offset=(ox, oy)), R0, t0, a0, l0, light_basis, tpl.valid)
    assert bool(valid_ref.all()) and bool((valid == valid_ref).all())
    torch.testing.assert_close(r, r_ref, rtol=0, atol=1e-12)
    torch.testing.assert_close(sampled, r + tpl.intensity + (light_basis * l0[:, None]).sum(-1), rtol=0, atol=1e-12)
    for name in ("translation", "expression", "illumination"):
        cols = GROUPS[name]
        torch.testing.assert_close(J[..., cols], J_ref[..., cols], rtol=1e-10, atol=1e-14)
    # Rotation columns: at the identity rotation the additive axis-angle column and the turn about the head's
    # origin are the same derivative, X_model x g (g = dI/dX_cam, the translation columns).
    if kind == "zero":
        g = J[..., 3:6]
        torch.testing.assert_close(J[..., 0:3], J_ref[..., 0:3], rtol=1e-9, atol=1e-12)
        # ... and not the turn about the camera centre, (X_model + t) x g.
        about_camera = J_ref[..., 0:3] + torch.linalg.cross(t0[:, None].expand_as(g), g, dim=-1)
        assert float((J[..., 0:3] - about_camera).abs().max()) > 1e-3 * float(J[..., 0:3].abs().max())


def test_points_outside_the_crop_are_invalid():
    tpl, x, image = make_template(B=1, N=40), params("zero", B=1), gray(bilinear_image(B=1))
    R0, t0, a0, l0 = split(x)
    light_basis = _light_basis(tpl, x)
    crop = image[:, :, :, 80:].contiguous()  # right half of the frame only
    _, _, valid, _ = linearise(tpl, crop, full_camera(B=1, offset=(80, 0)), R0, t0, a0, l0, light_basis, tpl.valid)
    uv_u = CAM.fx * (tpl.points[..., 0] + t0[:, None, 0]) / (tpl.points[..., 2] + t0[:, None, 2]) + CAM.cx
    assert bool((valid == (uv_u >= 80)).all())
    assert 0 < int(valid.sum()) < 40


def test_sampled_gradients_at_the_crop_border_equal_the_gradient_image():
    """Within one pixel of the crop's edge the sampled differences are clamped by the sampler as the gradient
    image replicates its border: the fast path's residuals and translation columns equal ``frame_residuals`` with
    the crop's own central-difference image and a camera moved onto the crop."""
    from torchface.geometry.camera import Intrinsics

    tpl, x, image = make_template(B=1, N=600, seed=4), params("nonzero", B=1), gray(smooth_image(B=1))
    light_basis = _light_basis(tpl, x)
    ox, oy = 80, 50
    crop = image[:, :, oy:, ox:].contiguous()
    crop_cam = Intrinsics(CAM.width - ox, CAM.height - oy, CAM.fx, CAM.fy, CAM.cx - ox, CAM.cy - oy)
    r_ref, J_ref, valid_ref = frame_residuals(x, LAYOUT, tpl, image_with_gradients(crop), crop_cam, light_basis, tpl.valid)
    R0, t0, a0, l0 = split(x)
    r, J, valid, _ = linearise(tpl, crop, full_camera(B=1, offset=(ox, oy)), R0, t0, a0, l0, light_basis, tpl.valid)
    assert bool((valid == valid_ref).all())
    Xc = (tpl.points + (tpl.basis * a0[:, None, None]).sum(-1)) @ R0.mT + t0[:, None]
    u = CAM.fx * Xc[..., 0] / Xc[..., 2] + CAM.cx - ox
    v = CAM.fy * Xc[..., 1] / Xc[..., 2] + CAM.cy - oy
    near_edge = valid & ((u < 1) | (v < 1))
    assert int(near_edge.sum()) >= 3  # the case under test is there
    torch.testing.assert_close(r[valid], r_ref[valid], rtol=0, atol=1e-12)
    cols = GROUPS["translation"]
    torch.testing.assert_close(J[valid][:, cols], J_ref[valid][:, cols], rtol=1e-10, atol=1e-14)


def _synthetic_problem(B: int = 2, N: int = 400, seed: int = 3, coupled: float | None = None):
    """Template whose intensities are the smooth image sampled (bilinearly, as the solver does) at the true
    parameters with the true light: the truth is an exact zero-residual solution. With ``coupled``, animation unit
    1's basis is unit 0's plus ``coupled`` times its own: the two move the points nearly alike (as CANDIDE-3's
    eyelid units do)."""
    tpl = make_template(B=B, N=N, seed=seed)
    if coupled is not None:
        basis = tpl.basis.clone()
        basis[..., 1] = basis[..., 0] + coupled * tpl.basis[..., 1]
        tpl = Template(tpl.face_index, tpl.bary, tpl.points, basis, tpl.normals, tpl.intensity, tpl.valid)
    x_true = params("nonzero", B=B)
    light_basis = _light_basis(tpl, x_true)
    image = gray(smooth_image(B=B))
    R, t, a, lam = split(x_true)
    cam = full_camera(B=B)
    zero_light = torch.zeros_like(lam)
    tpl0 = Template(tpl.face_index, tpl.bary, tpl.points, tpl.basis, tpl.normals, torch.zeros_like(tpl.intensity), tpl.valid)
    observed = linearise(tpl0, image, cam, R, t, a, zero_light, light_basis, tpl.valid)[3]
    # observed = T + B lambda with B = [T, 1, T n] -> T = (observed - bias) / (1 + gain + l.n)
    n_cam = tpl.normals @ R.mT
    T = (observed - lam[:, 1:2]) / (1 + lam[:, 0:1] + (n_cam * lam[:, None, 2:5]).sum(-1))
    tpl = Template(tpl.face_index, tpl.bary, tpl.points, tpl.basis, tpl.normals, T, tpl.valid)
    from torchface.appearance import illumination_basis

    light_basis = illumination_basis(T, n_cam)
    return tpl, image, cam, x_true, light_basis


def _solve(tpl, image, cam, x0, light_basis, robust=None, iterations=30, backend=Backend.TORCH, workspace=None):
    R, t, a, lam = split(x0)
    free = torch.ones(LAYOUT.size, dtype=torch.bool)
    lo, hi = torch.full((A,), -5.0, dtype=D), torch.full((A,), 5.0, dtype=D)
    return solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, iterations=iterations, free=free,
                       alpha_lower=lo, alpha_upper=hi, alpha_prior=0.0, robust=robust, step_tolerance=1e-8,
                       function_tolerance=0.0, backend=backend, workspace=workspace)


def _perturbed(x_true: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
    """Start ``scale`` x (1.5 degrees, 5.8 mm, 0.1 AU, the light at reference) away from the truth."""
    x0 = x_true.clone()
    x0[:, 0:3] += scale * torch.tensor([0.02, -0.015, 0.01], dtype=D)
    x0[:, 3:6] += scale * torch.tensor([2.0, -1.5, 5.0], dtype=D)
    x0[:, LAYOUT.animation] += scale * 0.1
    x0[:, LAYOUT.illumination] *= 1.0 - scale
    return x0


def test_solve_level_recovers_known_parameters(backend):
    """From a perturbed start (1.5 degrees, 5.8 mm, 0.1 AU, reference light) Gauss-Newton reaches the truth.

    Convergence is linear, not quadratic: the gradient channels are bilinearly interpolated central differences,
    not the derivative of the bilinear interpolant, so the step is an inexact Newton step (measured: 0.02 degree
    after 10 iterations, 6e-5 after 30)."""
    tpl, image, cam, x_true, light_basis = _synthetic_problem()
    R, t, a, lam, out = _solve(tpl, image, cam, _perturbed(x_true), light_basis, iterations=60, backend=backend)
    R_true, t_true, a_true, lam_true = split(x_true)
    assert bool(out.finite.all())
    assert float(geodesic_angle_deg(R, R_true).max()) < 1e-6
    torch.testing.assert_close(t, t_true, rtol=0, atol=1e-5)
    torch.testing.assert_close(a, a_true, rtol=0, atol=1e-6)
    torch.testing.assert_close(lam, lam_true, rtol=0, atol=1e-6)
    assert float(out.residual[out.valid].abs().max()) < 1e-8


def test_function_tolerance_stops_a_pass_once_the_predicted_decrease_is_small(backend):
    """The predicted decrease of a Gauss-Newton step never exceeds the cost, so a function tolerance of 1 stops
    every sample after one step (converged); 0 leaves the parameter test alone; with noise on the template (a
    cost that levels off above zero, where the parameter test is slow to pass) the default stops on the way,
    a small fraction of the noise's own error away from where the full run ends."""
    tpl, image, cam, x_true, light_basis = _synthetic_problem()
    noise = 0.002 * torch.randn(tpl.intensity.shape, generator=torch.Generator().manual_seed(3), dtype=D)
    tpl = Template(tpl.face_index, tpl.bary, tpl.points, tpl.basis, tpl.normals, tpl.intensity + noise, tpl.valid)
    R0, t0, a0, l0 = split(_perturbed(x_true))
    free = torch.ones(LAYOUT.size, dtype=torch.bool)
    lo, hi = torch.full((A,), -5.0, dtype=D), torch.full((A,), 5.0, dtype=D)

    def solve(ftol):
        return solve_level(tpl, image, cam, R0, t0, a0, l0, light_basis, tpl.valid, iterations=40, free=free,
                           alpha_lower=lo, alpha_upper=hi, alpha_prior=0.0, robust=None, step_tolerance=1e-9,
                           function_tolerance=ftol, backend=backend)

    one, full, default = solve(1.0), solve(0.0), solve(FUNCTION_TOLERANCE)
    assert one[4].iterations.tolist() == [1, 1] and bool(one[4].converged.all())
    assert bool((full[4].iterations > 3).all())
    n = default[4].iterations
    assert bool(default[4].converged.all()) and bool((n > 1).all()) and bool((n < full[4].iterations).all()), n
    # measured: 4 steps instead of 31 and 20, 0.002 degree from the full run's end (itself 0.6 and 0.3 from the
    # truth: the noise's own error)
    assert float(geodesic_angle_deg(default[0], full[0]).max()) < 0.01


def test_solve_level_robust_weights_reject_corrupted_points(backend):
    """20 % of the template intensities corrupted by +0.3..0.6: from a start 0.4 degree / 1.5 mm off, Tukey IRLS
    lands on the truth while plain least squares is dragged tens of degrees away (the fast solver has no cost
    check, so it does not stop at the start either)."""
    tpl, image, cam, x_true, light_basis = _synthetic_problem()
    gen = torch.Generator().manual_seed(9)
    bad = torch.rand(tpl.intensity.shape, generator=gen, dtype=D) < 0.2
    T = torch.where(bad, tpl.intensity + 0.3 + 0.3 * torch.rand(tpl.intensity.shape, generator=gen, dtype=D), tpl.intensity)
    from torchface.appearance import illumination_basis

    R_true = split(x_true)[0]
    light_basis = illumination_basis(T, tpl.normals @ R_true.mT)  # the light basis follows the template (B_1 = T)
    tpl = Template(tpl.face_index, tpl.bary, tpl.points, tpl.basis, tpl.normals, T, tpl.valid)
    x0 = _perturbed(x_true, 0.25)  # from 1.5 degrees off, sample 1 of Tukey also diverges (no cost check)
    R_rob, t_rob, *_ = _solve(tpl, image, cam, x0, light_basis, robust=RobustLoss(RobustKind.TUKEY, 4.685), backend=backend)
    R_l2, t_l2, *_ = _solve(tpl, image, cam, x0, light_basis, robust=None, backend=backend)
    err_rob = geodesic_angle_deg(R_rob, R_true)
    err_l2 = geodesic_angle_deg(R_l2, R_true)
    assert float(err_rob.max()) < 1e-3, err_rob
    assert float(err_l2.min()) > 1.0, (err_l2, err_rob)
    torch.testing.assert_close(t_rob, split(x_true)[1], rtol=0, atol=1e-3)


def test_solve_level_survives_an_unobservable_animation_unit(backend):
    tpl, image, cam, x_true, light_basis = _synthetic_problem()
    basis = tpl.basis.clone()
    basis[..., 0] = 0.0  # animation unit 0 moves nothing
    tpl = Template(tpl.face_index, tpl.bary, tpl.points, basis, tpl.normals, tpl.intensity, tpl.valid)
    *_, out = _solve(tpl, image, cam, _perturbed(x_true), light_basis, backend=backend)
    assert bool(out.finite.all())


@pytest.mark.parametrize("test", ["step", "predicted_decrease"])
def test_a_unit_the_data_holds_at_its_bound_converges(test, backend):
    """Animation unit 1's lower bound (-0.15) above stream 0's truth (-0.2): the data pushes it against the bound
    every iteration. The convergence tests (each alone here) read the change the bounds let through, so the level
    converges with the unit held there, at the solution with the unit fixed at its bound. They read the unclipped
    increment, whose step never came out small and whose predicted decrease the bounds never let through: the level
    ran to its cap (30 of 30 iterations, not converged; the step test: 63 to converge from 300), reported
    MAX_ITERATIONS. Stream 1 (truth 0.25, off the bound) is the control."""
    tpl, image, cam, x_true, light_basis = _synthetic_problem()
    R, t, a, lam = split(_perturbed(x_true))
    free = torch.ones(LAYOUT.size, dtype=torch.bool)
    lo, hi = torch.full((A,), -5.0, dtype=D), torch.full((A,), 5.0, dtype=D)
    lo[1] = -0.15
    tolerances = (STEP_TOLERANCE, 0.0) if test == "step" else (1e-9, FUNCTION_TOLERANCE)
    kw = dict(alpha_lower=lo, alpha_upper=hi, alpha_prior=0.0, robust=None, step_tolerance=tolerances[0],
              function_tolerance=tolerances[1], backend=backend)
    R1, t1, a1, l1, out = solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, iterations=30,
                                      free=free, **kw)
    assert out.converged.tolist() == [True, True] and int(out.iterations[0]) <= 8, out.iterations
    assert a1[0, 1].item() == -0.15
    # measured 5e-6 degree, 3e-4 mm, 3e-7 AU from the fixed unit's solution (the start was 1.5 degrees off). The
    # solver clipped the whole step instead of holding the unit, and crawled there: 0.13 degree, 0.07 mm, 0.002 AU
    # off (0.06 degree after 300 iterations).
    fixed = free.clone()
    fixed[6 + 1] = False
    a_held = a.clone()
    a_held[0, 1] = -0.15
    R2, t2, a2, l2, _ = solve_level(tpl, image, cam, R, t, a_held, lam, light_basis, tpl.valid, iterations=60,
                                    free=fixed, **{**kw, "step_tolerance": 1e-9, "function_tolerance": 0.0})
    assert float(geodesic_angle_deg(R1[:1], R2[:1]).max()) < 1e-3
    torch.testing.assert_close(t1[:1], t2[:1], rtol=0, atol=0.01)
    torch.testing.assert_close(a1[:1], a2[:1], rtol=0, atol=1e-4)


def _box_qp(g: torch.Tensor, H: torch.Tensor, alpha: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """The slow reference: ``argmin g.d + d^T H d / 2`` over ``d (P,)`` with ``lo <= alpha + d[6:6+A] <= hi``, by
    brute force (float64): every animation unit free, at its lower or at its upper bound (3^A active sets), the
    others' minimum for each, the least value among the feasible ones (the optimum's own active set is one)."""
    import itertools

    P = g.shape[0]
    best, best_d = float("inf"), None
    for states in itertools.product((None, 0, 1), repeat=A):
        d = torch.zeros(P, dtype=D)
        fixed = torch.zeros(P, dtype=torch.bool)
        for a, side in enumerate(states):
            if side is not None:
                fixed[6 + a] = True
                d[6 + a] = (lo if side == 0 else hi)[a] - alpha[a]
        f = ~fixed
        d[f] = torch.linalg.solve(H[f][:, f], -(g[f] + H[f][:, fixed] @ d[fixed]))
        moved = alpha + d[6 : 6 + A]
        if bool((moved < lo - 1e-12).any() or (moved > hi + 1e-12).any()):
            continue
        value = float(g @ d + 0.5 * d @ H @ d)
        if value < best:
            best, best_d = value, d
    assert best_d is not None
    return best_d


@pytest.mark.parametrize("push", ["outward", "inward"])
def test_one_step_at_a_bound_is_the_box_constrained_minimum_of_the_model(push, backend):
    """Animation unit 0 starts at its lower bound, unit 1 moves the points nearly as it does. Outward: the bound
    (0.45) lies above the truth (0.3, -0.4), so the data push unit 0 below it; the solver holds it (its row and
    column out of the damped system) and the other parameters' step is the one with it fixed: one step equals the
    minimum of the same damped quadratic model over the box, found by brute force. The old solver took the free
    step and clipped unit 0 afterwards: unit 1 and the pose moved as if unit 0 had gone below it (measured: unit 1
    off by 0.14 and 0.74, the rotation by 0.04 and 0.30 degree). Inward: the bound (0.2 and -0.5) lies below the
    truth, the data pull unit 0 up, and it must leave the bound (not be held): the step is the free one."""
    tpl, image, cam, x_true, light_basis = _synthetic_problem(coupled=0.1)
    x0 = _perturbed(x_true, 0.3)
    bound = (0.45, 0.45) if push == "outward" else (0.2, -0.5)  # unit 0's lower bound, per stream
    x0[:, 6] = torch.tensor(bound, dtype=D)
    R, t, a, lam = split(x0)
    hi = torch.full((A,), 5.0, dtype=D)
    free = torch.ones(LAYOUT.size, dtype=torch.bool)
    damping = 1e-3
    for b in range(2):  # one stream at a time: the bounds are (A,)
        lob = torch.full((A,), -5.0, dtype=D)
        lob[0] = bound[b]
        one = Template(*(getattr(tpl, f)[b : b + 1] for f in tpl.__dataclass_fields__))
        cb = LevelCamera(cam.fx, cam.fy, cam.cx, cam.cy, cam.offset[b : b + 1], cam.height, cam.width)
        args = (one, image[b : b + 1], cb, R[b : b + 1], t[b : b + 1], a[b : b + 1], lam[b : b + 1],
                light_basis[b : b + 1])  # fmt: skip
        R1, t1, a1, l1, _ = solve_level(*args, one.valid, iterations=1, free=free, alpha_lower=lob, alpha_upper=hi,
                                        alpha_prior=0.0, robust=None, damping=damping, final_check=False,
                                        step_tolerance=1e-12, function_tolerance=0.0, backend=backend)  # fmt: skip
        step = torch.cat([matrix_to_axis_angle(R1 @ R[b : b + 1].mT), t1 - t[b : b + 1], a1 - a[b : b + 1],
                          l1 - lam[b : b + 1]], -1)[0]  # fmt: skip
        # the model the step minimises: the damped Gauss-Newton system at the start (linearise's, float64)
        r, J, valid, _ = linearise(*args, one.valid)
        Jv, rv = J[0][valid[0]], r[0][valid[0]]
        H = Jv.T @ Jv
        Hd = H + damping * torch.diag(H.diagonal() + 1e-6 * H.diagonal().max())
        want = _box_qp(Jv.T @ rv, Hd, a[b], lob, hi)
        torch.testing.assert_close(step, want, rtol=0, atol=1e-9 * float(want.abs().max()))
        free_step = -torch.linalg.solve(Hd, Jv.T @ rv)
        if push == "outward":
            assert float(step[6]) == 0.0 and float(free_step[6]) < -0.05  # held, where the free step went down
            # the case under test: clipping the free step is far from the minimum
            assert float((free_step[7] - step[7]).abs()) > 0.05
        else:
            assert float(step[6]) > 0.05 and torch.allclose(step, free_step, rtol=0, atol=1e-9)



@pytest.mark.parametrize("gap", [0.4, 2.0])
def test_a_unit_within_the_bound_margin_counts_as_at_the_bound(gap, backend):
    """The outward case above with unit 0 started ``gap`` margins (BOUND_MARGIN of its range, 4.55e-6 here) inside
    its bound: within the margin it is held (it keeps its start, 0.4 margins inside), beyond it it takes the free
    step, which the clip stops at the bound."""
    tpl, image, cam, x_true, light_basis = _synthetic_problem(coupled=0.1)
    lo, hi = torch.full((A,), -5.0, dtype=D), torch.full((A,), 5.0, dtype=D)
    lo[0] = 0.45
    start = 0.45 + gap * BOUND_MARGIN * (5.0 - 0.45)
    x0 = _perturbed(x_true, 0.3)
    x0[:, 6] = start
    R, t, a, lam = split(x0)
    *_, a1, _, _ = solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, iterations=1,
                               free=torch.ones(LAYOUT.size, dtype=torch.bool), alpha_lower=lo, alpha_upper=hi,
                               alpha_prior=0.0, robust=None, final_check=False, step_tolerance=1e-12,
                               function_tolerance=0.0, backend=backend)  # fmt: skip
    assert a1[:, 0].tolist() == ([start] * 2 if gap < 1 else [0.45] * 2)


@pytest.mark.parametrize("bounds", [(-5.0, math.inf), (-math.inf, 5.0), (-math.inf, math.inf)])
def test_an_infinite_bound_is_no_bound(bounds, backend):
    """An animation unit's bound may be infinite (no bound on that side; the clip lets everything through): no unit
    is then at that bound, and the solve is the one with finite bounds that no unit comes near (-5 and 5 here), to
    the bit. The margin BOUND_MARGIN * (upper - lower) was infinite: the lower bound's inner edge -5 + inf = inf, so
    every unit whose gradient pointed down was held at a 'lower bound' wherever it was (and with -inf below, the
    upper's inner edge 5 - inf = -inf held every unit the gradient pushed up): measured 1.8 and 1.1 degrees, 8.4 mm,
    0.1 AU (-5, inf) and 0.024 degree, 0.012 mm, 0.005 AU (-inf, 5) off the finite bounds' solve, both solvers."""
    tpl, image, cam, x_true, light_basis = _synthetic_problem()
    R, t, a, lam = split(_perturbed(x_true))
    free = torch.ones(LAYOUT.size, dtype=torch.bool)
    kw = dict(iterations=8, free=free, alpha_prior=0.0, robust=None, backend=backend)
    args = (tpl, image, cam, R, t, a, lam, light_basis, tpl.valid)
    finite = solve_level(*args, alpha_lower=torch.full((A,), -5.0, dtype=D), alpha_upper=torch.full((A,), 5.0, dtype=D),
                         **kw)  # fmt: skip
    got = solve_level(*args, alpha_lower=torch.full((A,), bounds[0], dtype=D),
                      alpha_upper=torch.full((A,), bounds[1], dtype=D), **kw)  # fmt: skip
    assert float((finite[2] - a).abs().max()) > 0.05  # the units moved (so that holding them would show)
    for x, y in zip(got[:4], finite[:4]):
        assert torch.equal(x, y)
    for field in ("iterations", "converged", "residual"):
        assert torch.equal(getattr(got[4], field), getattr(finite[4], field)), field


def test_a_unit_pushed_past_its_bound_with_a_coupled_partner_reaches_the_constrained_optimum(backend):
    """Animation unit 0's lower bound (0.45) above both streams' truth, unit 1 coupled to it, the start at the
    bound: the level ends at the constrained optimum, the solution with unit 0 fixed at its bound (solved to
    1e-10), where the cost's gradient still pushes unit 0 outward (so that the bound is active there: the KKT
    condition). Measured within 0.0006 degree, 0.003 mm and 4e-6 AU of it after 4 and 10 iterations; the clipped
    step ended 0.13 and 0.48 degree, 0.9 and 0.5 mm, 0.007 and 0.011 AU away after 18 and 26."""
    tpl, image, cam, x_true, light_basis = _synthetic_problem(coupled=0.1)
    x0 = _perturbed(x_true, 0.3)
    x0[:, 6] = 0.45
    R, t, a, lam = split(x0)
    free = torch.ones(LAYOUT.size, dtype=torch.bool)
    lo, hi = torch.full((A,), -5.0, dtype=D), torch.full((A,), 5.0, dtype=D)
    lo[0] = 0.45
    kw = dict(alpha_lower=lo, alpha_upper=hi, alpha_prior=0.0, robust=None, backend=backend)
    R1, t1, a1, l1, out = solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, iterations=30, free=free,
                                      step_tolerance=STEP_TOLERANCE, function_tolerance=0.0, **kw)  # fmt: skip
    assert out.converged.tolist() == [True, True] and a1[:, 0].tolist() == [0.45, 0.45]
    fixed = free.clone()
    fixed[6] = False
    R2, t2, a2, l2, _ = solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, iterations=100, free=fixed,
                                    step_tolerance=1e-10, function_tolerance=0.0, **kw)  # fmt: skip
    r, J, valid, _ = linearise(tpl, image, cam, R2, t2, a2, l2, light_basis, tpl.valid)
    grad = (J[..., 6] * torch.where(valid, r, 0.0)).sum(-1)
    assert bool((grad > 0).all()), grad  # -grad points below the bound: it is active at the optimum
    assert float(geodesic_angle_deg(R1, R2).max()) < 0.005
    torch.testing.assert_close(t1, t2, rtol=0, atol=0.02)
    torch.testing.assert_close(a1, a2, rtol=0, atol=1e-4)
    torch.testing.assert_close(l1, l2, rtol=0, atol=1e-4)


def test_a_negative_predicted_decrease_does_not_stop_the_level(backend):
    """Stream 0 starts at the truth but for the coupled units 0 and 1 (0.3 and -0.2), both at 0; unit 0's upper
    bound is 0.1. The first step takes both towards the truth, the clip holds unit 0 at 0.1 while unit 1 goes to
    -0.15: together they move the points further from the data than the start (predicted decrease -0.0013,
    negative). That is no reason to stop: the level goes on, to the constrained optimum (unit 0 fixed at 0.1; held
    there from the third iteration). The test ``pred < tol * cost`` stopped it
    after that one step, the final check undid the step, and the level reported CONVERGED at the start, 0.12
    degree, 0.24 mm and 0.1 AU from it. Stream 1 (unit 0's truth -0.4, far from the bound) is the control."""
    tpl, image, cam, x_true, light_basis = _synthetic_problem(coupled=0.1)
    R, t, a, lam = split(x_true)
    a = a.clone()
    a[0, :2] = 0.0
    free = torch.ones(LAYOUT.size, dtype=torch.bool)
    lo, hi = torch.full((A,), -5.0, dtype=D), torch.full((A,), 5.0, dtype=D)
    hi[0] = 0.1
    kw = dict(alpha_lower=lo, alpha_upper=hi, alpha_prior=0.0, robust=None, backend=backend)
    R1, t1, a1, l1, out = solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, iterations=30, free=free,
                                      step_tolerance=STEP_TOLERANCE, function_tolerance=FUNCTION_TOLERANCE, **kw)  # fmt: skip
    assert out.converged.tolist() == [True, True] and int(out.iterations[0]) > 1
    fixed = free.clone()
    fixed[6] = False
    a_fixed = a.clone()
    a_fixed[0, 0] = 0.1
    R2, t2, a2, l2, _ = solve_level(tpl, image, cam, R, t, a_fixed, lam, light_basis, tpl.valid, iterations=100,
                                    free=fixed, step_tolerance=1e-10, function_tolerance=0.0, **kw)  # fmt: skip
    # measured 0.003 degree, 0.02 mm, 8e-6 AU (the step tolerance's own error)
    assert float(geodesic_angle_deg(R1[:1], R2[:1]).max()) < 0.01
    torch.testing.assert_close(t1[:1], t2[:1], rtol=0, atol=0.05)
    torch.testing.assert_close(a1[:1], a2[:1], rtol=0, atol=1e-4)
    R_true, t_true, a_true, _ = split(x_true)
    assert float(geodesic_angle_deg(R1[1:], R_true[1:]).max()) < 0.01
    torch.testing.assert_close(a1[1:], a_true[1:], rtol=0, atol=1e-3)


@pytest.mark.parametrize("centred", [False, True])
def test_prior_pulls_an_unobservable_animation_unit_to_its_mean(centred, backend):
    """An animation unit that moves nothing is set by its prior alone: it ends at the prior's mean (the first
    frame's expression when ``alpha_mean`` is given, zero otherwise), whatever it started from."""
    tpl, image, cam, x_true, light_basis = _synthetic_problem()
    basis = tpl.basis.clone()
    basis[..., 0] = 0.0
    tpl = Template(tpl.face_index, tpl.bary, tpl.points, basis, tpl.normals, tpl.intensity, tpl.valid)
    R, t, a, lam = split(_perturbed(x_true))
    mean = torch.full_like(a, 0.35) if centred else None
    free = torch.ones(LAYOUT.size, dtype=torch.bool)
    lo, hi = torch.full((A,), -5.0, dtype=D), torch.full((A,), 5.0, dtype=D)
    *_, a_out, _, out = solve_level(
        tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, iterations=30, free=free, alpha_lower=lo,
        alpha_upper=hi, alpha_prior=1.0, alpha_mean=mean, robust=None, step_tolerance=1e-9, backend=backend,
    )
    assert bool(out.finite.all())
    torch.testing.assert_close(a_out[:, 0], torch.full_like(a_out[:, 0], 0.35 if centred else 0.0), rtol=0, atol=1e-4)


@pytest.mark.parametrize("size", [(24, 36), (32, 48)])
def test_crop_gray_equals_slicing_each_stream(size):
    from torchface.appearance.sampling import to_gray
    from torchface.tracker.step import _crop_gray

    g = torch.Generator().manual_seed(3)
    frames = torch.rand(3, 3, 40, 56, generator=g)
    h, w = size
    # the last stream's window touches the bottom-right corner: the last run of the flat storage
    offsets = torch.tensor([[0, 0], [4, 4], [56 - w, 40 - h]])
    crop = _crop_gray(frames, offsets, h, w)
    for b in range(3):
        x0, y0 = offsets[b].tolist()
        ref = to_gray(frames[b : b + 1, :, y0 : y0 + h, x0 : x0 + w])
        assert torch.equal(crop[b : b + 1], ref)
    # frames that require grad take the differentiable path: the same values, and the gradient reaches the pixels
    live = frames.clone().requires_grad_(True)
    crop_d = _crop_gray(live, offsets, h, w)
    assert torch.equal(crop_d.detach(), crop)
    crop_d.sum().backward()
    assert float(live.grad.sum()) > 0


def test_crop_windows_equals_slicing_of_a_non_contiguous_batch():
    from torchface.tracker.step import crop_windows

    g = torch.Generator().manual_seed(4)
    images = torch.rand(2, 5, 30, 3, generator=g, dtype=torch.float64).permute(0, 3, 1, 2)  # (2, 3, 5, 30) strided
    offsets = torch.tensor([[27, 0], [0, 2]])
    got = crop_windows(images, offsets, 3, 3)
    for b in range(2):
        x0, y0 = offsets[b].tolist()
        assert torch.equal(got[b], images[b, :, y0 : y0 + 3, x0 : x0 + 3])


def _prior_solver(backend):
    """``solve(prior)``: one synthetic level solve (two streams, no robust loss, prior centred at 0.35) with the
    given ``alpha_prior``, and that centre ``(B, A)``."""
    tpl, image, cam, x_true, light_basis = _synthetic_problem()
    R, t, a, lam = split(_perturbed(x_true))
    free = torch.ones(LAYOUT.size, dtype=torch.bool)
    lo, hi = torch.full((A,), -5.0, dtype=D), torch.full((A,), 5.0, dtype=D)
    mean = torch.full_like(a, 0.35)

    def solve(prior):
        return solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, iterations=8, free=free,
                           alpha_lower=lo, alpha_upper=hi, alpha_prior=prior, alpha_mean=mean, robust=None,
                           backend=backend)

    return solve, mean


def test_per_stream_prior_equals_each_stream_solved_with_its_own(backend):
    """``alpha_prior`` as ``(B,)``: each stream ends where solving it with its own float precision ends."""
    solve, _ = _prior_solver(backend)
    mixed = solve(torch.tensor([50.0, 0.01], dtype=D))
    for b, prior in enumerate((50.0, 0.01)):
        alone = solve(prior)
        for got, want in zip(mixed[:4], alone[:4]):
            torch.testing.assert_close(got[b], want[b], rtol=0, atol=1e-10)
    # the two precisions really lead to different answers (so the test can tell them apart)
    assert float((solve(50.0)[2] - solve(0.01)[2]).abs().max()) > 1e-3


def test_per_unit_prior_is_the_per_stream_prior_where_equal_and_pins_a_heavily_weighted_unit(backend):
    """``alpha_prior`` as ``(B, A)``: equal across units it is the ``(B,)`` prior; a unit given a huge precision
    stays at its prior mean while the others move as before (to the solve's tolerance)."""
    solve, mean = _prior_solver(backend)
    per_stream = torch.tensor([50.0, 0.01], dtype=D)
    same = solve(per_stream[:, None].expand(2, A).contiguous())
    for got, want in zip(same[:4], solve(per_stream)[:4]):
        torch.testing.assert_close(got, want, rtol=0, atol=1e-12)
    pinned = torch.full((2, A), 0.01, dtype=D)
    pinned[:, 0] = 1e9
    out = solve(pinned)
    torch.testing.assert_close(out[2][:, 0], mean[:, 0], rtol=0, atol=1e-6)
    free_run = solve(0.01)
    assert float((free_run[2][:, 0] - mean[:, 0]).abs().max()) > 1e-3  # without the weight it moves


@pytest.mark.parametrize("robust", [None, RobustLoss(RobustKind.TUKEY, 4.685)])
def test_a_pass_started_from_the_last_linearisation_equals_one_that_linearises_again(robust, backend):
    """``solve_level(start=out.linearisation)`` (the refinement pass after the finest level) gives exactly what
    linearising at the start again gives, and the linearisation is the one at the returned estimate. In a
    StepWorkspace whose buffers hold stale values (NaN) the pass is the same bit for bit; the native solver's
    Jacobian is then the workspace's memory (the torch code does not use it), and the refinement pass, in the
    same workspace, starts from it as from new memory."""
    from torchface.tracker.step import StepWorkspace

    tpl, image, cam, x_true, light_basis = _synthetic_problem()
    R, t, a, lam, first = _solve(tpl, image, cam, _perturbed(x_true), light_basis, robust=robust, iterations=3, backend=backend)
    ws = StepWorkspace()
    for name in ("jacobian", "neg_light_basis"):
        ws.buffer(name, (1 << 18,), D, torch.device("cpu")).fill_(float("nan"))  # (more than the pass needs)
    in_ws = _solve(tpl, image, cam, _perturbed(x_true), light_basis, robust=robust, iterations=3, backend=backend,
                   workspace=ws)  # fmt: skip
    for got, want in zip(in_ws[:4] + in_ws[4].linearisation, (R, t, a, lam) + first.linearisation):
        assert torch.equal(got, want)
    native_ws = in_ws[4].linearisation[1].data_ptr() == ws.buffer("jacobian", (1,), D, torch.device("cpu")).data_ptr()
    assert native_ws == (backend is not Backend.TORCH)
    r, J, valid, sampled = first.linearisation
    again = linearise(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid)
    if backend is Backend.TORCH:
        for got, want in zip((r, J, valid, sampled), again):
            assert torch.equal(got, want)
    else:  # the native solver's own linearisation: the torch code's to rounding, its Jacobian zero where not valid
        assert torch.equal(valid, again[2])
        torch.testing.assert_close(r, again[0], rtol=0, atol=1e-12)
        torch.testing.assert_close(sampled, again[3], rtol=0, atol=1e-12)
        torch.testing.assert_close(J[valid], again[1][valid], rtol=1e-9, atol=1e-12)
        assert bool((J[~valid] == 0).all())
    free = torch.ones(LAYOUT.size, dtype=torch.bool)
    free[0:6] = False  # a refinement pass: expression and light only
    lo, hi = torch.full((A,), -5.0, dtype=D), torch.full((A,), 5.0, dtype=D)

    def refine(start, workspace=None):
        return solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, iterations=3, free=free,
                           alpha_lower=lo, alpha_upper=hi, alpha_prior=0.1, robust=robust, start=start,
                           backend=backend, workspace=workspace)

    reused, fresh = refine(first.linearisation), refine(None)
    for got, want in zip(reused[:4], fresh[:4]):
        assert torch.equal(got, want)
    for got, want in zip(refine(in_ws[4].linearisation, ws)[:4], fresh[:4]):  # as the step's refinement pass
        assert torch.equal(got, want)
    assert torch.equal(reused[4].iterations, fresh[4].iterations)
    assert float((reused[2] - a).abs().max()) > 1e-6  # the pass moved (so equality says something)


def test_round_down_to_a_power_of_two_is_floor_division_also_below_zero():
    from torchface.tracker.step import _round_down

    x = torch.arange(-37, 41, dtype=torch.int64)
    for q in (1, 2, 4, 8):
        assert torch.equal(_round_down(x, q), torch.div(x, q, rounding_mode="floor") * q)


@pytest.mark.parametrize("robust", [None, RobustLoss(RobustKind.TUKEY, 4.685)])
def test_a_residual_only_final_check_gives_the_same_pass(robust, backend):
    """``keep_linearisation=False``: the final check linearises residuals only (one sample per point, no Jacobian)
    and the pass ends exactly where the full check ends, with the same outcome but no linearisation to hand on."""
    tpl, image, cam, x_true, light_basis = _synthetic_problem()
    R, t, a, lam = split(_perturbed(x_true))
    full = linearise(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid)
    cheap = linearise(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, jacobian=False)
    assert cheap[1] is None
    for i in (0, 2, 3):
        assert torch.equal(cheap[i], full[i])
    free = torch.ones(LAYOUT.size, dtype=torch.bool)
    lo, hi = torch.full((A,), -5.0, dtype=D), torch.full((A,), 5.0, dtype=D)

    def solve(keep):
        return solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, iterations=3, free=free,
                           alpha_lower=lo, alpha_upper=hi, alpha_prior=0.1, robust=robust, keep_linearisation=keep,
                           backend=backend)

    kept, checked = solve(True), solve(False)
    for got, want in zip(checked[:4], kept[:4]):
        assert torch.equal(got, want)
    for name in ("residual", "valid", "sampled", "iterations", "converged", "finite"):
        assert torch.equal(getattr(checked[4], name), getattr(kept[4], name)), name
    assert kept[4].linearisation is not None and checked[4].linearisation is None


def test_cached_constants_first_made_in_inference_mode_serve_a_differentiable_pass():
    """The per-camera and per-setting constants (cached on first use) are made outside inference mode: a pass run
    first under ``torch.inference_mode`` leaves them usable by a later differentiable one (gradients flow), and a
    pass with other settings (a fixed parameter, another prior) gets its own, not the first one's."""
    from torchface.tracker import fast

    fast._camera_constants.cache_clear()
    fast._solver_constants.cache_clear()
    tpl, image, cam, x_true, light_basis = _synthetic_problem()
    x0 = _perturbed(x_true)
    with torch.inference_mode():
        first = _solve(tpl, image, cam, x0, light_basis, iterations=3)
    assert fast._camera_constants.cache_info().currsize == 1 and fast._solver_constants.cache_info().currsize == 1
    R, t, a, lam = split(x0)
    R = R.clone().requires_grad_()
    r, J, valid, _ = linearise(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid)
    (r * r).sum().backward()
    assert R.grad is not None and bool(torch.isfinite(R.grad).all()) and float(R.grad.abs().sum()) > 0
    again = _solve(tpl, image, cam, x0, light_basis, iterations=3)  # outside inference mode, from the cache
    assert all(torch.equal(p, q) for p, q in zip(first[:4], again[:4]))
    # A fixed translation: its own constants, and the translation does not move.
    free = torch.ones(LAYOUT.size, dtype=torch.bool)
    free[3:6] = False
    lo, hi = torch.full((A,), -5.0, dtype=D), torch.full((A,), 5.0, dtype=D)
    R0, t0, a0, l0 = split(x0)
    out = solve_level(tpl, image, cam, R0, t0, a0, l0, light_basis, tpl.valid, iterations=3, free=free,
                      alpha_lower=lo, alpha_upper=hi, alpha_prior=0.0, robust=None, backend=Backend.TORCH)
    assert fast._solver_constants.cache_info().currsize == 2
    assert torch.equal(out[1], t0) and not torch.equal(out[0], R0)


def test_the_torch_solver_reads_the_host_twice_per_iteration():
    """Each host read of a device value (``bool``, ``item``, ``tolist``, ...) waits for the device: on a GPU, a
    synchronisation, worse than a kernel launch. The torch solver reads one flag for the system's finiteness and the
    steps' acceptance together (two reads before), one for whether any stream goes on (none after the last
    iteration), and after the loop the final check's acceptance; its free mask is a host tensor (the tracker's is
    made on the CPU) and not counted."""

    class HostReads(torch.overrides.TorchFunctionMode):
        def __init__(self, skip: torch.Tensor) -> None:
            super().__init__()
            self.count, self.skip = 0, skip

        def __torch_function__(self, func, types, args=(), kwargs=None):
            name = getattr(func, "__name__", "")
            if name in ("__bool__", "__int__", "__float__", "__index__", "item", "tolist") and args[0] is not self.skip:
                self.count += 1
            return func(*args, **(kwargs or {}))

    tpl, image, cam, x_true, light_basis = _synthetic_problem()
    R, t, a, lam = split(_perturbed(x_true))
    free = torch.ones(LAYOUT.size, dtype=torch.bool)
    lo, hi = torch.full((A,), -5.0, dtype=D), torch.full((A,), 5.0, dtype=D)
    with HostReads(free) as reads:
        out = solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, iterations=6, free=free,
                          alpha_lower=lo, alpha_upper=hi, alpha_prior=0.0, robust=RobustLoss(RobustKind.TUKEY),
                          step_tolerance=1e-12, function_tolerance=0.0, backend=Backend.TORCH)[4]
    assert out.iterations.tolist() == [6, 6]  # (every step accepted: no read for a rejection)
    assert reads.count == 2 * 6  # (3 * 6 before: 18)


def test_no_iteration_without_the_final_check_reports_no_linearisation(backend):
    """``iterations=0`` with ``final_check=False``: nothing linearised, the start handed back and no point reported
    (the native solver's zeros). The torch code read the loop's last residuals, which it never made: an
    UnboundLocalError ('r')."""
    tpl, image, cam, x_true, light_basis = _synthetic_problem()
    R, t, a, lam = split(_perturbed(x_true))
    free = torch.ones(LAYOUT.size, dtype=torch.bool)
    lo, hi = torch.full((A,), -5.0, dtype=D), torch.full((A,), 5.0, dtype=D)
    R1, t1, a1, l1, out = solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, iterations=0, free=free,
                                      alpha_lower=lo, alpha_upper=hi, alpha_prior=0.0, robust=None, final_check=False,
                                      backend=backend)  # fmt: skip
    assert torch.equal(R1, R) and torch.equal(t1, t) and torch.equal(a1, a) and torch.equal(l1, lam)
    assert out.residual.shape == tpl.valid.shape and not bool(out.residual.any()) and not bool(out.valid.any())
    assert out.iterations.tolist() == [0, 0] and out.converged.tolist() == [False, False]


@pytest.mark.parametrize("iterations", [0, 3])
@pytest.mark.parametrize(
    "lower, upper", [(math.nan, 5.0), (-5.0, math.nan), (math.nan, math.nan), (6.0, 5.0), (math.inf, math.inf),
                     (-math.inf, -math.inf)], ids=["nan-lower", "nan-upper", "nan-both", "crossed", "lower-inf",
                                                   "upper-minus-inf"],
)  # fmt: skip
@pytest.mark.parametrize("rows", [False, True], ids=["shared", "per-stream"])
def test_unusable_bounds_are_refused_naming_the_unit(lower, upper, iterations, rows, backend, monkeypatch):
    """A NaN bound, bounds the wrong way round or a bound at the wrong infinity are refused with a ValueError naming
    the unit. Before, the torch code failed every stream without a word (``finite`` False, the start handed back:
    the clip made the unit NaN) while the native solver ran on as if that side had no bound, and bounds the wrong
    way round put the unit at its upper bound in both. Per-stream ``(B, A)`` bounds (the second stream's unit 2
    here) are checked elementwise before their values are read as lists (as more than
    ``fast._LIST_CHECK_VALUES`` are: 0 here)."""
    import torchface.tracker.fast as fast

    tpl, image, cam, x_true, light_basis = _synthetic_problem()
    R, t, a, lam = split(_perturbed(x_true))
    lo, hi = torch.full((A,), -5.0, dtype=D), torch.full((A,), 5.0, dtype=D)
    if rows:
        monkeypatch.setattr(fast, "_LIST_CHECK_VALUES", 0)
        lo, hi = lo.expand(2, A).clone(), hi.expand(2, A).clone()
        lo[1, 2], hi[1, 2] = lower, upper
    else:
        lo[2], hi[2] = lower, upper
    with pytest.raises(ValueError, match=r"alpha_lower and alpha_upper must be bounds.*for animation unit 2"):
        solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, iterations=iterations,
                    free=torch.ones(LAYOUT.size, dtype=torch.bool), alpha_lower=lo, alpha_upper=hi, alpha_prior=0.0,
                    robust=None, backend=backend)  # fmt: skip


def test_per_stream_bounds_clip_each_stream_at_its_own(backend):
    """``(B, A)`` bounds, one row a stream (the tracker's, about each stream's first fit:
    ``expression_range_from_start``): rows equal to the shared ``(A,)`` bounds solve to the same estimates, and a row
    that moves one stream's bound onto its estimate holds that stream's unit there and leaves the other stream as it
    was."""
    tpl, image, cam, x_true, light_basis = _synthetic_problem()
    R, t, a, lam = split(_perturbed(x_true))
    kw = dict(iterations=6, free=torch.ones(LAYOUT.size, dtype=torch.bool), alpha_prior=0.0, robust=None,
              backend=backend)  # fmt: skip
    lo, hi = torch.full((A,), -5.0, dtype=D), torch.full((A,), 5.0, dtype=D)
    shared = solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, alpha_lower=lo, alpha_upper=hi, **kw)
    rows = solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, alpha_lower=lo.expand(2, A),
                       alpha_upper=hi.expand(2, A), **kw)  # fmt: skip
    for x, y in zip(shared[:4], rows[:4]):
        torch.testing.assert_close(x, y, rtol=0, atol=0)
    cap = float(shared[2][0, 1]) - 0.05  # below stream 0's estimate of unit 1
    upper = hi.expand(2, A).clone()
    upper[0, 1] = cap
    held = solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, alpha_lower=lo.expand(2, A),
                       alpha_upper=upper, **kw)  # fmt: skip
    assert float(held[2][0, 1]) <= cap + 1e-9 and abs(float(held[2][0, 1]) - cap) < 1e-6
    torch.testing.assert_close(held[2][1], shared[2][1], rtol=0, atol=0)


@pytest.mark.parametrize("shape", [(1,), (3, A), (A + 1,), (2, A + 1)])
def test_bounds_of_another_shape_are_refused(shape, backend):
    """The bounds are ``(A,)`` or ``(B, A)`` (B = 2 here): the native solver read ``A`` values wherever they were
    (past a shorter tensor's end; a ``(B, A)`` one's first row for every stream, before it took one row a stream)."""
    tpl, image, cam, x_true, light_basis = _synthetic_problem()
    R, t, a, lam = split(_perturbed(x_true))
    lo, hi = torch.full(shape, -5.0, dtype=D), torch.full((A,), 5.0, dtype=D)
    with pytest.raises(ValueError, match=rf"alpha_lower must be \({A},\) or \(2, {A}\), one bound per animation unit"):
        solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, iterations=3,
                    free=torch.ones(LAYOUT.size, dtype=torch.bool), alpha_lower=lo, alpha_upper=hi, alpha_prior=0.0,
                    robust=None, backend=backend)  # fmt: skip


def test_torch_solver_gives_a_point_last_light_basis_the_same_estimates():
    """The light basis as the transpose of a contiguous ``(B, L, N)`` (a large batch's step writes it so into its
    workspace) gives the torch solver's estimates bit for bit as the contiguous ``(B, N, L)`` basis: the solver lays
    it out as the latter before its batched products, whose roundings depend on the layout (the point-last
    basis's own layout changed the last bits of 16 streams' estimates on the pose sweep)."""
    tpl, image, cam, x_true, light_basis = _synthetic_problem(N=400)
    x0 = _perturbed(x_true)
    point_last = light_basis.transpose(1, 2).contiguous().transpose(1, 2)
    want = _solve(tpl, image, cam, x0, light_basis, robust=RobustLoss(RobustKind.TUKEY), iterations=6)
    got = _solve(tpl, image, cam, x0, point_last, robust=RobustLoss(RobustKind.TUKEY), iterations=6)
    for w, g in zip(want[:4], got[:4]):
        assert torch.equal(w, g)
    assert torch.equal(want[4].residual, got[4].residual)
