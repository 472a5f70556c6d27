"""Tests for the native level solver (torchface._native, :class:`~torchface.backend.Backend`): the fast
path against the slow reference (the torch code of :func:`~torchface.tracker.fast.solve_level`, one stream at a
time), batch and thread consistency, non-finite frames, the fallbacks and the build."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from torchface import _native
from torchface.geometry.so3 import geodesic_angle_deg
from torchface.solver.robust import RobustKind, RobustLoss, SwitchedRobustLoss
from torchface.template import Template
from torchface.backend import Backend
from torchface.tracker.fast import LevelCamera, solve_level

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_fast import D, LAYOUT, A, _perturbed, _synthetic_problem, split  # noqa: E402

pytestmark = pytest.mark.skipif(
    _native.library() is None, reason=f"native solver unavailable: {_native.unavailable_reason()}"
)

TORCH, NATIVE = Backend.TORCH, Backend.NATIVE


def _noisy_problem(B: int = 3, seed: int = 5):
    """The synthetic problem of test_fast with noise and 15 % gross outliers on the template, so that the robust
    weights, the scale and the step acceptance all have work to do, and a start 1.5 degrees off."""
    parts = [_synthetic_problem(B=2, N=400, seed=seed + k) for k in range((B + 1) // 2)]  # two streams each

    def cat(xs):
        return torch.cat(list(xs))[:B]

    tpl = Template(*(cat(getattr(p[0], f) for p in parts) for f in parts[0][0].__dataclass_fields__))
    image, x_true, light_basis = (cat(p[i] for p in parts) for i in (1, 3, 4))
    c = parts[0][2]
    cam = LevelCamera(c.fx, c.fy, c.cx, c.cy, cat(p[2].offset for p in parts), c.height, c.width)
    g = torch.Generator().manual_seed(seed)
    T = tpl.intensity + 0.003 * torch.randn(tpl.intensity.shape, generator=g, dtype=D)
    bad = torch.rand(T.shape, generator=g, dtype=D) < 0.15
    T = torch.where(bad, T + 0.4, T)
    tpl = Template(tpl.face_index, tpl.bary, tpl.points, tpl.basis, tpl.normals, T, tpl.valid)
    x0 = _perturbed(x_true)
    if B > 1:
        x0[1] = _perturbed(x_true, 0.5)[1]  # the streams start at different distances from the truth
    return tpl, image, cam, x0, light_basis


def _select(tpl: Template, image, cam: LevelCamera, b: int):
    one = Template(*(getattr(tpl, f)[b : b + 1] for f in tpl.__dataclass_fields__))
    return one, image[b : b + 1], LevelCamera(cam.fx, cam.fy, cam.cx, cam.cy, cam.offset[b : b + 1], cam.height, cam.width)


SETTINGS = {
    "l2": dict(robust=None),
    "tukey": dict(robust=RobustLoss(RobustKind.TUKEY, 4.685)),
    "huber": dict(robust=RobustLoss(RobustKind.HUBER, 1.345)),
    "cauchy": dict(robust=RobustLoss(RobustKind.CAUCHY)),
    "geman_mcclure": dict(robust=RobustLoss(RobustKind.GEMAN_MCCLURE)),
    "none_kind": dict(robust=RobustLoss(RobustKind.NONE)),
    "switched": dict(robust="switched"),
    "prior_centred": dict(robust=RobustLoss(RobustKind.TUKEY, 4.685), alpha_prior=1.0, alpha_mean=0.2),
    "prior_per_stream": dict(robust=None, alpha_prior="per_stream"),
    "prior_per_unit": dict(robust=RobustLoss(RobustKind.TUKEY, 4.685), alpha_prior="per_unit", alpha_mean=0.1),
    "pose_fixed": dict(robust=RobustLoss(RobustKind.TUKEY, 4.685), free="pose_fixed", alpha_prior=0.1),
    "no_light": dict(robust=RobustLoss(RobustKind.TUKEY, 4.685), free="no_light"),
    "intermediate": dict(robust=RobustLoss(RobustKind.TUKEY, 4.685), final_check=False),
    "residuals_only": dict(robust=RobustLoss(RobustKind.TUKEY, 4.685), keep_linearisation=False),
    "ftol": dict(robust=RobustLoss(RobustKind.TUKEY, 4.685), function_tolerance=3e-3, step_tolerance=(2e-4, 0.05, 2e-3)),
    "no_iterations": dict(robust=None, iterations=0),
    "at_bounds": dict(robust=RobustLoss(RobustKind.TUKEY, 4.685), bounds=(-0.1, 0.3), step_tolerance=(2e-4, 0.05, 2e-3)),
}


def _arguments(setting: dict, B: int, dtype=D) -> dict:
    s = dict(setting)
    free = torch.ones(LAYOUT.size, dtype=torch.bool)
    kind = s.pop("free", None)
    if kind == "pose_fixed":
        free[0:6] = False
    elif kind == "no_light":
        free[LAYOUT.illumination] = False
    prior = s.pop("alpha_prior", 0.0)
    if prior == "per_stream":
        prior = torch.tensor([50.0, 0.01, 1.0][:B], dtype=dtype)
    elif prior == "per_unit":  # (B, A): each stream and unit its own precision
        prior = torch.logspace(-2, 2, B * A, dtype=dtype).reshape(B, A).flip(-1)
    mean = s.pop("alpha_mean", None)
    robust = s.pop("robust")
    if robust == "switched":
        switch = torch.tensor([[True], [False], [True]][:B])
        robust = SwitchedRobustLoss(RobustLoss(RobustKind.TUKEY, 4.685), RobustLoss(RobustKind.HUBER, 4.685), switch)
    lo, hi = s.pop("bounds", (-5.0, 5.0))  # (-0.1, 0.3): some of the truth's units (-0.4 .. 0.5) held at a bound
    args = dict(
        iterations=s.pop("iterations", 8), free=free, alpha_lower=torch.full((A,), lo, dtype=dtype),
        alpha_upper=torch.full((A,), hi, dtype=dtype), alpha_prior=prior, robust=robust,
        alpha_mean=None if mean is None else torch.full((B, A), mean, dtype=dtype), scale_floor=0.002,
        step_tolerance=s.pop("step_tolerance", 1e-8), function_tolerance=s.pop("function_tolerance", 0.0),
    )
    args.update(s)
    return args


def _stream_args(args: dict, b: int) -> dict:
    """``args`` for stream ``b`` alone."""
    out = dict(args)
    if isinstance(args["alpha_prior"], torch.Tensor):
        out["alpha_prior"] = args["alpha_prior"][b : b + 1]
    if args["alpha_mean"] is not None:
        out["alpha_mean"] = args["alpha_mean"][b : b + 1]
    if isinstance(args["robust"], SwitchedRobustLoss):
        sw = args["robust"]
        out["robust"] = sw.alternative if bool(sw.switch[b, 0]) else sw.base
    return out


@pytest.mark.parametrize("name", list(SETTINGS))
def test_native_equals_the_torch_code_stream_by_stream_float64(name):
    """In float64 the native solver on the batch gives what the torch code gives on each stream alone (its batch
    semantics), to rounding: the estimate, the iteration counts, the flags, the final residuals and the
    linearisation handed on (whose Jacobian the native solver zeroes where a point is not valid)."""
    tpl, image, cam, x0, light_basis = _noisy_problem()
    B = x0.shape[0]
    args = _arguments(SETTINGS[name], B)
    R, t, a, lam = split(x0)
    nat = solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, backend=NATIVE, **args)
    moved = False
    for b in range(B):
        tb, ib, cb = _select(tpl, image, cam, b)
        ref = solve_level(tb, ib, cb, R[b : b + 1], t[b : b + 1], a[b : b + 1], lam[b : b + 1], light_basis[b : b + 1],
                          tb.valid, backend=TORCH, **_stream_args(args, b))  # fmt: skip
        assert float(geodesic_angle_deg(nat[0][b : b + 1], ref[0])) < 1e-7
        for got, want in zip(nat[1:4], ref[1:4]):
            torch.testing.assert_close(got[b : b + 1], want, rtol=0, atol=1e-8)
        o, r = nat[4], ref[4]
        for field in ("iterations", "converged", "finite", "valid"):
            assert torch.equal(getattr(o, field)[b : b + 1], getattr(r, field)), field
        v = r.valid
        torch.testing.assert_close(o.residual[b : b + 1][v], r.residual[v], rtol=0, atol=1e-9)
        torch.testing.assert_close(o.sampled[b : b + 1], r.sampled, rtol=0, atol=1e-9)
        assert (o.linearisation is None) == (r.linearisation is None)
        if r.linearisation is not None:
            vr = r.linearisation[2]
            assert torch.equal(o.linearisation[2][b : b + 1], vr)
            torch.testing.assert_close(o.linearisation[1][b : b + 1][vr], r.linearisation[1][vr], rtol=1e-7, atol=1e-9)
        moved |= float((nat[2][b] - a[b]).abs().max()) > 1e-4
    assert moved or args["iterations"] == 0  # the solve did something (so agreement says something)


def test_native_batch_is_each_stream_alone_and_independent_of_threads():
    """Streams are solved independently: the batch equals each stream alone bit for bit, with 1 or 3 threads."""
    tpl, image, cam, x0, light_basis = _noisy_problem()
    args = _arguments(SETTINGS["tukey"], 3)
    R, t, a, lam = split(x0)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, backend=NATIVE, **args)
        torch.set_num_threads(3)
        three = solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, backend=NATIVE, **args)
    finally:
        torch.set_num_threads(threads)
    for got, want in zip(one[:4], three[:4]):
        assert torch.equal(got, want)
    assert torch.equal(one[4].residual, three[4].residual)
    for b in range(3):
        tb, ib, cb = _select(tpl, image, cam, b)
        alone = solve_level(tb, ib, cb, R[b : b + 1], t[b : b + 1], a[b : b + 1], lam[b : b + 1], light_basis[b : b + 1],
                            tb.valid, backend=NATIVE, **args)  # fmt: skip
        for got, want in zip(one[:4], alone[:4]):
            assert torch.equal(got[b : b + 1], want)


def test_native_float32_is_the_torch_code_to_float_rounding():
    tpl, image, cam, x0, light_basis = _noisy_problem()
    f = torch.float32
    tpl32 = Template(*(x.float() if x.is_floating_point() else x for x in (getattr(tpl, k) for k in tpl.__dataclass_fields__)))
    cam32 = LevelCamera(cam.fx, cam.fy, cam.cx, cam.cy, cam.offset.float(), cam.height, cam.width)
    args = _arguments(SETTINGS["tukey"], 3, dtype=f)
    R, t, a, lam = (p.float() for p in split(x0))
    outs = [solve_level(tpl32, image.float(), cam32, R, t, a, lam, light_basis.float(), tpl.valid, backend=be, **args)
            for be in (NATIVE, TORCH)]  # fmt: skip
    nat, ref = outs
    assert nat[0].dtype == torch.float32 and nat[4].residual.dtype == torch.float32
    assert float(geodesic_angle_deg(nat[0].double(), ref[0].double()).max()) < 2e-3
    torch.testing.assert_close(nat[1], ref[1], rtol=0, atol=2e-3)
    torch.testing.assert_close(nat[2], ref[2], rtol=0, atol=2e-4)
    torch.testing.assert_close(nat[3], ref[3], rtol=0, atol=2e-4)


def test_a_non_finite_frame_is_reported_as_the_torch_code_reports_it():
    """A frame of NaN: no point is valid, the solve is reported failed (not finite), the estimate does not move,
    nothing is NaN in it; as the torch code does."""
    tpl, image, cam, x0, light_basis = _noisy_problem(B=2)
    image = image.clone()
    image[0] = float("nan")
    args = _arguments(SETTINGS["tukey"], 2)
    R, t, a, lam = split(x0)
    nat = solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, backend=NATIVE, **args)
    ref = solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, backend=TORCH, **args)
    for out in (nat, ref):
        assert not bool(out[4].finite[0]) and bool(out[4].finite[1])
        assert int(out[4].valid[0].sum()) == 0
        assert torch.equal(out[0][0], R[0]) and torch.equal(out[2][0], a[0])
        assert all(bool(torch.isfinite(p).all()) for p in out[:4])


@pytest.mark.parametrize("value", [float("inf"), -float("inf"), float("nan")])
def test_non_finite_pixels_are_left_out_as_the_torch_code_leaves_them_out(value):
    """A block of infinite (or NaN) pixels where the face is: the points whose samples or gradient stencils touch
    it are left out and the rest is solved, as the torch code does. The native solver's finiteness tests were
    ``|x| <= inf``, true for an infinite pixel: its residual entered the cost and the whole frame FAILED (with
    template management, LOST) where the torch code tracked it."""
    tpl, clean, cam, x0, light_basis = _noisy_problem(B=2)
    image = clean.clone()
    h, w = image.shape[-2:]
    image[0, :, h // 2 - 4 : h // 2 + 4, w // 2 - 4 : w // 2 + 4] = value
    args = _arguments(SETTINGS["tukey"], 2)
    R, t, a, lam = split(x0)
    whole = solve_level(tpl, clean, cam, R, t, a, lam, light_basis, tpl.valid, backend=TORCH, **args)[4].valid
    nat = solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, backend=NATIVE, **args)
    ref = solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, backend=TORCH, **args)
    assert bool(nat[4].finite.all()) and bool(ref[4].finite.all())
    assert torch.equal(nat[4].valid, ref[4].valid)
    assert 0 < int(ref[4].valid[0].sum()) < int(whole[0].sum())  # points were left out, not all
    assert float(geodesic_angle_deg(nat[0], ref[0]).max()) < 1e-7
    torch.testing.assert_close(nat[1], ref[1], rtol=0, atol=1e-8)


def test_inputs_that_ask_for_gradients_take_the_torch_code_and_native_refuses_them():
    tpl, image, cam, x0, light_basis = _noisy_problem(B=1)
    args = _arguments(SETTINGS["l2"], 1)
    args["iterations"] = 2
    R, t, a, lam = split(x0)
    live = image.clone().requires_grad_(True)
    auto = solve_level(tpl, live, cam, R, t, a, lam, light_basis, tpl.valid, backend=Backend.AUTO, **args)
    ref = solve_level(tpl, live, cam, R, t, a, lam, light_basis, tpl.valid, backend=TORCH, **args)
    for got, want in zip(auto[:4], ref[:4]):  # AUTO ran the torch code (bit for bit its result)
        assert torch.equal(got, want)
    assert auto[4].residual.requires_grad  # and autograd recorded it
    with pytest.raises(RuntimeError, match="gradients"):
        solve_level(tpl, live, cam, R, t, a, lam, light_basis, tpl.valid, backend=NATIVE, **args)
    with pytest.raises(RuntimeError, match="one dtype"):
        solve_level(tpl, image.float(), cam, R, t, a, lam, light_basis, tpl.valid, backend=NATIVE, **args)


def test_without_the_library_auto_runs_the_torch_code_and_native_says_why(monkeypatch):
    tpl, image, cam, x0, light_basis = _noisy_problem(B=2)
    args = _arguments(SETTINGS["tukey"], 2)
    R, t, a, lam = split(x0)
    ref = solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, backend=TORCH, **args)
    monkeypatch.setattr(_native, "_library", None)
    monkeypatch.setattr(_native, "_reason", "no C compiler found (test)")
    auto = solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, backend=Backend.AUTO, **args)
    for got, want in zip(auto[:4], ref[:4]):
        assert torch.equal(got, want)
    with pytest.raises(RuntimeError, match="no C compiler found"):
        solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, backend=NATIVE, **args)


def test_native_available_says_whether_the_library_loads_and_why_not(monkeypatch):
    """The public question a package built on torchface asks (``training_hooks``' cache key records the answer)."""
    from torchface.backend import native_available, native_unavailable_reason

    assert native_available() == (_native.library() is not None)
    assert native_available() or native_unavailable_reason() == _native.unavailable_reason() is not None
    monkeypatch.setattr(_native, "_library", None)  # (library() was asked above: it is not built again)
    monkeypatch.setattr(_native, "_reason", "no C compiler found (test)")
    assert not native_available() and native_unavailable_reason() == "no C compiler found (test)"


def test_a_thread_asking_while_another_builds_the_library_waits_for_it(monkeypatch):
    """The first :func:`_native.library` calls from two threads at once: the second waits for the first's build
    and gets the library too (it used to get None, with no reason, and ran the torch code or raised)."""
    import threading
    import time

    build = _native._build

    def slow_build(*args, **kwargs):
        time.sleep(0.3)  # a compiler run: seconds
        return build(*args, **kwargs)

    for name, value in (("_library", None), ("_reason", None), ("_tried", False), ("_parallel", None),
                        ("_parallel_pid", -1), ("_build", slow_build)):  # fmt: skip
        monkeypatch.setattr(_native, name, value)
    got: list[tuple[bool, str | None]] = []

    def ask() -> None:
        got.append((_native.library() is not None, _native.unavailable_reason()))

    threads = [threading.Thread(target=ask) for _ in range(2)]
    threads[0].start()
    time.sleep(0.1)  # the first is building
    threads[1].start()
    for thread in threads:
        thread.join(timeout=60)
    assert got == [(True, None), (True, None)]


def _library_in_child(queue) -> None:
    queue.put(_native.library() is not None)


@pytest.mark.skipif(sys.platform != "linux", reason="fork start method")
def test_a_child_forked_while_a_thread_builds_the_library_does_not_hang(monkeypatch):
    """A data-loader worker forked while another thread of the parent builds the library: the child has no such
    thread to release the lock it held; it takes a lock of its own and loads the library itself (it hung)."""
    import multiprocessing
    import threading
    import time

    build = _native._build

    def slow_build(*args, **kwargs):
        time.sleep(0.6)  # a compiler run: seconds
        return build(*args, **kwargs)

    for name, value in (("_library", None), ("_reason", None), ("_tried", False), ("_parallel", None),
                        ("_parallel_pid", -1), ("_build", slow_build)):  # fmt: skip
        monkeypatch.setattr(_native, name, value)
    monkeypatch.setattr(_native, "_lock", threading.Lock())  # restored after, whichever lock the fork left
    builder = threading.Thread(target=_native.library)
    builder.start()
    time.sleep(0.2)  # the thread holds the lock, building
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_library_in_child, args=(queue,))
    child.start()
    try:
        assert queue.get(timeout=20)  # a hang fails here
    finally:
        child.join(timeout=10)
        if child.is_alive():
            child.kill()
        builder.join(timeout=60)
    assert child.exitcode == 0


