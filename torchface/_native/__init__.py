"""Compiled kernels of torchface's hot loops, built from C source at first use and called through ctypes.

At one stream a tracking step's level solves are thousands of small tensor operations, and their dispatch, not
their arithmetic, is most of the step's time; at many streams the same loops stream every intermediate through
memory. :func:`library` compiles ``kernels.c`` with the machine's C compiler into a shared library, caches it,
and loads it. ``kernels.c`` includes, each as its torch code computes it:

- ``level_solver.h``: one pyramid level's Levenberg-Marquardt solve per stream
  (:func:`torchface.tracker.fast.solve_level`);
- ``dissimilarity.h``: the dissimilarity confidence's smoothing and patch tracking, and a reference's patches;
- ``normalised_face.h``: the normalised face without the z-buffer;
- ``confidence.h``: the last two (and the nearest mosaic entry) as template management's per-frame confidence;
- ``coverage.h``: the rasterizer's coverage (z-buffer) and its per-triangle coefficients;
- ``select_pixels.h``: a template's candidate pixels and their selection scores;
- ``management.h``: template management's per-frame decisions (entry selection, gating);
- ``template_at.h``: a template from its compact form;
- ``top_pixels.h``: the top-k of a template's candidate pixels (a stable descending sort's first k), and the
  template's pixels there;
- ``gray_pyramid.h``: a tracking step's gray crop pyramid (:func:`torchface.tracker.step.gray_crop_pyramid`);
- ``visible.h``: which surface points the camera sees, given the coverage
  (:func:`torchface.rendering.visibility.points_visible`).

:func:`run` calls a kernel over a batch. It needs only a C compiler (``cc``, ``gcc`` or ``clang`` on the PATH, or
``$CC``, which may carry arguments as in make: ``CC="ccache gcc"``); where there is none, or the build fails, the
callers use their torch code instead (:func:`unavailable_reason` says why; :mod:`torchface.backend` decides).

The library is cached under ``$TORCHFACE_CACHE_DIR/native`` (default ``~/.cache/torchface/native``), named by a
hash of the source, the compiler and its flags and the CPU it was built for (``-march=native``: a cache shared by
machines with other CPUs, such as a network home folder, builds one library per CPU instead of handing a machine
instructions it lacks), so a changed source is built again; it is built into a temporary
file and renamed into place, so processes that build it at the same time (data-loader workers) do not see a
partial file (one left by a process killed mid-build is deleted by a later build once a day old). Where that
folder cannot be written (a read-only home), the library is built for the process alone in a temporary folder,
with a ``RuntimeWarning``. ``TORCHFACE_NATIVE=0`` in the environment turns the kernels off.

Switches read from the environment (``TORCHFACE_NATIVE``, ``TORCHFACE_OPENMP``): ``0``, ``false``, ``no`` or
``off`` (any case) turn the feature off; unset, empty, ``1``, ``true``, ``yes`` or ``on`` leave it on; any other
value leaves it on with a ``RuntimeWarning`` that names it (:func:`_env_switch`).

Floating-point: compiled with ``-ffp-contract=off`` (no fused multiply-adds), so a build gives the same results
on any x86-64 machine for the same inputs; the normal equations are accumulated in double precision.
"""

from __future__ import annotations

import atexit
import ctypes
import hashlib
import multiprocessing.util
import os
import platform
import shlex
import shutil
import subprocess
import tempfile
import threading
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

__all__ = ["library", "unavailable_reason", "run", "run_chunks", "LevelProblem", "LKProblem", "FaceProblem",
           "ConfProblem", "CoverProblem", "CoeffProblem", "SelectProblem", "ManageProblem", "CleanProblem",
           "TemplateProblem", "PickProblem", "PyramidProblem", "VisibleProblem", "LOSS_CODES"]

