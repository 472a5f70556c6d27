"""Input validation shared by the geometry modules and the settings dataclasses (public-boundary checks, never inside
hot loops)."""

from __future__ import annotations

import enum
import functools
import math
import numbers
import re
import sys
from typing import Literal, TypeVar, cast, overload

import numpy as np
import torch

from torchface.geometry.camera import Intrinsics

E = TypeVar("E", bound=enum.Enum)


def check_tensor(x: object, name: str, trailing: tuple[int, ...], min_dim: int | None = None) -> torch.Tensor:
    """Check that ``x`` is a floating tensor whose last dimensions are ``trailing``.

    Args:
        x: the value to check.
        name: argument name used in error messages.
        trailing: required sizes of the last ``len(trailing)`` dimensions.
        min_dim: minimum number of dimensions (defaults to ``len(trailing)``).

    Returns:
        ``x`` unchanged.

    Raises:
        TypeError: ``x`` is not a floating-point tensor.
        ValueError: its shape does not end with ``trailing`` or it has too few dimensions.
    """
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if not x.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got dtype {x.dtype}")
    need = len(trailing) if min_dim is None else min_dim
    if x.dim() < need or tuple(x.shape[x.dim() - len(trailing) :]) != trailing:
        want = "(..., " + ", ".join(str(s) for s in trailing) + ")"
        raise ValueError(f"{name} must have shape {want} with at least {need} dims, got {tuple(x.shape)}")
    return x


def check_bool(value: object, name: str) -> bool:
    """``value`` as a Python bool: a ``bool`` or a numpy bool (``np.True_``, as an element of a numpy array).

    The settings' one rule for flags: ``"no"``, ``1`` or ``None`` were taken as true or false without a word.

    Raises:
        TypeError: ``value`` is of another type (the message names the setting ``name``).
    """
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be a bool, got {type(value).__name__} {value!r}")
    return bool(value)


def check_int(value: object, name: str, low: int | None = None) -> int:
    """``value`` as a Python int: an ``int``, a numpy integer (``np.int64(32)``) or a 0-d integer tensor or array
    (``torch.tensor(32)``, as :func:`check_real` takes a 0-d real one), never a bool.

    The settings' one rule for counts and sizes, PyTorch's convention: a value of the wrong type (``2.0``, ``"3"``,
    ``True``) is a ``TypeError``, one out of range a ``ValueError``; both messages say what was expected. Numpy
    integers are converted, so that a setting holds a Python int (as :class:`~torchface.geometry.Intrinsics`' sizes).

    Args:
        value: the setting's value.
        name: the setting's name, for the messages.
        low: the least value allowed (None: any).

    Raises:
        TypeError: ``value`` is not an integer.
        ValueError: it is below ``low``.
    """
    return _check_int(value, name, low, "")


def check_optional_int(value: object, name: str, low: int | None = None) -> int | None:
    """``None``, or ``value`` checked and converted as :func:`check_int` does."""
    return None if value is None else _check_int(value, name, low, " or None")


def _check_int(value: object, name: str, low: int | None, extra: str) -> int:
    want = ("an int" if low is None else f"an int >= {low}") + extra
    # (a tensor that requires grad is a float one: refused below as any 0-d float is, not told to pass float(x))
    grad = isinstance(value, torch.Tensor) and value.requires_grad
    if isinstance(value, (torch.Tensor, np.ndarray)) and value.ndim == 0 and not grad:
        _refuse_grad(value, name, want)  # (a meta one)
        item = value.item()  # (a 0-d integer tensor or array as its int, as check_real takes a 0-d real one)
        if isinstance(item, int) and not isinstance(item, bool):
            value = item
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name} must be {want}, got {type(value).__name__} {value!r}")
    if low is not None and value < low:
        raise ValueError(f"{name} must be {want}, got {value!r}")
    return int(value)


