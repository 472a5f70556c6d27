"""torchface._compiling: the ``torch.compile`` check on every torch pyproject.toml accepts (``torch>=2.1``)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import torch

from torchface._compiling import is_compiling


def test_is_compiling_is_false_in_eager_code_and_true_while_traced():
    seen = []

    def f(x):
        seen.append(is_compiling())
        return x + 1

    f(torch.zeros(1))
    torch.compile(f, backend="eager")(torch.zeros(1))
    assert seen[0] is False and seen[-1] is True


def test_torchface_runs_on_a_torch_without_torch_compiler_is_compiling():
    """``torch.compiler.is_compiling`` came with torch 2.3; on torch 2.1 and 2.2 (accepted by pyproject.toml) the
    kernel dispatch asked it at the first native kernel and raised ``AttributeError``: no frame could be tracked.
    A child process without it (``torch._utils.is_compiling``: False, as torch 2.2's in eager code) tracks, makes
    a normalised face and runs training_hooks' layer check."""
    code = textwrap.dedent("""
        import kornia  # (kornia 0.9 needs it: an older kornia comes with an older torch)
        import torch
        del torch.compiler.is_compiling
        torch._utils.is_compiling = lambda: False  # torch 2.1 / 2.2's flag, False outside a traced region
        torch.set_num_threads(1)
        from torchface.backend import Backend, use_native
        from torchface.geometry.camera import Intrinsics
        from torchface.model import load_candide3
        from torchface.normalise import build_normalised_layout, normalised_face
        from torchface._scalar import scalar
        from training_hooks.layer import _tracked
        x = torch.zeros(2)
        use_native(Backend.AUTO, (x,), "test")
        assert float(scalar(0.5, x)) == 0.5
        m = load_candide3()
        lay = build_normalised_layout(m, 16)
        cam = Intrinsics.default(64, 48)
        frames = torch.rand(1, 3, 48, 64, generator=torch.Generator().manual_seed(0))
        out = normalised_face(frames, m, lay, torch.zeros(1, m.num_shape), torch.zeros(1, m.num_animation),
                              torch.tensor([[0.05, 0.1, 0.0]]), torch.tensor([[0.0, 0.0, 400.0]]), None, cam)
        assert out.mask.sum() > 50
        assert _tracked(len) is len
        print("ok")
    """)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and run.stdout.strip() == "ok", (run.returncode, run.stderr[-2000:])


def test_an_older_torchs_transforms_are_read_value_by_value_and_refused_by_a_step(monkeypatch):
    """torch 2.5 to 2.9 could not ``.tolist()`` a ``torch.func`` transform's tensor ("Cannot access data pointer of
    Tensor that doesn't have storage"; ``.item()`` worked): the frames' and faces' checks read one value at a time
    there, and a tracking step, which reads values in many places, is refused in one line. Simulated on this torch
    (the flag forced)."""
    import pytest

    from torchface import _compiling
    from torchface._compiling import check_reverse_mode, host_values

    monkeypatch.setattr(_compiling, "TRANSFORMS_READ_VALUES", False)
    seen = []

    def f(x: torch.Tensor) -> torch.Tensor:
        values = torch.stack([x.amin(), x.amax()])
        seen.append(host_values(values))
        with pytest.raises(RuntimeError, match=r"^a step under a torch.func transform needs torch 2.10 or later \("):
            check_reverse_mode("a step", x)
        return x.sum()

    x = torch.tensor([0.25, -1.5, 3.0], dtype=torch.float64)
    torch.func.grad(f)(x)
    assert seen == [[-1.5, 3.0]]
    check_reverse_mode("a step", x)  # outside a transform: nothing to refuse
    assert host_values(torch.tensor([1, 2])) == [1, 2]