_SOURCE_DIR = Path(__file__).resolve().parent
_SOURCES = ("kernels.c", "level_solver.h", "dissimilarity.h", "normalised_face.h", "confidence.h", "coverage.h",
            "select_pixels.h", "management.h", "template_at.h", "top_pixels.h", "gray_pyramid.h",
            "visible.h")
#: The library's ABI version (``tf_abi_version``); a cached build of another version is not used.
_ABI_VERSION = 20
_FLAGS = ("-O3", "-ffp-contract=off", "-fPIC", "-shared", "-std=c11")
#: Tried first, then left out if the compiler refuses it.
_ARCH_FLAGS = ("-march=native",)
#: Tried first where torch's threads run on GNU OpenMP (:func:`_openmp_wanted`).
_OPENMP_FLAGS = ("-fopenmp",)
#: Age (seconds) after which a build's temporary file is taken for one left by a killed process and deleted.
_STALE_PARTIAL_S = 24 * 3600.0

#: ``torchface.solver.robust.RobustKind`` value -> the kernel's loss code.
LOSS_CODES = {"none": 0, "huber": 1, "cauchy": 2, "tukey": 3, "geman_mcclure": 4}

_lock = threading.Lock()


def _lock_of_its_own() -> None:
    """In a forked child (a data-loader worker): a new :data:`_lock`. The parent's may be held by one of its
    threads (one building the library), which the child does not have: the child would wait for it for ever."""
    global _lock
    _lock = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_lock_of_its_own)
_library: ctypes.CDLL | None = None
#: ``tf_parallel`` where the library was built with OpenMP and shares torch's runtime (:func:`run_chunks`), and
#: the process that loaded it (GNU OpenMP's threads do not survive a fork: a forked child uses the thread pool).
_parallel = None
_parallel_pid = -1
_reason: str | None = None
_tried = False


class LKProblem(ctypes.Structure):
    """``TFLKProblem`` of ``kernels.c`` (same field order): the dissimilarity's smoothing and patch tracking of a
    batch of normalised faces (see ``dissimilarity.h`` for the arrays' shapes)."""

    _fields_ = [
        *((name, ctypes.c_int) for name in ("B", "C", "G", "K", "n", "radius", "iterations", "project_out_bias",
                                            "has_max_displacement")),  # fmt: skip
        *((name, ctypes.c_double) for name in ("eps", "tolerance", "max_displacement")),
        *((name, ctypes.c_void_p) for name in (
            "normalised", "mask", "kernel", "grid", "templ", "sd", "ref_weight", "ref_total", "out_gray", "out_p",
            "out_support", "out_converged", "out_valid",
        )),  # fmt: skip
        ("radius_border", ctypes.c_int),
    ]


class FaceProblem(ctypes.Structure):
    """``TFFaceProblem`` of ``kernels.c`` (same field order): the normalised face of posed meshes without the
    z-buffer test (see ``normalised_face.h`` for the arrays' shapes)."""

    _fields_ = [
        *((name, ctypes.c_int) for name in ("B", "V", "F", "M", "C", "G", "height", "width")),
        *((name, ctypes.c_double) for name in ("fx", "fy", "cx", "cy", "min_facing_cos", "min_gain", "depth_eps")),
        *((name, ctypes.c_void_p) for name in ("verts", "normals", "back", "faces", "face_index", "pixel_index", "bary",
                                               "frames", "illumination", "out_image", "out_mask")),  # fmt: skip
    ]