_PROBE = (
    "import torchface._native as n; lib = n.library(); print('OK' if lib is not None else 'NONE', "
    "n.unavailable_reason())"
)


def _probe(env: dict[str, str], stderr: list[str] | None = None) -> str:
    out = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, env={**os.environ, **env},
                         timeout=600)  # fmt: skip
    assert out.returncode == 0, out.stderr
    if stderr is not None:
        stderr.append(out.stderr)
    return out.stdout.strip()


def test_the_library_is_built_into_the_cache_folder_once(tmp_path):
    env = {"TORCHFACE_CACHE_DIR": str(tmp_path)}
    assert _probe(env).startswith("OK")
    built = list((tmp_path / "native").glob("torchface_native-*.so"))
    assert len(built) == 1 and not list((tmp_path / "native").glob("*.partial"))
    umask = os.umask(0o022)
    os.umask(umask)
    # Readable by whom the umask allows, as any file the compiler writes (a shared cache folder serves every user):
    # it was built into a mkstemp file, readable by its builder alone.
    assert built[0].stat().st_mode & 0o444 == 0o444 & ~umask
    stamp = built[0].stat().st_mtime_ns
    assert _probe(env).startswith("OK")  # found, not built again
    assert built[0].stat().st_mtime_ns == stamp


def _fake_compiler(folder: Path) -> Path:
    """A stand-in C compiler that writes an empty output file (``-o FILE``) and logs its calls."""
    cc = folder / "fake-cc"
    cc.write_text('#!/bin/sh\necho "$@" >> "$0.log"\nwhile [ "$#" -gt 1 ]; do [ "$1" = -o ] && : > "$2"; shift; done\n')
    cc.chmod(0o755)
    return cc


