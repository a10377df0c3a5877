"""One array namespace over numpy and torch, so the batched simulator has one code path.

numpy runs on the CPU; torch runs wherever its device says (``"cuda"``, ``"torch:cpu"``).
Only the handful of operations whose names or signatures differ between the two libraries
are wrapped; everything else (``+``, ``*``, indexing, comparisons) is the arrays' own.
torch is imported only when a torch device is asked for, so ``arena`` never pulls it in.

>>> ops = get_ops("numpy")
>>> ops.name, ops.to_numpy(ops.atan2(ops.asarray([1.0]), ops.asarray([1.0]))).round(4).tolist()
('numpy', [0.7854])
"""

from __future__ import annotations

import contextlib
import functools
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from tracks.errors import SlipstreamError

Array = Any  # a numpy ndarray or a torch Tensor, as the ops' library makes them
_FEW_ROWS = 64  # up to this many rows, NumpyOps.inverse_permutation sorts (see there)


def count_true(mask: np.ndarray) -> int:
    """``np.count_nonzero`` of a numpy bool array: its bytes are 0 or 1, so one count of
    its bytes, without numpy's Python-level wrapper (which costs more on the env's few cars
    than the count; the episode rules test a dozen masks a step)."""
    return mask.tobytes().count(1)


class DeviceError(SlipstreamError):
    """An unknown device, or torch / CUDA asked for where it is not installed."""