class ConfProblem(ctypes.Structure):
    """``TFConfProblem`` of ``kernels.c`` (same field order): template management's per-frame confidence (see
    ``confidence.h`` for the arrays' shapes)."""

    _fields_ = [
        *((name, ctypes.c_int) for name in ("B", "V", "F", "M", "C", "G", "height", "width", "K", "n", "radius",
                                            "iterations", "project_out_bias", "has_max_displacement",
                                            "min_patches", "S", "A", "E")),  # fmt: skip
        *((name, ctypes.c_double) for name in ("fx", "fy", "cx", "cy", "min_facing_cos", "min_gain", "depth_eps", "eps",
                                               "tolerance", "max_displacement", "max_displacement_or_inf",
                                               "min_support", "min_present_fraction", "d0", "trim_fraction")),  # fmt: skip
        *((name, ctypes.c_void_p) for name in (
            "mean", "shape_units", "anim_units", "faces", "surface", "shape", "alpha", "R", "t", "ypr", "face_index",
            "pixel_index", "bary", "frames", "illumination", "rows", "mosaic_ypr", "used", "kernel", "patch_valid",
            "grid", "templ", "sd", "ref_weight", "ref_total", "out_entry", "out_image", "out_mask", "out_p",
            "out_support", "out_converged", "out_valid", "out_present", "out_dissimilarity", "out_confidence",
            "out_inside",
        )),  # fmt: skip
    ]


class CoverProblem(ctypes.Structure):
    """``TFCoverProblem`` of ``kernels.c`` (same field order): the rasterizer's coverage (see ``coverage.h``)."""

    _fields_ = [
        *((name, ctypes.c_int) for name in ("B", "F", "H", "W")),
        *((name, ctypes.c_double) for name in ("near", "fx", "fy", "cx", "cy", "margin", "max_projected")),
        *((name, ctypes.c_void_p) for name in ("coefficients", "ray_a", "ray_b", "tri", "usable", "front",
                                               "pix_to_face", "facing", "depth", "sizes", "starts")),  # fmt: skip
    ]


class CoeffProblem(ctypes.Structure):
    """``TFCoeffProblem`` of ``kernels.c`` (same field order): the rasterizer's per-triangle coefficients (see
    ``coverage.h``)."""

    _fields_ = [
        ("N", ctypes.c_int), ("large", ctypes.c_double), ("eps", ctypes.c_double),
        *((name, ctypes.c_void_p) for name in ("tri", "coefficients", "front", "usable", "scaled")),
    ]


class SelectProblem(ctypes.Structure):
    """``TFSelectProblem`` of ``kernels.c`` (same field order): a template's candidate pixels and scores (see
    ``select_pixels.h``)."""

    _fields_ = [
        *((name, ctypes.c_int) for name in ("B", "H", "W", "V", "F", "erode", "full_w", "batch_offset",
                                            "num_columns")),  # fmt: skip
        *((name, ctypes.c_double) for name in ("gradient_threshold", "min_facing_cos", "facing_margin", "fx", "fy", "cx",
                                               "cy")),  # fmt: skip
        *((name, ctypes.c_void_p) for name in ("gray", "pix_to_face", "facing", "coefficients", "ray_a", "ray_b",
                                               "verts", "normals", "faces", "offsets", "keys", "out_score")),
    ]


class ManageProblem(ctypes.Structure):
    """``TFManageProblem`` of ``kernels.c`` (same field order): template management's per-frame decisions (see
    ``management.h``)."""

    _fields_ = [
        *((name, ctypes.c_int) for name in ("B", "E", "lost_after", "lost_after_very_low", "recovery_every",
                                            "max_entries")),  # fmt: skip
        *((name, ctypes.c_double) for name in (
            "switch_margin_deg", "reference_radius_deg", "clean_radius_deg", "min_inside_fraction",
            "confidence_threshold", "very_low_confidence", "recover_confidence", "yaw_bin_deg", "pitch_bin_deg",
            "bin_centre_fraction", "entry_reach", "add_confidence",
        )),  # fmt: skip
        *((name, ctypes.c_void_p) for name in (
            "mosaic_ypr", "bins", "used", "ypr", "entry", "confidence", "inside", "failed", "lost", "low_count",
            "very_low_count", "since", "out_entry", "out_near", "out_confident", "out_low_count",
            "out_very_low_count", "out_lost", "out_reverted", "out_since", "out_attempt", "out_bins", "out_add",
        )),  # fmt: skip
    ]


