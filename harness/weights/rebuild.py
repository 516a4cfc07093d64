"""What a checkpoint's pickle may rebuild: inert placeholders for the classes it names, and the rebuild list.

``REBUILD`` maps the global names a ``torch.save`` file uses (tensor rebuilders, containers, dtypes, storage types,
NumPy scalars and arrays, ``datetime``, paths) to tokens; a token that may be called carries a checked
implementation that charges what it makes to the read's budget before making it (``harness.weights.bounds``). Any
other name becomes a :class:`Stub` class: an instance records its arguments and state, and calling the class is
refused. The unpickler itself is ``harness.weights.unpickle``, which imports this module; a rebuild call sees it
only as a :class:`Reader` (its budget, its limits and its key check), so this module does not import it.
"""

from __future__ import annotations

import collections
import datetime
import math
import operator
import pathlib
from typing import Any, Callable, Protocol

import numpy as np
import torch

from harness.weights.bounds import (
    MAX_DIMS,
    Budget,
    CheckpointFormatError,
    CheckpointLimitError,
    Limits,
    UnsafeCheckpointError,
    human,
)


class Reader(Protocol):
    """What a rebuild call uses of the unpickler that calls it (``harness.weights.unpickle``)."""

    budget: Budget
    limits: Limits

    def check_key(self, key: Any) -> None:
        """Refuse a dict key or set item whose hashing the file could make costly."""


# ------------------------------------------------------------------------------------------------ placeholders
class _StubMeta(type):
    """Metaclass of placeholder classes: calling one (pickle's REDUCE) is refused."""

    __stub_name__: str

    def __call__(cls, *args: Any, **kwargs: Any) -> Any:
        raise UnsafeCheckpointError(
            f"the checkpoint asks to call {cls.__stub_name__[:100]}(...); only tensors, containers and inert objects "
            f"are rebuilt, so this call is refused and nothing from the file was run"
        )


class Stub(metaclass=_StubMeta):
    """An inert stand-in for an instance of a class named in the checkpoint: its name, arguments and state."""

    __stub_name__ = "Stub"

    def __new__(cls, *args: Any, **kwargs: Any) -> "Stub":
        obj = object.__new__(cls)
        object.__setattr__(obj, "__stub_args__", args)
        object.__setattr__(obj, "__stub_state__", None)
        object.__setattr__(obj, "__stub_merged__", None)
        return obj

    def __setstate__(self, state: Any) -> None:
        object.__setattr__(self, "__stub_state__", state)
        object.__setattr__(self, "__stub_merged__", None)

    def __reduce__(self) -> Any:  # never pickled back out
        raise TypeError("placeholders from a restricted checkpoint read cannot be pickled")

    def __repr__(self) -> str:
        return f"<{self.__stub_name__} (placeholder)>"

    @property
    def stub_name(self) -> str:
        return type(self).__stub_name__

    @property
    def state(self) -> dict[str, Any]:
        """The recorded state as a dict (``{}`` when the file gave none or gave a non-dict state); built once."""
        merged = self.__stub_merged__  # type: ignore[attr-defined]
        if merged is None:
            st = self.__stub_state__  # type: ignore[attr-defined]
            if isinstance(st, tuple) and len(st) == 2 and isinstance(st[0], dict):  # (dict, slotstate)
                merged = {**st[0], **(st[1] if isinstance(st[1], dict) else {})}
            else:
                merged = st if isinstance(st, dict) else {}
            object.__setattr__(self, "__stub_merged__", merged)
        return merged

    def get(self, key: str, default: Any = None) -> Any:
        return self.state.get(key, default)


def stub_class(module: str, name: str) -> type:
    """A new placeholder class for a qualified name (a read makes one per name, so the instances of one name share
    a class across a file, and nothing is kept between files)."""
    return _StubMeta(name, (Stub,), {"__stub_name__": f"{module}.{name}", "__module__": "harness.weights.stubs"})


# ------------------------------------------------------------------------------------------------ the rebuild list
class Token:
    """What an allowed global name resolves to: a token (``torch.Tensor`` as ``_rebuild_from_type_v2``'s type
    argument), optionally with a checked implementation run when the file calls it."""

    def __init__(self, name: str, call: Callable[..., Any] | None = None, value: Any = None):
        self.name, self.call, self.value = name, call, value

    def __repr__(self) -> str:
        return f"<global {self.name}>"