#: A stand-in compiler that writes its output in two parts, with a wait between them that lasts until a second
#: compiler run has begun (5 s at most): a library read while it is being built is ``half`` instead of ``half+whole``.
_HALTING_COMPILER = r"""#!/bin/sh
out=; prev=
for arg in "$@"; do [ "$prev" = -o ] && out=$arg; prev=$arg; done
printf half > "$out"
echo start >> "$0.log"
n=0
while [ "$(grep -c start "$0.log")" -lt 2 ] && [ "$n" -lt 100 ]; do sleep 0.05; n=$((n + 1)); done
printf +whole >> "$out"
echo end >> "$0.log"
"""


def _build_in_child(queue, cc: str, after_a_start: bool) -> None:
    if after_a_start:  # the other process is mid-build: its output file is on disk, half written
        log, waited = Path(cc + ".log"), 0
        while not (log.exists() and "start" in log.read_text()) and waited < 400:
            time.sleep(0.025)
            waited += 1
    target = _native._build(cc)
    queue.put((str(target), target.read_text()))


@pytest.mark.skipif(sys.platform != "linux", reason="fork start method")
def test_two_processes_building_into_an_empty_cache_folder_each_get_a_whole_library(tmp_path, monkeypatch):
    """pytest-xdist workers (or data-loader workers) that import torchface at once on a fresh machine build the
    library into the same empty ``$TORCHFACE_CACHE_DIR/native`` at the same time. The second starts while the
    first's output is half written: it must not take that file for a built library, and each gets a whole one
    (both builds run; the last rename wins), with no temporary file left behind."""
    import multiprocessing

    monkeypatch.setenv("TORCHFACE_CACHE_DIR", str(tmp_path / "cache"))  # (empty: not even made yet)
    cc = tmp_path / "slow-cc"
    cc.write_text(_HALTING_COMPILER)
    cc.chmod(0o755)
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    children = [ctx.Process(target=_build_in_child, args=(queue, str(cc), second)) for second in (False, True)]
    for child in children:
        child.start()
    try:
        got = [queue.get(timeout=60) for _ in children]
    finally:
        for child in children:
            child.join(timeout=30)
            if child.is_alive():
                child.kill()
    assert [child.exitcode for child in children] == [0, 0]
    assert [text for _, text in got] == ["half+whole"] * 2  # (the second took the first's half-written file)
    assert Path(str(cc) + ".log").read_text().split() == ["start", "start", "end", "end"]  # the builds overlapped
    path = got[0][0]
    assert got[1][0] == path
    assert [p.name for p in (tmp_path / "cache" / "native").iterdir()] == [Path(path).name]  # no .partial left