class CleanProblem(ctypes.Structure):
    """``TFCleanProblem`` of ``kernels.c`` (same field order): the solve's clean-frame rule (see ``management.h``)."""

    _fields_ = [
        *((name, ctypes.c_int) for name in ("B", "N", "share_double")),
        *((name, ctypes.c_double) for name in ("scale_floor", "min_scale", "c", "fraction")),
        *((name, ctypes.c_void_p) for name in ("r", "valid", "near", "out_clean")),
    ]


class TemplateProblem(ctypes.Structure):
    """``TFTemplateProblem`` of ``kernels.c`` (same field order): a template from its compact form (see
    ``template_at.h``)."""

    _fields_ = [
        *((name, ctypes.c_int) for name in ("B", "V", "A", "N")),
        *((name, ctypes.c_void_p) for name in ("verts", "vertex_normals", "anim_units", "faces", "face_index", "bary",
                                               "out_points", "out_basis", "out_normals", "out_points_t",
                                               "out_normals_t", "out_basis_t", "out_rows")),  # fmt: skip
    ]


class TopProblem(ctypes.Structure):
    """``TFTopProblem`` of ``kernels.c`` (same field order): the k highest scores of each row (see
    ``top_pixels.h``)."""

    _fields_ = [
        ("B", ctypes.c_int), ("N", ctypes.c_int64), ("k", ctypes.c_int64),
        *((name, ctypes.c_void_p) for name in ("score", "out_index", "out_value")),
    ]


class PickProblem(ctypes.Structure):
    """``TFPickProblem`` of ``kernels.c`` (same field order): a template's pixels at its chosen candidates (see
    ``top_pixels.h``)."""

    _fields_ = [
        *((name, ctypes.c_int) for name in ("B", "H", "W", "F", "batch_offset")),
        ("k", ctypes.c_int64), ("num_columns", ctypes.c_int64),
        *((name, ctypes.c_void_p) for name in ("index", "value", "pix_to_face", "gray", "coefficients", "ray_a",
                                               "ray_b", "out_face", "out_bary", "out_intensity", "out_valid")),
    ]


class PyramidProblem(ctypes.Structure):
    """``TFPyramidProblem`` of ``kernels.c`` (same field order): a tracking step's gray crop pyramid (see
    ``gray_pyramid.h``; ``out`` points to an array of one pointer per level)."""

    _fields_ = [
        *((name, ctypes.c_int) for name in ("B", "height", "width", "levels")),
        *((name, ctypes.c_int64) for name in ("stride_frame", "stride_channel", "stride_row", "stride_col")),
        *((name, ctypes.c_void_p) for name in ("frames", "rows", "offsets", "out")),
    ]


class VisibleProblem(ctypes.Structure):
    """``TFVisibleProblem`` of ``kernels.c`` (same field order): which surface points the camera sees (see
    ``visible.h``)."""

    _fields_ = [
        *((name, ctypes.c_int) for name in ("B", "N", "H", "W", "F", "batch_offset", "faces_batched")),
        ("num_columns", ctypes.c_int64),
        *((name, ctypes.c_double) for name in ("fx", "fy", "cx", "cy", "near", "keep")),
        *((name, ctypes.c_void_p) for name in ("points", "point_faces", "pix_to_face", "facing", "coefficients",
                                               "ray_a", "ray_b", "out")),  # fmt: skip
    ]


class LevelProblem(ctypes.Structure):
    """``TFLevelProblem`` of ``level_solver.c`` (same field order): one level solve's sizes, settings, input and
    output arrays (pointers to contiguous tensors; see ``level_solver.h`` for their shapes)."""

    _fields_ = [
        *((name, ctypes.c_int) for name in ("B", "N", "A", "L", "P", "height", "width", "iterations", "final_check")),
        *((name, ctypes.c_double) for name in ("fx", "fy", "cx", "cy", "scale_floor", "damping",
                                               "function_tolerance")),  # fmt: skip
        *((name, ctypes.c_void_p) for name in (
            "image", "points", "normals", "basis", "intensity", "neg_light_basis", "offsets", "mask", "free",
            "R", "t", "alpha", "light", "alpha_lower", "alpha_upper", "alpha_mean", "alpha_prior", "loss_c",
            "step_tolerance", "loss_kind", "start_r", "start_J", "start_valid", "out_residual", "out_sampled",
            "out_J", "out_valid", "out_converged", "out_finite", "out_iterations",
        )),  # fmt: skip
    ]