class NumpyOps:
    """The numpy namespace (CPU). ``dtype`` is the float type of every state array."""

    name = "numpy"
    device = "cpu"
    # Elementwise functions with the same name and meaning in numpy and torch (set per library).
    sin: Callable[..., Array]
    cos: Callable[..., Array]
    tanh: Callable[..., Array]
    sqrt: Callable[..., Array]
    abs: Callable[..., Array]
    floor: Callable[..., Array]
    hypot: Callable[..., Array]
    isnan: Callable[..., Array]
    minimum: Callable[..., Array]
    maximum: Callable[..., Array]

    def __init__(self, dtype: str = "float64") -> None:
        self._init_args: tuple[str, ...] = (dtype,)
        self.float: Any = np.dtype(dtype)
        self.int: Any = np.dtype(np.int64)
        self.bool: Any = np.dtype(np.bool_)
        self.float32: Any = np.dtype(np.float32)
        self.lib: Any = np
        # Plain ufuncs with the same name and meaning in both libraries.
        for fn in ("sin", "cos", "tanh", "sqrt", "abs", "floor", "minimum", "maximum", "hypot"):
            setattr(self, fn, getattr(np, fn))
        self.isnan = np.isnan

    def __reduce__(self) -> tuple[type[NumpyOps], tuple[str, ...]]:
        """Pickle (and deep-copy) as the constructor call: the library module itself cannot be
        pickled, and a copied env (SuperSuit's vector envs, subprocesses) needs its ops."""
        return (type(self), self._init_args)

    # ---- creation ----------------------------------------------------------------------------
    def asarray(self, x: Any, dtype: Any = None) -> Array:
        """``x`` as an array of this library (floats become ``self.float`` by default)."""
        arr = np.asarray(x)
        if dtype is None and arr.dtype.kind == "f":
            dtype = self.float
        return arr.astype(dtype, copy=False) if dtype is not None else arr

    def zeros(self, shape: Sequence[int] | int, dtype: Any = None) -> Array:
        """Zeros (floats by default)."""
        return np.zeros(shape, dtype=self.float if dtype is None else dtype)

    def full(self, shape: Sequence[int] | int, value: float, dtype: Any = None) -> Array:
        """An array filled with ``value`` (floats by default)."""
        return np.full(shape, value, dtype=self.float if dtype is None else dtype)

    def arange(self, n: int) -> Array:
        """0 … n-1, int64 (read-only, cached)."""
        return _arange(n)

    def eye(self, n: int) -> Array:
        """(n, n) boolean identity (read-only, cached)."""
        return _eye(n)

    def to_numpy(self, x: Array) -> np.ndarray:
        """A numpy view or copy of ``x`` (on the host)."""
        return np.asarray(x)

    def const(self, x: np.ndarray) -> Array:
        """A long-lived read-only numpy constant as an array of this library (cached)."""
        return x

    def floats(self, values: tuple[float, ...]) -> Array:
        """``values`` (K,) as a read-only array of the state's float type (cached)."""
        return _floats(values, self.float)

    # ---- maths and reductions ------------------------------------------------------------------
    def atan2(self, y: Array, x: Array) -> Array:
        """Elementwise ``atan2(y, x)``, rad."""
        return np.arctan2(y, x)

    def mod(self, x: Array, m: Any) -> Array:
        """Remainder with the sign of ``m`` (numpy's ``mod``, torch's ``remainder``)."""
        return np.mod(x, m)

    def wrap(self, x: Array, period: float) -> Array:
        """Floats folded into [0, period) (``x − period · floor(x / period)``: cheaper than
        ``mod``, and the same up to rounding)."""
        return x - period * self.floor(x * (1.0 / period))

    def put_along(self, base: Array, idx: Array, values: Array, axis: int) -> Array:
        """``base`` with ``values`` written at ``idx`` along ``axis`` (``base`` is consumed)."""
        np.put_along_axis(base, idx, values, axis=axis)
        return base

    def quiet(self) -> contextlib.AbstractContextManager[Any]:
        """A context in which division by zero gives ±inf silently (IEEE, as torch does)."""
        return np.errstate(divide="ignore", invalid="ignore")

    def matmul(self, a: Array, b: Array) -> Array:
        """Matrix product over the last axes."""
        return np.matmul(a, b)

    def where(self, cond: Array, a: Any, b: Any) -> Array:
        """Elementwise choice (Python floats take the state's float type, not float64)."""
        if isinstance(a, float):
            a = self.float.type(a)
        if isinstance(b, float):
            b = self.float.type(b)
        return np.where(cond, a, b)

    def clip(self, x: Array, lo: Any, hi: Any) -> Array:
        """Clamp into [lo, hi] (numbers or arrays; NaN stays NaN): ``np.clip``'s values
        without its Python-level overhead, which dominates on the env's few cars."""
        return np.minimum(np.maximum(x, lo), hi)

    def stack(self, xs: Sequence[Array], axis: int = 0) -> Array:
        """Stack along a new axis (``np.stack``'s result; a concatenation of views is several
        times cheaper on small arrays)."""
        if not all(isinstance(x, np.ndarray) for x in xs):
            return np.stack(xs, axis=axis)
        at = (..., None) + (slice(None),) * (-axis - 1) if axis < 0 else (slice(None),) * axis
        if axis >= 0:
            at = (*at, None)
        return np.concatenate([x[at] for x in xs], axis=axis)

    def concat(self, xs: Sequence[Array], axis: int = 0) -> Array:
        """Join along an existing axis."""
        return np.concatenate(xs, axis=axis)

    # The reductions call the ufuncs' reduce directly: what the array methods end in, without
    # their Python-level wrapper (which costs more than the work on the env's few cars).
    def sum(self, x: Array, axis: int) -> Array:
        """Sum over ``axis``."""
        return np.add.reduce(x, axis=axis)

    def any(self, x: Array, axis: int) -> Array:
        """Logical or over ``axis``."""
        return np.logical_or.reduce(x, axis=axis)

    def all(self, x: Array, axis: int) -> Array:
        """Logical and over ``axis``."""
        return np.logical_and.reduce(x, axis=axis)

    def amin(self, x: Array, axis: int) -> Array:
        """Minimum over ``axis``."""
        return np.amin(x, axis=axis)

    def argmin(self, x: Array, axis: int) -> Array:
        """Index of the minimum over ``axis``."""
        return np.argmin(x, axis=axis)

    def argsort(self, x: Array, axis: int = -1) -> Array:
        """Stable argsort (the array method: no dispatch cost on small arrays)."""
        return x.argsort(axis=axis, kind="stable")

    def take_along(self, x: Array, idx: Array, axis: int) -> Array:
        """``take_along_axis``."""
        return np.take_along_axis(x, idx, axis=axis)

    def searchsorted(self, sorted_1d: Array, x: Array) -> Array:
        """Right-side insertion indices of ``x`` into a sorted 1-D array."""
        return np.searchsorted(sorted_1d, x, side="right")

    def inverse_permutation(self, order: Array) -> Array:
        """The inverse of permutations along the last axis (``inv[order[k]] = k``)."""
        # Exact either way: argsort of a permutation is its inverse. A scatter is cheaper
        # than a second sort on many rows; on a few short ones the sort is (no 2-D index).
        if order.ndim == 1:
            inv = np.empty_like(order)
            inv[order] = _arange(len(order))
            return inv
        if order.ndim == 2 and order.shape[0] > _FEW_ROWS:
            inv = np.empty_like(order)
            inv[_arange(order.shape[0])[:, None], order] = _arange(order.shape[1])
            return inv
        return self.argsort(order, axis=-1)

    def swap_pairs(self, x: Array) -> Array:
        """``x`` with each pair along the last axis swapped: [a, b, c, d] → [b, a, d, c]."""
        return x.take(_pair_swap(x.shape[-1]), axis=-1)

    def gather_rows(self, x: Array, idx: Array) -> Array:
        """Rows ``x[..., i, idx[..., i, q], :]``: (..., n, n, F) by (..., n, m) → (..., n, m, F)."""
        if x.ndim == 3:  # no batch axes: plain fancy indexing is several times cheaper
            return x[_arange(x.shape[0])[:, None], idx]
        return np.take_along_axis(x, idx[..., None], axis=-2)

    def cast(self, x: Array, dtype: Any) -> Array:
        """``x`` converted to ``dtype``."""
        return x.astype(dtype)

    def copy(self, x: Array) -> Array:
        """A copy of ``x``."""
        return x.copy()

    # ---- randomness ------------------------------------------------------------------------------
    def rng(self, seed: int | None) -> Any:
        """A seeded generator for :meth:`uniform` and :meth:`integers`."""
        return np.random.default_rng(seed)

    def uniform(self, gen: Any, shape: Sequence[int]) -> Array:
        """Uniform floats in [0, 1)."""
        return gen.random(shape).astype(self.float)

    def integers(self, gen: Any, high: int, shape: Sequence[int]) -> Array:
        """Uniform integers in [0, high)."""
        return gen.integers(0, high, size=shape, dtype=np.int64)

    def permutations(self, gen: Any, n_rows: int, n: int) -> Array:
        """(n_rows, n) independent random permutations of 0 … n-1."""
        return self.argsort(self.uniform(gen, (n_rows, n)), axis=1)