def test_a_cached_build_is_named_by_the_cpu_it_was_built_for(tmp_path, monkeypatch):
    # The build asks for -march=native: a cache folder shared by machines with other CPUs (a network home folder)
    # must not hand one of them the other's library (AVX-512 instructions on a CPU without them: SIGILL).
    monkeypatch.setenv("TORCHFACE_CACHE_DIR", str(tmp_path / "cache"))
    cc = _fake_compiler(tmp_path)
    built = {}
    for cpu, flags in (("a", "fpu sse2 avx2"), ("b", "fpu sse2 avx2 avx512f"), ("a again", "fpu sse2 avx2")):
        info = tmp_path / f"cpuinfo-{cpu}"
        info.write_text(f"processor\t: 0\nvendor_id\t: GenuineIntel\nmodel name\t: X\nflags\t\t: {flags}\n"
                        f"cpu MHz\t\t: {len(cpu)}000.0\n\nprocessor\t: 1\n")  # fmt: skip
        monkeypatch.setattr(_native, "_CPUINFO", info, raising=False)
        built[cpu] = _native._build(str(cc))
    assert "-march=native" in Path(str(cc) + ".log").read_text()
    assert built["a"] != built["b"]  # another CPU's features: built again
    assert built["a again"] == built["a"]  # the same CPU (its clock aside): found in the cache
    assert len(Path(str(cc) + ".log").read_text().splitlines()) == 2