def _compiler() -> str | None:
    cc = os.environ.get("CC")
    if cc:
        return cc
    for name in ("cc", "gcc", "clang"):
        path = shutil.which(name)
        if path:
            return path
    return None


#: Where :func:`_cpu_signature` reads the CPU's model and features (Linux).
_CPUINFO = Path("/proc/cpuinfo")
#: The ``/proc/cpuinfo`` fields that say what ``-march=native`` compiles for (x86, then ARM, RISC-V, POWER).
_CPU_FIELDS = ("vendor_id", "cpu family", "model", "model name", "flags", "CPU implementer", "CPU architecture",
               "CPU variant", "CPU part", "Features", "isa", "uarch", "cpu")  # fmt: skip


def _cpu_signature() -> str:
    """The CPU a ``-march=native`` build is for: the model and feature fields of ``/proc/cpuinfo``'s first
    processor (Linux), else :func:`platform.processor`. Part of the cached library's name, so that machines with
    other CPUs sharing a cache folder do not load a build with instructions they lack (``Illegal instruction``)."""
    try:
        first = _CPUINFO.read_text(errors="replace").split("\n\n")[0]
    except OSError:
        return platform.processor()
    fields = (line.partition(":") for line in first.splitlines())
    found = "\n".join(f"{key.strip()}:{value.strip()}" for key, _, value in fields if key.strip() in _CPU_FIELDS)
    return found or platform.processor()  # (no known field: every such machine would share one key)