def check_real(value: object, name: str) -> float:
    """``value`` as a Python number: an ``int`` or a ``float`` as given, a numpy real number (``np.float32(0.5)``)
    as a Python float, a 0-d real tensor or array (``torch.tensor(0.5)``, ``np.array(2)``) as its Python number
    (``.item()``: a float, or an int for an integer one); never a bool (nor a bool or complex tensor).

    The settings' one rule for their numbers, as :func:`check_int`'s for counts: a value of another type (``"0.5"``,
    ``True``, ``None``) is a ``TypeError`` naming the setting ``name`` (``"0.5"`` was "'<' not supported between
    ...", or taken); the setting's own range check follows. An int stays an int, so that a setting's ``repr`` (part
    of ``training_hooks``' cache key and of ``torchface track --resume``'s record) is what it was.

    A 0-d tensor was "must be a real number, got Tensor" where a Python number was taken, though
    :func:`check_reals` took its elements so (``normalised_face(depth_tolerance=torch.tensor(0.1))`` had worked).

    Raises:
        TypeError: ``value`` is not a real number.
    """
    return _check_real(value, name, "")


def check_optional_real(value: object, name: str) -> float | None:
    """``None``, or ``value`` checked and converted as :func:`check_real` does."""
    return None if value is None else _check_real(value, name, " or None")


def _refuse_grad(value: object, name: str, what: str = "a real number") -> None:
    """A tensor that requires grad, or has no values (``meta``), given for a setting's plain number(s): a
    ``TypeError`` (its ``.item()`` / ``.tolist()`` dropped the gradient silently, or raised torch's own error)."""
    if isinstance(value, torch.Tensor) and (value.requires_grad or value.is_meta):
        why = ("requires grad (a setting is a plain number: its gradient would be lost here); pass float(x.detach()) "
               "or x.detach().tolist() where no gradient is meant") if value.requires_grad \
            else "is a meta one (no values)"
        raise TypeError(f"{name} must be {what}, got a tensor that {why}")


def _check_real(value: object, name: str, extra: str) -> float:
    number = value
    if isinstance(value, (torch.Tensor, np.ndarray)) and value.ndim == 0:  # (as iterating a tensor gives)
        _refuse_grad(value, name)
        number = value.item()  # (a bool or complex one: a bool or complex, refused below)
    if isinstance(number, (bool, np.bool_)) or not isinstance(number, numbers.Real):
        raise TypeError(f"{name} must be a real number{extra}, got {type(value).__name__} {value!r}")
    return cast(float, number) if type(number) in (int, float) else float(number)


@overload
def check_number(value: object, name: str, interval: str, optional: Literal[False] = ..., unit: str = ...) -> float: ...
@overload
def check_number(value: object, name: str, interval: str, optional: bool, unit: str = ...) -> float | None: ...
def check_number(value: object, name: str, interval: str, optional: bool = False, unit: str = "") -> float | None:
    """``value`` checked and converted as :func:`check_real` does (a ``TypeError`` for another type; a 0-d real
    tensor is its Python number), then refused
    (``ValueError``) unless it lies in ``interval``, written as in mathematics: ``"[0, 1]"``, ``"(0, 0.5]"``,
    ``"[0, inf)"``. The settings' one rule for a number's range, each field's ``interval`` stated once.

    NaN lies in no interval. An infinite value lies in one only where the interval closes on it (``"[0, inf]"``:
    for a setting whose documented meaning of ``inf`` is "no limit"); ``"[0, inf)"`` is a finite number >= 0
    (``>= 0`` alone had taken ``inf`` as a tolerance, a threshold or a scale, which then failed or did nothing).

    Args:
        value: the setting's value.
        name: the setting's name, for the messages (``name[i]`` for an element).
        interval: the values allowed.
        optional: ``None`` is allowed too (and returned).
        unit: what the number counts, for the range's message (``"pixels"``: "focal must be a finite number > 0
            (pixels), got -5.0").

    Raises:
        TypeError: ``value`` is not a real number (or None with ``optional``).
        ValueError: it lies outside ``interval``; or ``interval`` is not one, or an empty one (``"[1, 0]"``).

    Example:
        >>> check_number(0.5, "texture_blend", "(0, 1]"), check_number(None, "focal", "(0, inf)", True)
        (0.5, None)
        >>> check_number(float("inf"), "search_step_px", "(0, inf)", unit="pixels")
        Traceback (most recent call last):
            ...
        ValueError: search_step_px must be a finite number > 0 (pixels), got inf
    """
    low, high, low_open, high_open = _interval(interval)  # (first: a mistyped interval is found with None too)
    if optional and value is None:
        return None
    number = _check_real(value, name, " or None" if optional else "")
    above = number > low if low_open else number >= low
    below = number < high if high_open else number <= high
    if not (above and below):  # (NaN: both False)
        unit = f" ({unit})" if unit else ""
        none = " or None" if optional else ""
        shown = number if isinstance(value, (torch.Tensor, np.ndarray)) else value  # (nan, not tensor(nan))
        raise ValueError(f"{name} must be {_interval_words(interval)}{unit}{none}, got {shown!r}")
    return number