def test_without_a_home_folder_the_library_is_built_for_the_process_alone(tmp_path, monkeypatch):
    # HOME unset and a user id without a passwd entry (a container's arbitrary user): Path.home() raised
    # "Could not determine home directory" and the kernels were given up.
    monkeypatch.delenv("TORCHFACE_CACHE_DIR", raising=False)
    monkeypatch.delenv("HOME", raising=False)

    def no_home():
        raise RuntimeError("Could not determine home directory.")

    monkeypatch.setattr(Path, "home", staticmethod(no_home))
    monkeypatch.setattr(_native, "_private", None, raising=False)
    with pytest.warns(RuntimeWarning, match="Could not determine home directory.*TORCHFACE_CACHE_DIR"):
        target = _native._build(str(_fake_compiler(tmp_path)))
    assert target.is_file() and target.parent.name.startswith("torchface-native-")
    _native._remove_private(target.parent, os.getpid())


def test_a_cache_folder_given_with_a_tilde_is_in_the_home_folder(tmp_path, monkeypatch):
    # TORCHFACE_CACHE_DIR="~/cache" from a .env file or a container's environment (no shell to expand it): the
    # library went to a folder named "~" in the working folder.
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.setenv("TORCHFACE_CACHE_DIR", "~/cache")
    monkeypatch.chdir(tmp_path)
    target = _native._build(str(_fake_compiler(tmp_path)))
    assert target.parent == tmp_path / "home" / "cache" / "native" and not (tmp_path / "~").exists()


def test_the_built_library_is_readable_by_those_sharing_the_cache(tmp_path, monkeypatch):
    # Built in a mkstemp file (0600; 0711 once the linker has marked it executable), the library could not be loaded
    # by another user of a shared TORCHFACE_CACHE_DIR: "Permission denied", and the torch code ran.
    monkeypatch.setenv("TORCHFACE_CACHE_DIR", str(tmp_path / "cache"))
    target = _native._build(str(_fake_compiler(tmp_path)))
    assert target.stat().st_mode & 0o777 == 0o777 & ~_native._UMASK  # 0755 under the usual umask 022
    monkeypatch.setattr(_native, "_UMASK", 0o077)  # a private umask keeps it private (the first fix made it 0755)
    private = _native._build(str(_fake_compiler(tmp_path)) + " -DOTHER")
    assert private.stat().st_mode & 0o777 == 0o700


def test_a_compiler_given_with_arguments_as_make_takes_it(tmp_path, monkeypatch):
    # CC="ccache gcc" or "gcc -m64": the command and its arguments, as make and setuptools read $CC.
    monkeypatch.setenv("TORCHFACE_CACHE_DIR", str(tmp_path / "cache"))
    cc = _fake_compiler(tmp_path)
    target = _native._build(f"{cc} -DTORCHFACE_TEST=1")
    assert target.is_file()
    assert Path(str(cc) + ".log").read_text().startswith("-DTORCHFACE_TEST=1 -O3")
    with pytest.raises(RuntimeError, match="No closing quotation"):  # a reason, not a ValueError from the loader
        _native._build(f'{cc} "-DX')