def _process_umask() -> int:
    """The process's file-creation mask (read by setting it and putting it back: at import, before any thread of
    this module builds)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


#: The umask at import: the built library's mode is ``0o777 & ~_UMASK``.
_UMASK = _process_umask()


def _cache_dir() -> Path:
    """``$TORCHFACE_CACHE_DIR/native`` (a leading ``~`` expanded: set where no shell expands it, in a ``.env`` file
    or a container's environment, it made a folder named ``~`` in the working folder), else
    ``~/.cache/torchface/native``."""
    root = os.environ.get("TORCHFACE_CACHE_DIR")
    return (Path(root).expanduser() if root else Path.home() / ".cache" / "torchface") / "native"


def _process_libgomp() -> set[str]:
    """The paths of the GNU OpenMP runtimes (``libgomp``) loaded in this process (Linux; empty elsewhere)."""
    try:
        with open("/proc/self/maps") as maps:
            return {line.split()[-1] for line in maps if "/libgomp" in line}
    except OSError:
        return set()


_SWITCH_OFF = ("0", "false", "no", "off")
_SWITCH_ON = ("", "1", "true", "yes", "on")


def _env_switch(name: str) -> bool:
    """Whether the environment switch ``name`` is on (the default): off for ``0``, ``false``, ``no``, ``off`` (any
    case, spaces ignored); on when unset or for ``1``, ``true``, ``yes``, ``on`` or empty. Any other value reads as
    on with a ``RuntimeWarning`` naming it (``TORCHFACE_NATIVE=maybe`` was taken as on, silently)."""
    raw = os.environ.get(name)
    if raw is None:
        return True
    value = raw.strip().lower()
    if value in _SWITCH_OFF:
        return False
    if value not in _SWITCH_ON:
        warnings.warn(f"torchface: {name}={raw!r} is not a switch value (0, false, no, off to turn it off; 1, true, "
                      "yes, on to leave it on): read as on", RuntimeWarning, stacklevel=2)  # fmt: skip
    return True


def _openmp_wanted() -> bool:
    """Whether to build the kernels' dispatch with OpenMP: torch runs its own threads on a GNU OpenMP runtime
    already loaded in the process (the Linux wheels), which the library then shares, and
    ``TORCHFACE_OPENMP`` is not off (:func:`_env_switch`)."""
    if not _env_switch("TORCHFACE_OPENMP"):
        return False
    return len(_process_libgomp()) == 1


_private: Path | None = None


def _private_dir(cache: Path, exc: OSError) -> Path:
    """Where the library is built when the cache folder ``cache`` cannot be written (``exc``: a read-only home, a
    ``TORCHFACE_CACHE_DIR`` that is a file): a temporary folder of this process, made once and removed at its exit.
    A ``RuntimeWarning`` says so once. Raises ``OSError`` where no temporary folder can be made either."""
    global _private
    if _private is None:
        _private = Path(tempfile.mkdtemp(prefix="torchface-native-"))
        atexit.register(_remove_private, _private, os.getpid())
        # A multiprocessing child (a data-loader worker) ends with os._exit, which runs no atexit function but
        # multiprocessing's finalizers: without one, each worker that built the library left its folder behind.
        multiprocessing.util.Finalize(None, _remove_private, args=(_private, os.getpid()), exitpriority=0)
        warnings.warn(
            f"torchface: the native kernels' cache folder {cache} cannot be written ({exc}); they are built for this "
            f"process only, in {_private} (a few seconds at each start). Set TORCHFACE_CACHE_DIR to a writable "
            "folder to keep them.", RuntimeWarning, stacklevel=5,
        )  # fmt: skip
    return _private


def _remove_private(folder: Path, pid: int) -> None:
    if os.getpid() == pid:  # not in a forked child that exits normally
        shutil.rmtree(folder, ignore_errors=True)


def _sweep_partials(folder: Path) -> None:
    """Delete the temporary files of builds in ``folder`` older than a day: left by a process killed while it
    built (a data-loader worker terminated at shutdown, the OOM killer), each nearly a library's size, they were
    never removed."""
    limit = time.time() - _STALE_PARTIAL_S
    for tmp in folder.glob("torchface_native-*.partial"):
        try:
            if tmp.stat().st_mtime < limit:
                tmp.unlink()
        except OSError:  # removed or renamed by its builder meanwhile, or not ours to remove
            pass


def _build(cc: str, openmp: bool = False) -> Path:
    """Compile the library (or find it built) and return its path; raises ``RuntimeError`` on failure. With
    ``openmp``, a build with ``-fopenmp`` is tried first (:func:`run` then dispatches on OpenMP's threads)."""
    source = b"".join((_SOURCE_DIR / name).read_bytes() for name in _SOURCES)
    try:
        folder = _cache_dir()
    except RuntimeError as exc:  # no home folder (HOME unset, a user id without a passwd entry) to put it in
        folder = _private_dir(Path("~/.cache/torchface/native"), OSError(str(exc)))
    errors = []
    for omp in ((_OPENMP_FLAGS, ()) if openmp else ((),)):
        for arch in (_ARCH_FLAGS, ()):
            flags = (*_FLAGS, *arch, *omp)
            cpu = _cpu_signature() if arch else ""
            key = hashlib.sha256(source + repr((cc, flags, platform.machine(), cpu, _ABI_VERSION)).encode()).hexdigest()
            target = folder / f"torchface_native-{key[:16]}.so"
            if target.is_file():
                return target
            try:
                target.parent.mkdir(parents=True, exist_ok=True)
                _sweep_partials(target.parent)
                fd, tmp = tempfile.mkstemp(prefix=target.name + ".", suffix=".partial", dir=target.parent)
            except OSError as exc:  # a read-only home, a cache path that is a file: built for this process only
                folder = _private_dir(folder, exc)
                target = folder / target.name
                if target.is_file():
                    return target
                fd, tmp = tempfile.mkstemp(prefix=target.name + ".", suffix=".partial", dir=target.parent)
            os.close(fd)
            try:
                cmd = [*shlex.split(cc), *flags, "-o", tmp, str(_SOURCE_DIR / "kernels.c"), "-lm"]
                out = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
                if out.returncode == 0:
                    # mkstemp's 0600 (0711 once linked): others sharing the cache folder could not load it. Now
                    # what the umask allows, as for any file the compiler writes (0755 under the usual 022).
                    os.chmod(tmp, 0o777 & ~_UMASK)
                    os.replace(tmp, target)
                    return target
                errors.append(f"{' '.join(cmd)}: {out.stderr.strip()[-500:]}")
            except (OSError, ValueError, subprocess.SubprocessError) as exc:  # ValueError: $CC unbalanced quotes
                errors.append(f"{cc}: {exc}")
            finally:
                if os.path.exists(tmp):
                    os.unlink(tmp)
    raise RuntimeError("; ".join(errors))


def _load() -> None:
    global _library, _reason
    if not _env_switch("TORCHFACE_NATIVE"):
        _reason = f"turned off by TORCHFACE_NATIVE={os.environ['TORCHFACE_NATIVE'].strip()}"
        return
    cc = _compiler()
    if cc is None:
        _reason = "no C compiler found (cc, gcc, clang or $CC)"
        _warn_fallback()
        return
    try:
        runtimes = _process_libgomp()
        lib = ctypes.CDLL(str(_build(cc, openmp=_openmp_wanted())))
        if lib.tf_abi_version() != _ABI_VERSION:
            raise RuntimeError(f"library ABI {lib.tf_abi_version()}, expected {_ABI_VERSION}")
    except (OSError, RuntimeError, AttributeError) as exc:
        _reason = f"the native kernels could not be built or loaded: {exc}"
        _warn_fallback()
        return
    for name, problem in (("tf_solve_level", LevelProblem), ("tf_dissimilarity", LKProblem),
                          ("tf_normalised_face", FaceProblem), ("tf_confidence", ConfProblem),
                          ("tf_coverage", CoverProblem), ("tf_face_coefficients", CoeffProblem),
                          ("tf_select_pixels", SelectProblem),
                          ("tf_reference_patches", LKProblem), ("tf_select_entries", ManageProblem),
                          ("tf_gate", ManageProblem), ("tf_template_at", TemplateProblem),
                          ("tf_top_pixels", TopProblem), ("tf_pick_pixels", PickProblem),
                          ("tf_gray_pyramid", PyramidProblem),
                          ("tf_visible", VisibleProblem), ("tf_clean_streams", CleanProblem)):
        for suffix in ("_f32", "_f64"):
            fn = getattr(lib, name + suffix)
            fn.argtypes = [ctypes.POINTER(problem), ctypes.c_int, ctypes.c_int]
            fn.restype = ctypes.c_int
    global _parallel, _parallel_pid
    # OpenMP's dispatch only where the library shares torch's runtime (no second libgomp came with it).
    if lib.tf_has_openmp() and _process_libgomp() == runtimes:
        _parallel, _parallel_pid = lib.tf_parallel, os.getpid()
        _parallel.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int, ctypes.c_int]
        _parallel.restype = ctypes.c_int
    _library = lib


def _warn_fallback() -> None:
    """Once per process, where the kernels were wanted but cannot run: the torch code runs instead, about twice as
    slow at one stream on a CPU (not when ``TORCHFACE_NATIVE=0`` turned them off)."""
    warnings.warn(
        f"torchface: native kernels unavailable ({_reason}); the torch code runs instead (same results, slower on "
        "the CPU). Install a C compiler, or set TORCHFACE_NATIVE=0 to silence this.", RuntimeWarning, stacklevel=4,
    )  # fmt: skip


def library() -> ctypes.CDLL | None:
    """The loaded library (built on the first call), or None where it is unavailable (see
    :func:`unavailable_reason`). Thread-safe: a thread that asks while another builds or loads it waits for that
    to finish."""
    global _tried
    if not _tried:
        with _lock:
            if not _tried:
                try:
                    _load()
                finally:  # set last: the check above must not let another thread past before the load has ended
                    _tried = True
    return _library


def unavailable_reason() -> str | None:
    """Why :func:`library` is None (None when it is available or was not asked for yet)."""
    return _reason


_pool: ThreadPoolExecutor | None = None
_pool_size = 0
_pool_pid = -1


def run_chunks(fn, problem: ctypes.Structure, batch: int, threads: int) -> None:
    """``fn(problem, b0, b1)`` over ``[0, batch)`` in contiguous chunks on up to ``threads`` threads, in parallel.
    Raises ``MemoryError`` when a chunk could not allocate its workspace.

    Where the library shares torch's GNU OpenMP runtime (:func:`uses_openmp`), the chunks run on that runtime's
    threads (``tf_parallel``: chunks of about ``batch / (8 threads)`` streams, each taken by the next free thread,
    so that a thread with cheap streams, or one the machine did not hold up, takes more of them), the ones torch's
    own operations use: after each parallel operation they spin for a while waiting for
    the next, and threads of another pool (the fallback here: a ``ThreadPoolExecutor``, ctypes releasing the GIL)
    then share the cores with them. Measured at 32 streams on 2 cores, the level solves took 34 ms per step on
    such a pool against 36 on one thread, and 19 on OpenMP's threads. A process forked from the one that loaded the
    library (a data-loader worker) uses the pool: GNU OpenMP's threads are not carried over a fork."""
    global _pool, _pool_size, _pool_pid
    chunks = max(1, min(threads, batch))
    if chunks == 1:
        codes = [fn(ctypes.byref(problem), 0, batch)]
    elif _parallel is not None and os.getpid() == _parallel_pid:
        codes = [_parallel(ctypes.cast(fn, ctypes.c_void_p), ctypes.addressof(problem), batch, chunks)]
    else:
        ref = ctypes.byref(problem)
        bounds = [batch * k // chunks for k in range(chunks + 1)]
        with _lock:  # submitted under the lock: another thread that grows the pool shuts the old one down
            if _pool is None or _pool_size < chunks or _pool_pid != os.getpid():  # a forked child: a pool of its own
                if _pool is not None and _pool_pid == os.getpid():
                    _pool.shutdown(wait=False)  # what was submitted to it still runs
                _pool, _pool_size = ThreadPoolExecutor(max_workers=chunks, thread_name_prefix="torchface"), chunks
                _pool_pid = os.getpid()
            futures = [_pool.submit(fn, ref, bounds[k], bounds[k + 1]) for k in range(1, chunks)]
        codes = [fn(ref, bounds[0], bounds[1])] + [f.result() for f in futures]
    if any(code != 0 for code in codes):
        raise MemoryError("a native kernel could not allocate its workspace")


def uses_openmp() -> bool:
    """Whether :func:`run_chunks` runs the chunks on torch's OpenMP threads (built with ``-fopenmp`` where torch
    uses GNU OpenMP, the Linux wheels; ``TORCHFACE_OPENMP=0`` turns it off) rather than on a thread pool of its
    own (as in a process forked from the one that loaded the library). Loads the library."""
    library()
    return _parallel is not None and os.getpid() == _parallel_pid


def run(kernel: str, double: bool, problem: ctypes.Structure, batch: int, threads: int) -> None:
    """The kernel ``tf_<kernel>`` (its float64 build where ``double``, else its float32 one) over ``[0, batch)`` by
    :func:`run_chunks`; nothing for an empty batch. The library must be available (:func:`library`)."""
    if batch > 0:
        run_chunks(getattr(library(), f"tf_{kernel}_{'f64' if double else 'f32'}"), problem, batch, threads)