_STORAGE_DTYPES = {
    "DoubleStorage": torch.float64,
    "FloatStorage": torch.float32,
    "HalfStorage": torch.float16,
    "BFloat16Storage": torch.bfloat16,
    "LongStorage": torch.int64,
    "IntStorage": torch.int32,
    "ShortStorage": torch.int16,
    "CharStorage": torch.int8,
    "ByteStorage": torch.uint8,
    "BoolStorage": torch.bool,
    "ComplexFloatStorage": torch.complex64,
    "ComplexDoubleStorage": torch.complex128,
    "UntypedStorage": torch.uint8,
}
_DTYPES = {
    name: getattr(torch, name)
    for name in (
        "float64",
        "float32",
        "float16",
        "bfloat16",
        "int64",
        "int32",
        "int16",
        "int8",
        "uint8",
        "bool",
        "complex64",
        "complex128",
        "double",
        "float",
        "half",
        "long",
        "int",
        "short",
    )
}


class StorageType:
    """What a ``torch.XStorage`` name stands for here: just its dtype."""

    def __init__(self, name: str):
        self.name, self.dtype = name, _STORAGE_DTYPES[name]
        self.itemsize = 1 if name == "UntypedStorage" else self.dtype.itemsize

    def __repr__(self) -> str:
        return f"torch.{self.name}"


_ATOMS = (str, bytes, int, float, bool, complex, type(None))


def _atoms(args: tuple, what: str) -> tuple:
    for a in args:
        if not isinstance(a, _ATOMS):
            raise UnsafeCheckpointError(f"the checkpoint calls {what} with {brief(a)}; refused")
        if isinstance(a, int) and a.bit_length() > 4096:
            raise CheckpointLimitError(f"the checkpoint calls {what} with {brief(a)}; refused")
    return args


def tensor_dims(value: Any, what: str) -> tuple[int, ...]:
    if not isinstance(value, (tuple, list)) or len(value) > MAX_DIMS:
        raise CheckpointFormatError(f"a tensor's {what} is {brief(value)}, not a tuple of at most {MAX_DIMS} ints")
    try:
        dims = tuple(operator.index(v) for v in value)
    except TypeError:
        raise CheckpointFormatError(f"a tensor's {what} holds a non-integer ({brief(value)})") from None
    if any(d < 0 for d in dims):
        raise CheckpointFormatError(f"a tensor's {what} {brief(dims)} is negative")
    return dims


def out_itemsize(dtype: torch.dtype) -> int:
    """Bytes per element once imported (floating tensors become float32)."""
    return 4 if dtype.is_floating_point else dtype.itemsize


def _view(u: Reader, storage: Any, offset: Any, size: Any, stride: Any) -> torch.Tensor:
    if not isinstance(storage, torch.Tensor):
        raise CheckpointFormatError(f"a tensor is rebuilt from {brief(storage)}, not from a storage")
    size, stride = tensor_dims(size, "size"), tensor_dims(stride, "stride")
    try:
        offset = operator.index(offset)
    except TypeError:
        raise CheckpointFormatError(f"a tensor's storage offset is {brief(offset)}") from None
    if len(size) != len(stride) or offset < 0:
        raise CheckpointFormatError(f"a tensor of size {size} has stride {stride} and offset {offset}")
    numel = math.prod(size)
    nbytes = numel * max(storage.element_size(), out_itemsize(storage.dtype))
    if nbytes > u.limits.tensor_bytes:
        raise CheckpointLimitError(
            f"a tensor of size {size} (stride {stride}) expands to {human(nbytes)}, over {u.limits.of_file()}; refused"
        )
    if numel == 0:
        return storage.new_empty(size)
    need = offset + sum((s - 1) * st for s, st in zip(size, stride)) + 1
    if need > storage.numel():
        raise CheckpointFormatError(f"a tensor of size {size} reaches element {need} of a storage of {storage.numel()}")
    # a view: legacy files fill their storages after the object pickle, and views see the bytes once they land
    return storage.as_strided(size, stride, offset)


def _rebuild_tensor(
    u: Reader, storage: Any = None, offset: Any = 0, size: Any = (), stride: Any = (), *rest: Any
) -> torch.Tensor:
    return _view(u, storage, offset, size, stride)


def _rebuild_tensor_v3(
    u: Reader,
    storage: Any = None,
    offset: Any = 0,
    size: Any = (),
    stride: Any = (),
    requires_grad: Any = False,
    hooks: Any = None,
    dtype: Any = None,
    *rest: Any,
) -> torch.Tensor:
    t = storage
    if isinstance(t, torch.Tensor) and isinstance(dtype, torch.dtype) and t.dtype != dtype:
        t = t.view(torch.uint8).view(dtype)
    return _view(u, t, offset, size, stride)