#: An interval as :func:`check_number` is given it.
_INTERVAL = re.compile(r"([\[(])\s*([^\s,]+)\s*,\s*([^\s,]+)\s*([\])])")


def _interval(interval: str) -> tuple[float, float, bool, bool]:
    """``(low, high, low_open, high_open)`` of an interval written ``"[a, b)"`` (``inf`` and ``-inf`` allowed).

    Raises:
        ValueError: ``interval`` is not so written, or holds no number (``"[1, 0]"``, ``"(0, 0]"``, a NaN bound:
            every value was refused, the message saying the empty range).
    """
    match = _INTERVAL.fullmatch(interval)  # (not cached: torch.compile traces the check in normalised_face, and
    # warns of a functools.lru_cache it meets; a parse is about a microsecond)
    try:
        low, high = (float(match[2]), float(match[3])) if match is not None else (math.nan, math.nan)
    except ValueError:
        low = high = math.nan
    low_open, high_open = match is not None and match[1] == "(", match is not None and match[4] == ")"
    if not (low < high or (low == high and not (low_open or high_open))):  # (NaN: False)
        raise ValueError(f'interval must be a non-empty interval of numbers written "[a, b]", "(a, b)", "[a, b)" or '
                         f'"(a, b]" (a or b inf), got {interval!r}')
    return low, high, low_open, high_open


def _interval_words(interval: str) -> str:
    """How a message says ``interval``: "a finite number >= 0" for ``"[0, inf)"``, "in (0, 90)" for a bounded one."""
    low, high, low_open, high_open = _interval(interval)
    if high == math.inf and high_open:
        if low == -math.inf:
            return "a finite number"
        return f"a finite number {'>' if low_open else '>='} {low:g}"
    if low == -math.inf and low_open:
        return f"a finite number {'<' if high_open else '<='} {high:g}"
    return f"in {interval}"


def check_choice(value: object, name: str, kind: type[E]) -> E:
    """``value`` if it is a member of the enum ``kind``: the settings' one rule for choices (``TrackerConfig.solver``,
    ``LayerConfig.mode``, ``load_candide3(animation=)``, a ``backend`` argument, ...).

    Anything else is a ``TypeError`` that says what to pass and where to import it from: the member a string names
    (its value or name, any case: ``solver="fast"`` names ``TrackSolver.FAST``), else every member. A string is not
    taken for the member: a choice is spelled one way (a string was "must be a TrackSolver, got 'fast'", or "got
    str", not what to pass).

    Raises:
        TypeError: ``value`` is not a ``kind`` member.

    Example:
        >>> from torchface.solver import RobustKind
        >>> check_choice(RobustKind.HUBER, "robust", RobustKind)
        <RobustKind.HUBER: 'huber'>
        >>> check_choice("Huber", "robust", RobustKind)
        Traceback (most recent call last):
            ...
        TypeError: robust must be a RobustKind, got str 'Huber' (pass RobustKind.HUBER, from torchface.solver)
    """
    if isinstance(value, kind):
        return value
    spelled = value.strip().lower() if isinstance(value, str) else None
    named = [m for m in kind if spelled in (str(m.value).lower(), m.name.lower())]
    members = " or ".join(f"{kind.__name__}.{m.name}" for m in (named[:1] or list(kind)))
    article = "an" if kind.__name__[0] in "AEIOU" else "a"
    raise TypeError(f"{name} must be {article} {kind.__name__}, got {type(value).__name__} {value!r} (pass {members}, "
                    f"from {_home(kind)})")


def _home(kind: type) -> str:
    """The shortest package or module path that ``kind`` imports from (``torchface.tracker`` for ``TrackSolver``,
    defined in ``torchface.tracker.step``): the one its users are told to import from."""
    parts = kind.__module__.split(".")
    for n in range(1, len(parts) + 1):
        module = sys.modules.get(".".join(parts[:n]))
        if module is not None and getattr(module, kind.__name__, None) is kind:
            return module.__name__
    return kind.__module__