def test_an_unwritable_cache_folder_builds_for_the_process_alone(tmp_path, monkeypatch):
    # A read-only home or a TORCHFACE_CACHE_DIR that cannot hold the folder: the kernels were given up (the torch
    # code ran, about twice as slow) with a warning to install a C compiler.
    not_a_folder = tmp_path / "file"
    not_a_folder.write_text("")
    monkeypatch.setenv("TORCHFACE_CACHE_DIR", str(not_a_folder))
    monkeypatch.setattr(_native, "_private", None, raising=False)
    with pytest.warns(RuntimeWarning, match="cannot be written.*TORCHFACE_CACHE_DIR"):
        target = _native._build(str(_fake_compiler(tmp_path)))
    assert target.is_file() and target.parent.name.startswith("torchface-native-")
    assert _native._build(str(tmp_path / "fake-cc")) == target  # found there by a later try
    _native._remove_private(target.parent, os.getpid())
    assert not target.parent.exists()


def _private_build_in_child(queue, cc: str) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        queue.put(str(_native._build(cc).parent))


@pytest.mark.skipif(sys.platform != "linux", reason="fork start method")
def test_a_worker_process_that_built_for_itself_removes_its_folder(tmp_path, monkeypatch):
    """A data-loader worker (a multiprocessing child, which ends with ``os._exit``: no atexit function runs) that
    built the library in a folder of its own, its cache folder unwritable, left that folder behind: one per worker
    and epoch."""
    import multiprocessing

    not_a_folder = tmp_path / "file"
    not_a_folder.write_text("")
    monkeypatch.setenv("TORCHFACE_CACHE_DIR", str(not_a_folder))
    monkeypatch.setattr(_native, "_private", None, raising=False)
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_private_build_in_child, args=(queue, str(_fake_compiler(tmp_path))))
    child.start()
    try:
        folder = Path(queue.get(timeout=60))
    finally:
        child.join(timeout=30)
        if child.is_alive():
            child.kill()
    assert child.exitcode == 0 and folder.name.startswith("torchface-native-")
    assert not folder.exists()


_OPENMP_PROBE = """
import torch
torch.set_num_threads(2)
torch.ones(1000, 1000).sum()  # torch's threads started
from torchface import _native
from tests.tracker.test_native import _noisy_problem, _arguments, SETTINGS, NATIVE, solve_level, split
tpl, image, cam, x0, light_basis = _noisy_problem()
R, t, a, lam = split(x0)
out = solve_level(tpl, image, cam, R, t, a, lam, light_basis, tpl.valid, backend=NATIVE, **_arguments(SETTINGS["tukey"], 3))
print(_native.uses_openmp(), len(_native._process_libgomp()), torch.cat([out[0].flatten(), out[1].flatten()]).tolist())
"""


def test_openmp_dispatch_shares_torchs_runtime_and_changes_no_result(tmp_path):
    """Where torch runs on GNU OpenMP (one libgomp in the process), the kernels' chunks run on its threads (no
    second runtime loaded); ``TORCHFACE_OPENMP=0`` keeps the thread pool. Both give the same solve, bit for bit."""
    env = {"TORCHFACE_CACHE_DIR": str(tmp_path), "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    results = []
    for flag in ("1", "0"):
        out = subprocess.run([sys.executable, "-c", _OPENMP_PROBE], capture_output=True, text=True,
                             env={**os.environ, **env, "TORCHFACE_OPENMP": flag}, timeout=600)  # fmt: skip
        assert out.returncode == 0, out.stderr
        uses, runtimes, values = out.stdout.strip().split(" ", 2)
        results.append(values)
        if flag == "0":
            assert uses == "False"
        elif sys.platform.startswith("linux") and "gomp" in " ".join(sorted(_native._process_libgomp())):
            assert uses == "True" and runtimes == "1"  # torch's runtime, and no other
    assert results[0] == results[1]


def _top_in_child(queue, score: torch.Tensor, k: int) -> None:
    torch.set_num_threads(1)  # as a data-loader worker: torch's own OpenMP threads do not survive the fork either
    index = torch.empty(score.shape[0], k, dtype=torch.int64)
    value = torch.empty(score.shape[0], k)
    prob = _native.TopProblem(B=score.shape[0], N=score.shape[1], k=k, score=score.data_ptr(),
                              out_index=index.data_ptr(), out_value=value.data_ptr())  # fmt: skip
    _native.run("top_pixels", False, prob, score.shape[0], 2)  # two chunks
    queue.put((_native.uses_openmp(), index.tolist()))


@pytest.mark.skipif(sys.platform != "linux", reason="fork start method")
def test_a_forked_child_runs_the_kernels_in_two_chunks():
    """After the parent ran a kernel in 2 chunks (on OpenMP's threads where it uses them), a forked child (a
    data-loader worker) runs it in 2 chunks on a thread pool of its own (OpenMP's threads, which stay with the
    parent, would hang it), with the parent's result."""
    import multiprocessing

    score = torch.rand(4, 5000, generator=torch.Generator().manual_seed(0))
    index = torch.empty(4, 100, dtype=torch.int64)
    value = torch.empty(4, 100)
    prob = _native.TopProblem(B=4, N=5000, k=100, score=score.data_ptr(), out_index=index.data_ptr(),
                              out_value=value.data_ptr())  # fmt: skip
    _native.run("top_pixels", False, prob, 4, 2)
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_top_in_child, args=(queue, score, 100))
    child.start()
    try:
        uses_openmp, child_index = queue.get(timeout=60)  # a hang fails here
    finally:
        child.join(timeout=30)
        if child.is_alive():
            child.kill()
    assert child.exitcode == 0
    assert not uses_openmp
    assert child_index == index.tolist() == torch.topk(score, 100, dim=1).indices.tolist()