def _rebuild_parameter(u: Reader, data: Any = None, requires_grad: Any = True, *rest: Any) -> torch.Tensor:
    if not isinstance(data, torch.Tensor):
        raise CheckpointFormatError(f"a parameter is rebuilt from {brief(data)}, not from a tensor")
    return torch.nn.Parameter(data, requires_grad=bool(requires_grad) and data.is_floating_point())


def _rebuild_from_type_v2(u: Reader, func: Any = None, new_type: Any = None, args: Any = (), state: Any = None) -> Any:
    if func not in (G_REBUILD_TENSOR, G_REBUILD_TENSOR_V2, G_REBUILD_TENSOR_V3, G_REBUILD_PARAMETER) or not isinstance(
        args, tuple
    ):
        raise UnsafeCheckpointError(
            "the checkpoint rebuilds a tensor subclass through a function outside the rebuild list; refused"
        )
    t = func.call(u, *args)
    return torch.nn.Parameter(t, requires_grad=t.is_floating_point()) if new_type is G_PARAMETER else t


def _items(u: Reader, iterable: Any, what: str) -> list:
    """The items of an iterable argument, charged before they are made; only containers and ranges."""
    if isinstance(iterable, range):
        try:
            n = len(iterable)
        except OverflowError:
            n = u.limits.metadata_bytes
        u.budget.charge(40 * n)  # a list slot and an int object per item
        return list(iterable)
    if isinstance(iterable, (list, tuple, set, frozenset, str, bytes, bytearray)):
        u.budget.charge(8 * len(iterable) + 56)
        return list(iterable)
    if isinstance(iterable, dict):
        u.budget.charge(8 * len(iterable) + 56)
        return list(iterable.items())
    raise UnsafeCheckpointError(f"the checkpoint calls {what} on {brief(iterable)}; refused")


def _pairs(u: Reader, arg: Any, what: str) -> list[tuple[Any, Any]]:
    pairs = _items(u, arg, what)
    if isinstance(arg, dict):
        return pairs
    for p in pairs:
        if not isinstance(p, (tuple, list)) or len(p) != 2:
            raise CheckpointFormatError(f"the checkpoint calls {what} with an item that is not a pair ({brief(p)})")
        u.check_key(p[0])
    u.budget.charge(104 * len(pairs))
    return [tuple(p) for p in pairs]  # type: ignore[misc]


def _call_list(u: Reader, iterable: Any = ()) -> list:
    return _items(u, iterable, "list()")


def _call_tuple(u: Reader, iterable: Any = ()) -> tuple:
    return tuple(_items(u, iterable, "tuple()"))


def _call_set(u: Reader, iterable: Any = ()) -> set:
    items = _items(u, iterable, "set()")
    for k in items:
        u.check_key(k)
    u.budget.charge(104 * len(items))
    return set(items)


def _call_frozenset(u: Reader, iterable: Any = ()) -> frozenset:
    return frozenset(_call_set(u, iterable))


def _call_dict(u: Reader, arg: Any = ()) -> dict:
    return dict(_pairs(u, arg, "dict()"))


def _call_ordered_dict(u: Reader, arg: Any = ()) -> collections.OrderedDict:
    return collections.OrderedDict(_pairs(u, arg, "OrderedDict()"))


def _call_defaultdict(u: Reader, factory: Any = None, arg: Any = ()) -> collections.defaultdict:
    factories = {
        None: None,
        G_LIST: list,
        G_DICT: dict,
        G_INT: int,
        G_FLOAT: float,
        G_SET: set,
        G_STR: str,
        G_TUPLE: tuple,
    }
    if not (factory is None or isinstance(factory, Token)) or factory not in factories:
        raise UnsafeCheckpointError(f"the checkpoint builds a defaultdict with factory {brief(factory)}; refused")
    return collections.defaultdict(factories[factory], _pairs(u, arg, "defaultdict()"))


def _sized(u: Reader, ctor: type, args: tuple, what: str) -> Any:
    """``bytes``/``bytearray`` from a size, a string and encoding, bytes, or a list or range of ints."""
    if len(args) >= 1 and isinstance(args[0], int) and not isinstance(args[0], bool):
        u.budget.charge(args[0] + 64)  # before the allocation: bytearray(8e9) is refused here
        return ctor(args[0])
    if len(args) >= 1 and isinstance(args[0], (list, tuple, range)):
        return ctor(_items(u, args[0], what))
    _atoms(args, what)
    u.budget.charge(sum(len(a) for a in args if isinstance(a, (str, bytes))) * 4 + 64)
    return ctor(*args)