class TorchOps(NumpyOps):
    """The torch namespace on ``device`` (``"cpu"``, ``"cuda"``, ``"cuda:1"`` …)."""

    name = "torch"

    def __init__(self, device: str = "cpu", dtype: str = "float32") -> None:
        try:
            import torch  # noqa: PLC0415 - only when a torch device is requested
        except ImportError as err:  # pragma: no cover - torch is a training dependency
            raise DeviceError(
                "a torch device needs torch: pip install 'slipstream[train]'"
            ) from err
        if device.startswith("cuda") and not torch.cuda.is_available():
            raise DeviceError(f"device {device!r} asked for, but torch sees no CUDA GPU")
        self._init_args = (device, dtype)
        self.torch: Any = torch
        self.device = device
        self.float = getattr(torch, dtype)
        self.int = torch.int64
        self.bool = torch.bool
        self.float32 = torch.float32
        self.lib = torch
        self._consts: dict[int, tuple[np.ndarray, Any]] = {}
        for fn in ("sin", "cos", "tanh", "sqrt", "abs", "floor", "hypot"):
            setattr(self, fn, getattr(torch, fn))
        self.isnan = torch.isnan

    def minimum(self, a: Any, b: Any) -> Array:
        """Elementwise minimum (either side may be a number)."""
        t = self.torch
        if not isinstance(b, t.Tensor):
            return t.clamp(a, max=b)
        if not isinstance(a, t.Tensor):
            return t.clamp(b, max=a)
        return t.minimum(a, b)

    def maximum(self, a: Any, b: Any) -> Array:
        """Elementwise maximum (either side may be a number)."""
        t = self.torch
        if not isinstance(b, t.Tensor):
            return t.clamp(a, min=b)
        if not isinstance(a, t.Tensor):
            return t.clamp(b, min=a)
        return t.maximum(a, b)

    def asarray(self, x: Any, dtype: Any = None) -> Array:
        """``x`` as a tensor on the device (floats become ``self.float`` by default)."""
        t = self.torch
        if isinstance(x, np.ndarray):
            if not x.flags.writeable:
                x = x.copy()  # torch wants writable memory to share
            if dtype is None:
                dtype = {"f": self.float, "b": t.bool}.get(x.dtype.kind, t.int64)
        out = t.as_tensor(x, device=self.device)
        if dtype is None and out.is_floating_point():
            dtype = self.float
        return out.to(dtype) if dtype is not None else out

    def zeros(self, shape: Sequence[int] | int, dtype: Any = None) -> Array:
        """Zeros (floats by default)."""
        dt = self.float if dtype is None else dtype
        return self.torch.zeros(shape, dtype=dt, device=self.device)

    def full(self, shape: Sequence[int] | int, value: float, dtype: Any = None) -> Array:
        """An array filled with ``value`` (floats by default)."""
        dt = self.float if dtype is None else dtype
        return self.torch.full(_shape(shape), value, dtype=dt, device=self.device)

    def arange(self, n: int) -> Array:
        """0 … n-1, int64."""
        return self.torch.arange(n, device=self.device)

    def eye(self, n: int) -> Array:
        """(n, n) boolean identity."""
        return self.torch.eye(n, dtype=self.torch.bool, device=self.device)

    def to_numpy(self, x: Array) -> np.ndarray:
        """A host copy of ``x`` as numpy."""
        if isinstance(x, self.torch.Tensor):
            return x.detach().cpu().numpy()
        return np.asarray(x)

    def const(self, x: np.ndarray) -> Array:
        """A long-lived read-only numpy constant as a tensor on the device (cached by id)."""
        hit = self._consts.get(id(x))
        if hit is None or hit[0] is not x:
            hit = (x, self.asarray(x))
            self._consts[id(x)] = hit
        return hit[1]

    def floats(self, values: tuple[float, ...]) -> Array:
        """``values`` (K,) as a tensor of the state's float type on the device (cached)."""
        return self.const(_floats(values, np.dtype(np.float64)))

    def swap_pairs(self, x: Array) -> Array:
        """``x`` with each pair along the last axis swapped: [a, b, c, d] → [b, a, d, c]."""
        return x.index_select(-1, self.const(_pair_swap(x.shape[-1])))

    def atan2(self, y: Array, x: Array) -> Array:
        """Elementwise ``atan2(y, x)``, rad."""
        return self.torch.atan2(y, x)

    def mod(self, x: Array, m: Any) -> Array:
        """Remainder with the sign of ``m``."""
        return self.torch.remainder(x, m)

    def where(self, cond: Array, a: Any, b: Any) -> Array:
        """Elementwise choice (numbers are fine on either side)."""
        return self.torch.where(cond, a, b)

    def put_along(self, base: Array, idx: Array, values: Array, axis: int) -> Array:
        """``base`` with ``values`` written at ``idx`` along ``axis`` (``base`` is consumed)."""
        return base.scatter_(axis, idx, values)

    def quiet(self) -> contextlib.AbstractContextManager[Any]:
        """torch divides by zero silently already."""
        return contextlib.nullcontext()

    def matmul(self, a: Array, b: Array) -> Array:
        """Matrix product over the last axes."""
        return self.torch.matmul(a, b)

    def clip(self, x: Array, lo: Any, hi: Any) -> Array:
        """Clamp into [lo, hi] (numbers or tensors)."""
        return self.torch.clamp(x, lo, hi)

    def stack(self, xs: Sequence[Array], axis: int = 0) -> Array:
        """Stack along a new axis."""
        return self.torch.stack(list(xs), dim=axis)

    def concat(self, xs: Sequence[Array], axis: int = 0) -> Array:
        """Join along an existing axis."""
        return self.torch.cat(list(xs), dim=axis)

    def sum(self, x: Array, axis: int) -> Array:
        """Sum over ``axis``."""
        return self.torch.sum(x, dim=axis)

    def any(self, x: Array, axis: int) -> Array:
        """Logical or over ``axis``."""
        return self.torch.any(x, dim=axis)

    def all(self, x: Array, axis: int) -> Array:
        """Logical and over ``axis``."""
        return self.torch.all(x, dim=axis)

    def amin(self, x: Array, axis: int) -> Array:
        """Minimum over ``axis``."""
        return self.torch.amin(x, dim=axis)

    def argmin(self, x: Array, axis: int) -> Array:
        """Index of the minimum over ``axis``."""
        return self.torch.argmin(x, dim=axis)

    def argsort(self, x: Array, axis: int = -1) -> Array:
        """Stable argsort."""
        return self.torch.argsort(x, dim=axis, stable=True)

    def take_along(self, x: Array, idx: Array, axis: int) -> Array:
        """``take_along_dim``."""
        return self.torch.take_along_dim(x, idx, dim=axis)

    def searchsorted(self, sorted_1d: Array, x: Array) -> Array:
        """Right-side insertion indices of ``x`` into a sorted 1-D tensor."""
        return self.torch.searchsorted(sorted_1d, x.contiguous(), right=True)

    def inverse_permutation(self, order: Array) -> Array:
        """The inverse of permutations along the last axis (``inv[order[k]] = k``)."""
        return self.argsort(order, axis=-1)

    def gather_rows(self, x: Array, idx: Array) -> Array:
        """Rows ``x[..., i, idx[..., i, q], :]``: (..., n, n, F) by (..., n, m) → (..., n, m, F)."""
        return self.torch.take_along_dim(x, idx[..., None], dim=-2)

    def cast(self, x: Array, dtype: Any) -> Array:
        """``x`` converted to ``dtype``."""
        return x.to(dtype)

    def copy(self, x: Array) -> Array:
        """A copy of ``x``."""
        return x.clone()

    def rng(self, seed: int | None) -> Any:
        """A seeded ``torch.Generator`` on the device."""
        gen = self.torch.Generator(device=self.device)
        gen.manual_seed(int(np.random.SeedSequence(seed).generate_state(1)[0]))
        return gen

    def uniform(self, gen: Any, shape: Sequence[int]) -> Array:
        """Uniform floats in [0, 1)."""
        return self.torch.rand(tuple(shape), generator=gen, device=self.device, dtype=self.float)

    def integers(self, gen: Any, high: int, shape: Sequence[int]) -> Array:
        """Uniform integers in [0, high)."""
        return self.torch.randint(0, high, tuple(shape), generator=gen, device=self.device)


