"""The per-frame objective (paper Eq. 12-20): residuals and analytic Jacobian of the joint warp + light model.

For template points ``X_0`` with expression basis ``B_j``, normals ``n`` and intensities ``T``:

    ``X(alpha) = X_0 + sum_j alpha_j B_j``               (Eq. 3-9, head frame)
    ``x = pi(R(omega) X(alpha) + t)``                    (Eq. 14-16, pinhole projection)
    ``r = I(x) - T - sum_i lambda_i B^light_i``          (Eq. 19-20)

The Jacobian is ``dr/dp = grad I(x) . dx/dp`` for the warp parameters ``p = (omega, t, alpha)`` (Eq. 17)
and ``-B^light_i`` for the light. The light basis uses normals rotated by the rotation at the start of the
frame (held fixed within the frame), so the Jacobian is exact for the residual as defined.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchface._autocast import full_precision
from torchface._compiling import is_compiling, is_transformed
from torchface._scalar import isfinite
from torchface.appearance.sampling import sample_at_pixels
from torchface.geometry.camera import Intrinsics
from torchface.geometry.projection import in_front, project_points, project_points_jacobian
from torchface.geometry.so3 import axis_angle_to_matrix, rotate_points_jacobian
from torchface.template.points import Template
from torchface.tracker.params import ParamLayout


#: Values (streams times 3 N) per chunk of :func:`_expression_offsets`' loop: a chunk's sum and product (512 KB
#: each in float32) stay in a core's cache across its ``A`` passes, in few chunks (each pass over a chunk is
#: four dispatched operations). At 128 streams, 1500 points, one thread: 2**15 to 2**20 values a chunk took
#: 19-27 ms (median of 9, a loaded machine), 2**17 the least, against 31 ms for the matmul.
_OFFSET_CHUNK_VALUES: int = 1 << 17

#: The fewest streams times points for which :func:`_expression_offsets` takes its loop (below, the matmul: at one
#: stream the loop's ``2 A`` dispatched operations per chunk cost more than the matmul's broadcast copy).
_OFFSET_LOOP_MIN_POINTS: int = 16384


def _expression_offsets(template: Template, alpha: Tensor) -> Tensor | None:
    """``(B, 3, N)`` point-last ``sum_j alpha_j B_j`` with the same values as the broadcast matmul
    ``torch.matmul(template.basis, alpha[:, None, :, None])``, or None where this does not hold or does not pay.

    That matmul broadcasts ``alpha (B, 1, A, 1)`` over the ``N`` points: it copied ``alpha`` to ``(B N, A, 1)``
    (8.4 MB at 128 streams, 1500 points, 11 units: three a step, one per level, in the visibility test) and ran
    ``B N`` products of ``(3, A)`` by ``(A, 1)`` in torch's small-matrix kernel (``3 A < 400``), which sums the ``A``
    products one after another from 0, each product and sum rounded to the dtype. Here the same sums run over the
    template's point-last basis (:attr:`Template.point_last`, ``(B, A, 3, N)``, cached with the template: the fast
    solver's), a chunk of streams at a time: its first product, then each next one added (separate multiplies and
    adds: the same roundings; ``addcmul`` fuses them on a CPU with FMA, which changes the last bit; a sum of products
    that are all -0 stays -0 here, +0 there: equal values). One call at 128
    streams, 1500 points, one thread, on a loaded machine: 20 ms against the matmul's 31 (medians of 9).

    Only on the CPU, for float32 or float64 tensors of one dtype that ask for no gradient (nor tangent, nor
    ``torch.compile``), ``alpha`` ``(B, A)`` as the template's ``B`` (the matmul broadcasts a template of one sample
    over the streams' parameters; this does not), ``3 A < 400`` (the matmul's small-matrix kernel) and at least
    :data:`_OFFSET_LOOP_MIN_POINTS` streams times points; None elsewhere (the caller runs the matmul)."""
    basis = template.basis
    B, N, _, A = basis.shape
    tensors = (basis, template.points, alpha)
    if (
        B * N < _OFFSET_LOOP_MIN_POINTS or A == 0 or 3 * A >= 400 or alpha.shape != (B, A)
        or basis.dtype not in (torch.float32, torch.float64)
        or any(x.dtype != basis.dtype or x.device.type != "cpu" for x in tensors)
        or (torch.is_grad_enabled() and any(x.requires_grad for x in tensors))
        or is_compiling() or is_transformed(*tensors)
    ):  # fmt: skip
        return None
    basis_t = template.point_last[2]  # (B, A, 3, N)
    a = alpha.reshape(B, A, 1, 1)
    out = torch.empty(B, 3, N, dtype=basis.dtype, device=basis.device)
    step = max(1, _OFFSET_CHUNK_VALUES // (3 * N))
    product = torch.empty(min(step, B), 3, N, dtype=basis.dtype, device=basis.device)
    for first in range(0, B, step):
        last = min(first + step, B)
        acc, b, w, p = out[first:last], basis_t[first:last], a[first:last], product[: last - first]
        torch.mul(b[:, 0], w[:, 0], out=acc)
        for j in range(1, A):
            acc.add_(torch.mul(b[:, j], w[:, j], out=p))
    return out


def warp_points(
    template: Template, layout: ParamLayout, x: Tensor, R: Tensor | None = None, *, out: Tensor | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """Template points under parameters ``x``.

    Args:
        template: ``N`` points per sample; layout: the packing of ``x``; x: ``(B, P)``.
        R: ``(B, 3, 3)`` the rotation of ``x``'s axis-angle, when the caller has it (not differentiated
            through ``x`` then).
        out: a ``(B, N, 3)`` tensor (a view into a larger one may be) that ``points_cam`` is written into and
            returned as, with the same values (without autograd: ``out=`` arguments do not support it); None: a new
            tensor.

    Returns:
        ``points_model (B, N, 3)``, ``points_cam (B, N, 3)`` and the rotation ``(B, 3, 3)``.
    """
    aa, t, alpha, _ = layout.split(x)
    offsets = _expression_offsets(template, alpha)
    if offsets is None:
        points_model = template.points + torch.matmul(template.basis, alpha[:, None, :, None]).squeeze(-1)
    else:
        points_model = template.points + offsets.transpose(1, 2)
    R = axis_angle_to_matrix(aa) if R is None else R
    points_cam = torch.matmul(points_model, R.transpose(1, 2))
    points_cam = points_cam + t.unsqueeze(1) if out is None else torch.add(points_cam, t.unsqueeze(1), out=out)
    return points_model, points_cam, R


@full_precision
def frame_residuals(
    x: Tensor,
    layout: ParamLayout,
    template: Template,
    image: Tensor,
    intrinsics: Intrinsics,
    light_basis: Tensor,
    point_mask: Tensor,
) -> tuple[Tensor, Tensor, Tensor]:
    """Residuals, Jacobian and validity of Eq. 20 at ``x``.

    Args:
        x: ``(B, P)`` packed parameters.
        layout: the packing.
        template: ``N`` template points per sample.
        image: ``(B, 3, H, W)`` the frame's gray level and its ``d/du``, ``d/dv``
            (:func:`~torchface.appearance.sampling.image_with_gradients`) at ``intrinsics``' size.
        intrinsics: camera of ``image``.
        light_basis: ``(B, N, L)`` illumination basis (:func:`~torchface.appearance.illumination_basis`).
        point_mask: ``(B, N)`` bool, points usable this frame (template validity and visibility).

    Returns:
        ``r (B, N)``, ``J (B, N, P)`` and ``valid (B, N)``: inside the image, in front of the camera,
        facing the camera, in ``point_mask``, and sampling no missing (non-finite) pixel of ``image``: such a point
        is left out (``r`` and ``J`` are not finite there without autograd, and finite under it, so that the
        gradients stay finite), as the fast solver leaves it out.
    """
    aa, t, alpha, light = layout.split(x)
    points_model, points_cam, R = warp_points(template, layout, x)
    uv = project_points(points_cam, intrinsics)
    values, inside = sample_at_pixels(image, uv)
    seen = isfinite(values.detach()).all(-1)  # (B, N)
    if torch.is_grad_enabled() and not bool(seen.all()) and any(
        v.requires_grad for v in (x, image, light_basis, template.points, template.basis, template.intensity)
    ):
        # The sampler's backward multiplies the left-out points' zero gradient by the missing pixels, and so do
        # the Jacobian's products: NaN gradients everywhere. Sample a copy with 0 there (the same values elsewhere).
        values, _ = sample_at_pixels(torch.nan_to_num(image, nan=0.0, posinf=0.0, neginf=0.0), uv)
    intensity, grad = values[..., 0], values[..., 1:3]
    predicted = template.intensity + torch.matmul(light_basis, light.unsqueeze(-1)).squeeze(-1)
    r = intensity - predicted

    d_uv = project_points_jacobian(points_cam, intrinsics)  # (B, N, 2, 3)
    g_cam = torch.matmul(grad.unsqueeze(-2), d_uv)  # dI/dX_cam (B, N, 1, 3)
    j_rot = torch.matmul(g_cam, rotate_points_jacobian(aa, points_model)).squeeze(-2)
    g_model = torch.matmul(g_cam.squeeze(-2), R)  # dI/dX_model (B, N, 3)
    j_anim = torch.matmul(g_model.unsqueeze(-2), template.basis).squeeze(-2)
    g_cam = g_cam.squeeze(-2)
    J = torch.cat([j_rot, g_cam, j_anim, -light_basis], dim=-1)

    normals_cam = torch.matmul(template.normals, R.transpose(1, 2))
    facing = (normals_cam * points_cam).sum(-1) < 0
    valid = point_mask & inside & in_front(points_cam) & facing & seen
    return r, J, valid