def test_threads_that_grow_the_chunk_pool_at_once_all_get_their_results(monkeypatch):
    """Kernels run from several Python threads at once on the thread pool (TORCHFACE_OPENMP=0, a forked child),
    with different chunk counts: a thread that grows the pool shuts the old one down, and a thread that had taken
    the old one but not yet submitted its chunks raised 'cannot schedule new futures after shutdown'."""
    import threading

    score = torch.rand(64, 50, generator=torch.Generator().manual_seed(0))
    want = torch.topk(score, 5, dim=1).indices
    monkeypatch.setattr(_native, "_parallel", None)  # the pool, as without OpenMP's threads
    for name in ("_pool", "_pool_size", "_pool_pid"):  # restored after the trials
        monkeypatch.setattr(_native, name, getattr(_native, name))
    errors: list[str] = []
    wrong = []

    def top(chunks: int, barrier: threading.Barrier) -> None:
        index = torch.empty(64, 5, dtype=torch.int64)
        value = torch.empty(64, 5)
        prob = _native.TopProblem(B=64, N=50, k=5, score=score.data_ptr(), out_index=index.data_ptr(),
                                  out_value=value.data_ptr())  # fmt: skip
        barrier.wait()
        try:
            _native.run("top_pixels", False, prob, 64, chunks)
        except RuntimeError as exc:
            errors.append(str(exc))
            return
        if not torch.equal(index, want):
            wrong.append(chunks)

    for _ in range(30):
        monkeypatch.setattr(_native, "_pool", None)  # each trial as a fresh process's first kernels
        counts = (2, 3, 5, 9)
        barrier = threading.Barrier(len(counts))
        threads = [threading.Thread(target=top, args=(c, barrier)) for c in counts]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=60)
        _native._pool.shutdown(wait=True)
    assert not errors and not wrong, (errors[:1], wrong)


def test_turned_off_or_without_a_compiler_the_reason_is_given(tmp_path):
    err: list[str] = []
    assert _probe({"TORCHFACE_NATIVE": "0"}, err).startswith("NONE turned off by TORCHFACE_NATIVE=0")
    assert "RuntimeWarning" not in err[-1]  # the user's own choice: no warning
    missing = _probe({"TORCHFACE_CACHE_DIR": str(tmp_path), "CC": str(tmp_path / "no-such-cc")}, err)
    assert missing.startswith("NONE the native kernels could not be built"), missing
    assert err[-1].count("RuntimeWarning: torchface: native kernels unavailable") == 1, err[-1]  # said once


def test_an_unknown_switch_value_is_named_in_a_warning(monkeypatch):
    """``TORCHFACE_NATIVE=maybe`` was read as on without a word; any value but the documented ones now warns."""
    for value, on in (("0", False), (" Off ", False), ("no", False), ("1", True), ("TRUE", True), ("", True)):
        monkeypatch.setenv("TORCHFACE_OPENMP", value)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert _native._env_switch("TORCHFACE_OPENMP") is on, value
    monkeypatch.delenv("TORCHFACE_OPENMP")
    assert _native._env_switch("TORCHFACE_OPENMP") is True
    monkeypatch.setenv("TORCHFACE_OPENMP", "maybe")
    with pytest.warns(RuntimeWarning, match="TORCHFACE_OPENMP='maybe' is not a switch value"):
        assert _native._env_switch("TORCHFACE_OPENMP") is True
    err: list[str] = []
    assert _probe({"TORCHFACE_NATIVE": "maybe"}, err).startswith("OK")
    assert "RuntimeWarning: torchface: TORCHFACE_NATIVE='maybe' is not a switch value" in err[-1], err[-1]
    assert _probe({"TORCHFACE_NATIVE": "OFF"}, err).startswith("NONE turned off by TORCHFACE_NATIVE=OFF")


def test_tracking_with_either_backend_gives_the_same_poses():
    """A short rendered sequence tracked with the default configuration (native) and with the torch code: the
    same poses to a small fraction of a degree, the same statuses."""
    from test_step import BASE, gentle_spec, landmarks_of, run  # noqa: E402

    from torchface.model.candide import load_candide3
    from torchface.synth.sequence import render_sequence

    model = load_candide3()
    spec = gentle_spec("n", (10.0, -6.0, 3.0), (0.0, 0.0, 450.0), (5.0, -2.0, 8.0), {"AUV11 Jaw drop": 0.6})
    frames, gt = render_sequence(spec)
    frames, lm = frames.unsqueeze(0), landmarks_of((gt,))
    native, _ = run(model, replace(BASE, backend=NATIVE), frames, lm)
    torch_, _ = run(model, replace(BASE, backend=TORCH), frames, lm)
    for n, r in zip(native, torch_):
        assert float(geodesic_angle_deg(n.rotation.double(), r.rotation.double()).max()) < 0.02
        assert float((n.translation - r.translation).abs().max()) < 0.1
        assert torch.equal(n.status, r.status)



@pytest.fixture(scope="module")
def sweep():
    """A short pose sweep (320x240, 36 frames, head turning to +-45 degrees) and its first landmarks."""
    from torchface.synth.scenarios import make_scenario
    from torchface.synth.sequence import render_sequence

    frames, gt = render_sequence(make_scenario("pose_sweep", 36, 320, 240))
    return frames, gt