def check_ints(values: object, name: str, low: int | None = None) -> tuple[int, ...]:
    """``values`` (a tuple or list, or a 1-D numpy array or tensor, as :func:`check_reals` takes them) as a tuple of
    Python ints, each checked as :func:`check_int` does (``name[i]`` in the messages; a float array's elements are
    not ints).

    Raises:
        TypeError: ``values`` is not a tuple or list, or an element is not an integer.
        ValueError: an element is below ``low``.
    """
    if isinstance(values, (np.ndarray, torch.Tensor)) and values.ndim == 1:
        values = list(values)  # (its 0-d elements: an integer one is its int, a float one refused)
    if not isinstance(values, (tuple, list)):
        raise TypeError(f"{name} must be a tuple of ints, got {type(values).__name__} {values!r}")
    return tuple(check_int(v, f"{name}[{i}]", low) for i, v in enumerate(values))


def check_reals(values: object, name: str, interval: str | None = None) -> tuple[float, ...]:
    """``values`` (a tuple or list, or a 1-D numpy array or tensor) as a tuple of numbers, each checked and converted
    as :func:`check_real` does (``name[i]`` in the messages; an int stays an int, so that a default's ``repr`` stays
    what it was).

    The rule for the settings that hold several numbers (``TrackerConfig.robust_scale_floor``,
    ``expression_prior_weights``, ``TemplateConfig.search_depth_factors``, ...): a string was taken as its characters
    (``expression_prior_weights="1" * 11``: eleven ones; bytes: their codes), a string element was "'<' not supported
    between instances of 'int' and 'str'", and a bool element was taken as 0 or 1.

    An element may be a 0-d array or tensor (``tuple(torch.tensor([0.1, 0.02]))``, as iterating one gives), taken
    as its Python number: the settings that took ``float(w)`` or compared their elements had taken them.

    With ``interval``, each element must lie in it, as :func:`check_number` checks (a ``ValueError`` naming the
    element otherwise).

    Raises:
        TypeError: ``values`` is not a tuple, list or 1-D array, or an element is not a real number.
        ValueError: an element lies outside ``interval``.
    """
    if isinstance(values, (np.ndarray, torch.Tensor)) and values.ndim == 1:
        _refuse_grad(values, name, "a tuple of real numbers")
        values = values.tolist()
    if not isinstance(values, (tuple, list)):
        raise TypeError(f"{name} must be a tuple of real numbers, got {type(values).__name__} {values!r}")
    if interval is None:
        return tuple(check_real(v, f"{name}[{i}]") for i, v in enumerate(values))
    return tuple(check_number(v, f"{name}[{i}]", interval) for i, v in enumerate(values))


def check_names(values: object, name: str, optional: bool = False) -> tuple[str, ...] | None:
    """``values`` (a tuple or list of strings, or a 1-D NumPy array of them) as a tuple of distinct names: the rule of
    the settings that name a model's units (``FitConfig.held_shape_units``, ``LookaheadConfig.kept_shape_units``), as
    :func:`check_reals` is that of the settings that hold numbers (a list was refused with a ``ValueError``, and so
    was a wrong type, where the other settings take a list and say ``TypeError``). ``optional``: None is None.

    Raises:
        TypeError: ``values`` is not a tuple or list (a string would be its characters' names), or an element is not
            a string.
        ValueError: a name is given twice.
    """
    if values is None and optional:
        return None
    if isinstance(values, np.ndarray) and values.ndim == 1:
        values = values.tolist()
    if not isinstance(values, (tuple, list)):
        what = "None or a tuple" if optional else "a tuple"
        one = f" (one unit: ({values!r},))" if isinstance(values, str) else ""
        raise TypeError(f"{name} must be {what} of unit names, got {type(values).__name__} {values!r}{one}")
    for i, v in enumerate(values):
        if not isinstance(v, str):
            raise TypeError(f"{name}[{i}] must be a unit name (a str), got {type(v).__name__} {v!r}")
    twice = sorted({v for v in values if values.count(v) > 1})
    if twice:
        raise ValueError(f"{name} must name each unit once, got {twice} more than once in {tuple(values)}")
    return tuple(str(v) for v in values)