def _call_bytes(u: Reader, *args: Any) -> bytes:
    return _sized(u, bytes, args, "bytes()")


def _call_bytearray(u: Reader, *args: Any) -> bytearray:
    return _sized(u, bytearray, args, "bytearray()")


def _atomic(ctor: Callable[..., Any], what: str) -> Callable[..., Any]:
    def call(u: Reader, *args: Any) -> Any:
        _atoms(args, what)
        u.budget.charge(sum(len(a) for a in args if isinstance(a, (str, bytes))) * 4 + 64)
        return ctor(*args)

    return call


def _call_range(u: Reader, *args: Any) -> range:
    _atoms(args, "range()")
    return range(*args)


def _call_slice(u: Reader, *args: Any) -> slice:
    return slice(*_atoms(args, "slice()"))


def _call_size(u: Reader, iterable: Any = ()) -> torch.Size:
    items = _items(u, iterable, "torch.Size()")
    return torch.Size(tensor_dims(items, "torch.Size"))


def _numpy_scalar(u: Reader, dtype: Any = None, data: Any = b"") -> Any:
    if not isinstance(dtype, np.dtype) or dtype.hasobject or not isinstance(data, bytes) or len(data) < dtype.itemsize:
        raise CheckpointFormatError(f"a NumPy scalar is rebuilt from {brief(dtype)} and {brief(data)}")
    return np.frombuffer(data, dtype=dtype, count=1)[0].copy()


def _numpy_dtype(u: Reader, spec: Any = None, *rest: Any) -> np.dtype:
    if not isinstance(spec, str) or len(spec) > 64:
        raise CheckpointFormatError(f"a NumPy dtype is rebuilt from {brief(spec)}")
    dt = np.dtype(spec)
    if dt.hasobject or dt.itemsize > u.limits.tensor_bytes:
        raise UnsafeCheckpointError(f"the checkpoint builds the NumPy dtype {spec!r}; refused")
    return dt


def _numpy_reconstruct(u: Reader, cls: Any = None, *rest: Any) -> np.ndarray:
    if cls is not G_NDARRAY:
        raise UnsafeCheckpointError(f"the checkpoint rebuilds a NumPy array of class {brief(cls)}; refused")
    return np.ndarray.__new__(np.ndarray, (0,), np.uint8)  # filled by BUILD (checked in _Unpickler._build)


def _path(u: Reader, *parts: Any) -> str:
    if not all(isinstance(p, str) for p in parts):
        raise CheckpointFormatError("a path is rebuilt from something other than strings")
    u.budget.charge(sum(len(p) for p in parts) + 64)
    return str(pathlib.PurePosixPath(*parts))


def _latin1_bytes(u: Reader, text: Any = None, encoding: Any = "latin1") -> bytes:
    """Protocol-2 pickles write ``bytes`` as ``_codecs.encode(text, 'latin1')``: only that form is rebuilt."""
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
        raise UnsafeCheckpointError("the checkpoint calls _codecs.encode with other than a latin1 string; refused")
    u.budget.charge(len(text) + 64)
    return text.encode("latin1")


def _device(u: Reader, *args: Any) -> torch.device:
    return torch.device(*_atoms(args, "torch.device()"))


G_REBUILD_TENSOR = Token("torch._utils._rebuild_tensor", _rebuild_tensor)
G_REBUILD_TENSOR_V2 = Token("torch._utils._rebuild_tensor_v2", _rebuild_tensor)
G_REBUILD_TENSOR_V3 = Token("torch._utils._rebuild_tensor_v3", _rebuild_tensor_v3)
G_REBUILD_PARAMETER = Token("torch._utils._rebuild_parameter", _rebuild_parameter)
G_PARAMETER = Token("torch.nn.parameter.Parameter")  # a token: calling it is refused
G_TENSOR = Token("torch.Tensor")
G_NDARRAY = Token("numpy.ndarray")
G_LIST, G_TUPLE, G_SET = (
    Token("builtins.list", _call_list),
    Token("builtins.tuple", _call_tuple),
    Token("builtins.set", _call_set),
)
G_DICT, G_INT, G_FLOAT, G_STR = (
    Token("builtins.dict", _call_dict),
    Token("builtins.int", _atomic(int, "int()")),
    Token("builtins.float", _atomic(float, "float()")),
    Token("builtins.str", _atomic(str, "str()")),
)