def test_native_confidence_equals_the_torch_path(sweep):
    """Template management's per-frame confidence in one native pass (``native_mosaic_confidence``) against the
    torch path (normalised face, dissimilarity against the entry's reference, inside fraction), frame by frame
    over a managed track whose mosaic grows to several entries, two streams (one offset): the same confidence,
    dissimilarity, inside fraction and normalised face to float32 rounding; in float64 on the last frame, to
    1e-9."""
    from torchface.geometry.camera import Intrinsics
    from torchface.model.candide import load_candide3
    from torchface.tracker import TrackerConfig
    from torchface.tracker.managed import _confidence, initialise_managed, managed_step

    frames, gt = sweep
    model = load_candide3()
    cfg = TrackerConfig()
    torch_cfg = replace(cfg, backend=TORCH)
    two = torch.stack([frames[:30], frames[6:36]])  # (2, 30, 3, H, W)
    lm = torch.stack([gt.landmarks_px[0], gt.landmarks_px[6]]).float()
    intr = Intrinsics.default(320, 240)
    state, _ = initialise_managed(model, cfg, two[:, 0], lm, intr)
    status = torch.zeros(2, dtype=torch.int64)
    worst = [0.0, 0.0, 0.0, 0.0]
    for i in range(1, two.shape[1]):
        state, _ = managed_step(model, cfg, state, two[:, i])
        ms = state.management
        nat = _confidence(model, cfg, ms, two[:, i], state, status)
        ref = _confidence(model, torch_cfg, ms, two[:, i], state, status)
        for k in range(3):
            worst[k] = max(worst[k], float((nat[k] - ref[k]).abs().max()))
        assert torch.equal(nat[3][1], ref[3][1])  # the same mask
        worst[3] = max(worst[3], float((nat[3][0] - ref[3][0]).abs().max()))
    assert int(ms.mosaic.num_entries.max()) >= 3 and int(ms.mosaic.num_entries.min()) >= 2  # entries aligned against
    # A patch whose Lucas-Kanade update straddles the tolerance (0.02 px) in float32 rounding stops an iteration
    # apart on the two paths, and the dissimilarity moves by its next update over the patches kept: at frame 21 of
    # stream 1 one of 8 patches ended 1.6e-3 px apart, the dissimilarity 3.1e-4 (the others within 4e-6 px); 2.5e-4
    # since the landmark fit solves in float64 (native against torch, not the fit's batching: still over 2e-4).
    assert max(worst[0], worst[2], worst[3]) < 2e-4 and worst[1] < 1e-3, worst
    # float64: the last frame's state in double precision
    m64 = load_candide3(dtype=torch.float64)

    def double(x):
        return x.double() if isinstance(x, torch.Tensor) and x.is_floating_point() else x

    def cast(obj):
        if isinstance(obj, torch.Tensor):
            return double(obj)
        if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
            return type(obj)(**{f.name: cast(getattr(obj, f.name)) for f in dataclasses.fields(obj) if f.init})
        if isinstance(obj, tuple):
            return type(obj)(*(cast(v) for v in obj)) if hasattr(obj, "_fields") else tuple(cast(v) for v in obj)
        return obj

    s64 = cast(state)
    f64 = two[:, -1].double()
    nat = _confidence(m64, cfg, s64.management, f64, s64, status)
    ref = _confidence(m64, torch_cfg, s64.management, f64, s64, status)
    for k in range(3):
        torch.testing.assert_close(nat[k], ref[k], rtol=0, atol=1e-9)
    torch.testing.assert_close(nat[3][0], ref[3][0], rtol=0, atol=1e-9)
    assert float(nat[0].min()) > 0.5  # the track is confident (so agreement says something)


def test_moving_a_tracker_where_it_is_between_steps_keeps_no_old_model_alive():
    """A ``.to()`` that changes nothing (a parent module's ``.to(device)`` before each training step) makes a new
    face model object and keeps the state; the native confidence's constants, kept on the state's normalised-face
    layout, were keyed by ``id(model)``: each step with a new model added a set holding that model, so the models
    (and the sets) piled up, one per step. Now the old models are freed."""
    import gc
    import weakref

    from torchface.synth.scenarios import make_scenario
    from torchface.synth.sequence import render_sequence
    from torchface.tracker import FaceTracker

    frames, gt = render_sequence(make_scenario("pose_sweep", 6, 160, 120))
    tracker = FaceTracker(refine_first=None)
    tracker.initialise(frames[:1], gt.landmarks_px[:1].float())
    old = []
    for t in range(1, 6):
        old.append(weakref.ref(tracker.model))
        tracker.to(torch.float32)
        tracker(frames[t : t + 1])
    assert tracker.state is not None  # the state was kept
    gc.collect()
    assert sum(r() is not None for r in old) == 0


def test_a_build_deletes_the_temporary_files_of_killed_builds(tmp_path, monkeypatch):
    # A process killed while it built the library (a data-loader worker terminated at shutdown, the OOM killer)
    # left its temporary file, nearly a library's size, in the cache folder for good.
    monkeypatch.setenv("TORCHFACE_CACHE_DIR", str(tmp_path / "cache"))
    folder = tmp_path / "cache" / "native"
    folder.mkdir(parents=True)
    stale = folder / "torchface_native-0123456789abcdef.so.x1y2z3.partial"
    fresh = folder / "torchface_native-0123456789abcdef.so.a1b2c3.partial"  # a build running now
    other = folder / "notes.partial"  # not a build's
    for f in (stale, fresh, other):
        f.write_bytes(b"\0" * 100)
    old = stale.stat().st_mtime - 2 * 24 * 3600
    os.utime(stale, (old, old))
    os.utime(other, (old, old))
    target = _native._build(str(_fake_compiler(tmp_path)))
    assert target.parent == folder and target.is_file()
    assert not stale.exists() and fresh.exists() and other.exists()