def rotation_defects(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How far each of ``R`` ``(N, 3, 3)`` is from a rotation: ``(N,)`` the largest entry of ``|R R^T - I|`` and
    ``(N,)`` its determinant (a rotation: 0 and +1; each caller bounds the first by its own tolerance)."""
    off = np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2), initial=0.0)
    return off, np.linalg.det(R)


def check_exact_dim(x: torch.Tensor, name: str, dims: tuple[int, ...], shape_doc: str) -> None:
    """Raise ``ValueError`` unless ``x.dim()`` is one of ``dims`` (``shape_doc`` names the expected shapes)."""
    if x.dim() not in dims:
        raise ValueError(f"{name} must be {shape_doc}, got shape {tuple(x.shape)}")


def check_intrinsics(intrinsics: object) -> Intrinsics:
    """Raise ``TypeError`` unless ``intrinsics`` is an :class:`Intrinsics`."""
    if not isinstance(intrinsics, Intrinsics):
        raise TypeError(f"intrinsics must be torchface.geometry.Intrinsics, got {type(intrinsics).__name__}"
                        f"{_intrinsics_type_hint(intrinsics)}")  # fmt: skip
    return intrinsics


def _intrinsics_type_hint(value: object) -> str:
    """How to make an :class:`Intrinsics` of what a user passed instead, for :func:`check_intrinsics`' message: a 3x3
    calibration matrix (OpenCV's ``cameraMatrix``, a tensor, array or nested lists) or a sequence of the numbers
    (``fx, fy, cx, cy`` or with the size). Both were told the type alone."""
    shape: tuple[int, ...] | None = None
    if isinstance(value, (torch.Tensor, np.ndarray)):
        shape = tuple(value.shape)
    elif isinstance(value, (list, tuple)):
        try:
            shape = tuple(np.shape(np.asarray(value, dtype=object)))
        except ValueError:  # (ragged)
            shape = None
    if shape == (3, 3):
        return " (a 3x3 calibration matrix K: Intrinsics.from_matrix(K, width, height))"
    if shape in ((4,), (6,)):
        return " (the camera's numbers: Intrinsics(width, height, fx, fy, cx, cy), in pixels)"
    return ""


def check_batch(b1: int, b2: int, name1: str, name2: str) -> None:
    """Raise ``ValueError`` unless two batch sizes agree or one of them is 1 (broadcast)."""
    if b1 != b2 and b1 != 1 and b2 != 1:
        raise ValueError(f"batch sizes of {name1} ({b1}) and {name2} ({b2}) must match or be 1")


def check_batches(*named: tuple[str, int]) -> None:
    """:func:`check_batch` of every pair of ``(name, batch size)``: three or more batched arguments broadcast only
    if all sizes other than 1 agree (pairs checked against one argument alone let ``R (1)``, ``t (2)``,
    ``points (3)`` through to torch's "The size of tensor a (3) must match the size of tensor b (2)")."""
    for i, (name1, b1) in enumerate(named):
        for name2, b2 in named[i + 1 :]:
            check_batch(b1, b2, name1, name2)


def promoted(*tensors: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """``tensors`` in their promoted dtype (float32 against float64: float64), as torch's elementwise operations
    promote; a matmul of mixed dtypes raised "expected scalar type Float but found Double"."""
    dtype = tensors[0].dtype
    for x in tensors[1:]:
        dtype = torch.promote_types(dtype, x.dtype)
    return tuple(x.to(dtype) for x in tensors)


def check_broadcast(a: torch.Tensor, b: torch.Tensor, name_a: str, name_b: str, trailing: int) -> None:
    """Raise ``ValueError`` unless the leading dimensions of ``a`` and ``b`` (all but their last ``trailing``)
    broadcast (their mismatch was torch's RuntimeError "The size of tensor a (4) must match ...")."""
    lead_a, lead_b = tuple(a.shape[: a.dim() - trailing]), tuple(b.shape[: b.dim() - trailing])
    # Compared here, not by torch.broadcast_shapes: its first call imports sympy (0.4 s of CPU, 486 modules), a stall
    # of the first recovery attempt a tracker makes (managed_step's geodesic_angle_deg).
    if any(x != y and x != 1 and y != 1 for x, y in zip(reversed(lead_a), reversed(lead_b))):
        raise ValueError(f"batch shapes of {name_a} {lead_a} and {name_b} {lead_b} must broadcast")