@functools.lru_cache(maxsize=32)
def _arange(n: int) -> np.ndarray:
    out = np.arange(n, dtype=np.int64)
    out.flags.writeable = False
    return out


@functools.lru_cache(maxsize=32)
def _eye(n: int) -> np.ndarray:
    eye = np.eye(n, dtype=bool)
    eye.flags.writeable = False
    return eye


@functools.lru_cache(maxsize=64)
def _floats(values: tuple[float, ...], dtype: np.dtype[Any]) -> np.ndarray:
    out = np.array(values, dtype=dtype)
    out.flags.writeable = False
    return out


@functools.lru_cache(maxsize=8)
def _pair_swap(n: int) -> np.ndarray:
    if n % 2:
        raise ValueError(f"swap_pairs needs an even last axis, got {n}")
    out = np.arange(n, dtype=np.int64) ^ 1  # 1, 0, 3, 2, …
    out.flags.writeable = False
    return out


def _shape(shape: Sequence[int] | int) -> tuple[int, ...]:
    return (shape,) if isinstance(shape, int) else tuple(shape)


NUMPY = NumpyOps()  # the float64 numpy namespace the pybullet env's pure functions default to


def get_ops(device: str = "numpy", dtype: str | None = None) -> NumpyOps:
    """The namespace for a device name.

    Args:
        device: ``"numpy"`` (or ``"cpu"``): numpy on the CPU; ``"torch"`` / ``"torch:cpu"``:
            torch on the CPU; ``"cuda"``, ``"cuda:N"`` or ``"torch:cuda[:N]"``: torch on a GPU.
        dtype: float type of the state (default float32 for torch, float64 for numpy).

    Raises:
        DeviceError: an unknown device, or torch / CUDA missing.
    """
    name = device.lower()
    if name in ("numpy", "cpu", "np"):
        return NumpyOps(dtype or "float64")
    if name.startswith("torch"):
        name = name.partition(":")[2] or "cpu"
    if name == "cpu" or name.startswith("cuda"):
        return TorchOps(name, dtype or "float32")
    raise DeviceError(f"unknown device {device!r}: use numpy, torch:cpu, cuda or cuda:N")


PI = math.pi