#: Every global the unpickler resolves to something real (others become placeholders, and calling them is refused).
REBUILD: dict[tuple[str, str], Any] = {
    ("torch._utils", "_rebuild_tensor"): G_REBUILD_TENSOR,
    ("torch._utils", "_rebuild_tensor_v2"): G_REBUILD_TENSOR_V2,
    ("torch._utils", "_rebuild_tensor_v3"): G_REBUILD_TENSOR_V3,
    ("torch._utils", "_rebuild_parameter"): G_REBUILD_PARAMETER,
    ("torch._utils", "_rebuild_parameter_with_state"): Token(
        "torch._utils._rebuild_parameter_with_state", _rebuild_parameter
    ),
    ("torch._tensor", "_rebuild_from_type_v2"): Token("torch._tensor._rebuild_from_type_v2", _rebuild_from_type_v2),
    ("torch.nn.parameter", "Parameter"): G_PARAMETER,
    ("torch", "Tensor"): G_TENSOR,
    ("torch", "Size"): Token("torch.Size", _call_size),
    ("torch", "device"): Token("torch.device", _device),
    ("collections", "OrderedDict"): Token("collections.OrderedDict", _call_ordered_dict),
    ("collections", "defaultdict"): Token("collections.defaultdict", _call_defaultdict),
    ("_codecs", "encode"): Token("_codecs.encode", _latin1_bytes),
    ("builtins", "set"): G_SET,
    ("builtins", "frozenset"): Token("builtins.frozenset", _call_frozenset),
    ("builtins", "list"): G_LIST,
    ("builtins", "tuple"): G_TUPLE,
    ("builtins", "dict"): G_DICT,
    ("builtins", "int"): G_INT,
    ("builtins", "float"): G_FLOAT,
    ("builtins", "str"): G_STR,
    ("builtins", "bytes"): Token("builtins.bytes", _call_bytes),
    ("builtins", "bytearray"): Token("builtins.bytearray", _call_bytearray),
    ("builtins", "bool"): Token("builtins.bool", _atomic(bool, "bool()")),
    ("builtins", "complex"): Token("builtins.complex", _atomic(complex, "complex()")),
    ("builtins", "slice"): Token("builtins.slice", _call_slice),
    ("builtins", "range"): Token("builtins.range", _call_range),
    ("datetime", "datetime"): Token("datetime.datetime", _atomic(datetime.datetime, "datetime()")),
    ("datetime", "date"): Token("datetime.date", _atomic(datetime.date, "date()")),
    ("datetime", "timedelta"): Token("datetime.timedelta", _atomic(datetime.timedelta, "timedelta()")),
    ("numpy", "dtype"): Token("numpy.dtype", _numpy_dtype),
    ("numpy", "ndarray"): G_NDARRAY,
    **{(m, "scalar"): Token(f"{m}.scalar", _numpy_scalar) for m in ("numpy.core.multiarray", "numpy._core.multiarray")},
    **{
        (m, "_reconstruct"): Token(f"{m}._reconstruct", _numpy_reconstruct)
        for m in ("numpy.core.multiarray", "numpy._core.multiarray")
    },
    **{
        ("pathlib", n): Token(f"pathlib.{n}", _path)
        for n in ("Path", "PosixPath", "WindowsPath", "PurePath", "PurePosixPath", "PureWindowsPath")
    },
    **{("torch", n): StorageType(n) for n in _STORAGE_DTYPES},
    **{("torch", n): d for n, d in _DTYPES.items()},
}


def brief(obj: Any, width: int = 60) -> str:
    """A short description of any object that never walks into it (``repr`` of a hostile structure can take
    exponential time, recurse without bound or fail on a huge integer)."""
    if isinstance(obj, str):
        return repr(obj if len(obj) <= width else obj[:width] + "...")
    if isinstance(obj, bool) or obj is None:
        return repr(obj)
    if isinstance(obj, int):
        return repr(obj) if obj.bit_length() <= 64 else f"<int of {obj.bit_length()} bits>"
    if isinstance(obj, float):
        return repr(obj)
    if isinstance(obj, (bytes, bytearray)):
        return f"<{type(obj).__name__} of {len(obj)}>"
    if isinstance(obj, (list, tuple, dict, set, frozenset)):
        return f"<{type(obj).__name__} of {len(obj)} items>"
    if isinstance(obj, Stub):
        return f"<{obj.stub_name[:width]}>"
    if isinstance(obj, type) and issubclass(obj, Stub):
        return obj.__stub_name__[:width]
    if isinstance(obj, Token):
        return obj.name[:width]
    if isinstance(obj, torch.Tensor):
        return f"<tensor {tuple(obj.shape)}>"
    return f"<{type(obj).__name__}>"
