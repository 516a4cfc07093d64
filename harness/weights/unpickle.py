"""Reading pickled PyTorch checkpoints without executing any code from the file, with work bounded by its size.

A ``torch.save`` file is a zip archive (``<name>/data.pkl`` plus one raw storage per tensor under ``<name>/data/``)
or, before PyTorch 1.6, a stream of pickles followed by the raw storages. The pickle describes how to rebuild
every object; an ordinary unpickler *calls* whatever the file names, which is how a checkpoint can run a shell
command. ``load_checkpoint`` reads the same files with a restricted unpickler:

* **tensors and containers** are rebuilt: storages come from the archive's raw bytes (never from a callable the
  file names), tensors and parameters are views on them, and ``OrderedDict``, ``set``, ``torch.Size``,
  ``torch.device``, dtypes, NumPy scalars and arrays, ``datetime`` and paths become what they are;
* **every other class** becomes an inert :class:`Stub` that records its qualified name, the arguments it was
  created with and the state the file gives it. Nothing of the named class is imported, so a checkpoint of
  Ultralytics' ``DetectionModel`` or YOLOv5's ``Model`` reads without those packages, and their modules'
  parameters and buffers can be found in the recorded state (``harness.weights.tree``). With
  ``placeholders=False`` (``load_plain``: ``--init``, resuming, ``model.weights``) such a class is refused instead;
* **every other callable** is refused: a file that asks to call ``posix.system``, ``builtins.eval``,
  ``torch.Tensor`` or any name outside the rebuild list raises :class:`UnsafeCheckpointError` naming it, before
  anything is called. Placeholders are created with ``NEWOBJ`` (``cls.__new__``), which is how protocol-2 pickles
  create instances; calling a placeholder class (``REDUCE``: "call this with these arguments") is the refusal.

A hostile file can also try to exhaust memory or time instead of running code. Everything the reader builds is
bounded by the file's own size F (see :class:`Limits`), and a file that asks for more is refused with a one-line
:class:`CheckpointLimitError` before the memory is taken:

* archive members: their declared uncompressed sizes together at most ``SIZE_MULTIPLE`` (4) x F, checked before
  any is read (a deflate bomb is refused up front); a legacy file's storages together at most F, checked before
  they are allocated, and a storage the file leaves out is refused (it would read as uninitialised memory);
* each tensor: at most 4 x F bytes once materialised as float32 (zero-stride ``expand`` tricks are refused);
* the Python objects the pickle rebuilds: at most ``METADATA_FLOOR`` (48 MiB) + ``METADATA_MULTIPLE`` (2) x F,
  charged opcode by opcode as they are made; allowed calls such as ``bytearray(n)`` or ``list(range(n))`` are
  charged before they allocate;
* dict keys and set items: small (hashing a deep or shared tuple takes exponential time or crashes the
  interpreter), and at most ``RISKY_KEYS`` keys whose hash a file can choose (numbers beyond 2**61, floats, tuples);
* nothing is walked recursively: the unpickler is a stack machine over ``pickle``'s pure-Python opcode handlers,
  and the walks over its result (``harness.weights.tree``, ``harness.weights.layout``) are iterative and visit a
  shared object once.

With these, a whole import stays within ``PEAK_FLOOR`` (64 MiB) + ``PEAK_MULTIPLE`` (8) x F of memory above the
interpreter's own (``tests/test_weights_hostile.py`` measures it on a corpus of hostile files).
"""

from __future__ import annotations

import _compat_pickle
import collections
import datetime
import io
import math
import operator
import pathlib
import pickle
import struct
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Callable

import numpy as np
import torch

from harness.errors import HarnessError


class CheckpointFormatError(HarnessError):
    """The file is not a readable PyTorch checkpoint."""


class UnsafeCheckpointError(CheckpointFormatError):
    """The checkpoint asks for a call outside the tensor-rebuild list (possibly code execution)."""


class ForeignObjectError(UnsafeCheckpointError):
    """A plain read (``load_plain``) met a class outside the rebuild list: the file pickles objects, not tensors."""


class CheckpointLimitError(CheckpointFormatError):
    """The file asks for more memory or work than its own size allows."""


# ------------------------------------------------------------------------------------------------ bounds
MiB = 1 << 20
#: decompressed members, each tensor as float32, and the imported output: at most this many times the file's bytes
SIZE_MULTIPLE = 4
#: the Python objects the pickle rebuilds: at most METADATA_FLOOR + METADATA_MULTIPLE x the file's bytes
METADATA_FLOOR = 48 * MiB
METADATA_MULTIPLE = 2
#: elements of one dict key or set item (a tuple key nested or shared beyond this is refused)
KEY_NODES = 64
#: What the whole import is held to (the tests measure it on every hostile file): peak memory above the
#: interpreter's at most PEAK_FLOOR + PEAK_MULTIPLE x the file's bytes. It follows from the bounds above: the
#: rebuilt objects (48 MiB + 2 F), the storages (F), one tensor being converted (4 F), and a few MiB of working room.
PEAK_FLOOR = 64 * MiB
PEAK_MULTIPLE = 8
#: keys whose hash the file can choose (ints beyond +-2**61, floats, tuples): at most this many per file
RISKY_KEYS = 1000
MAX_DIMS = 64


def human(n: int | float) -> str:
    """``1536 -> '1.5 KiB'``."""
    n = float(n)
    for unit in ("bytes", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{int(n)} bytes" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1024
    raise AssertionError  # pragma: no cover


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
        return f"<{obj.stub_name}>"
    if isinstance(obj, type) and issubclass(obj, Stub):
        return obj.__stub_name__
    if isinstance(obj, _Global):
        return obj.name
    if isinstance(obj, torch.Tensor):
        return f"<tensor {tuple(obj.shape)}>"
    return f"<{type(obj).__name__}>"


@dataclass(frozen=True)
class Limits:
    """The bounds of one read, from the file's size (module docstring)."""

    file_bytes: int

    @property
    def tensor_bytes(self) -> int:
        """One tensor materialised as float32, the archive's members together, and the imported output."""
        return SIZE_MULTIPLE * max(self.file_bytes, 1)

    @property
    def metadata_bytes(self) -> int:
        return METADATA_FLOOR + METADATA_MULTIPLE * self.file_bytes

    def of_file(self, multiple: int = SIZE_MULTIPLE) -> str:
        return f"{multiple} x the file's {human(self.file_bytes)}"


class _Budget:
    """Memory the rebuilt Python objects may take; ``charge`` refuses the step that would exceed it."""

    def __init__(self, limits: Limits):
        self.limits, self.left = limits, limits.metadata_bytes

    def charge(self, nbytes: int) -> None:
        self.left -= nbytes
        if self.left < 0:
            raise CheckpointLimitError(
                f"rebuilding the checkpoint's objects needs more than {human(self.limits.metadata_bytes)} of memory "
                f"(the limit is {human(METADATA_FLOOR)} + {self.limits.of_file(METADATA_MULTIPLE)}); refused")


# ------------------------------------------------------------------------------------------------ placeholders
class _StubMeta(type):
    """Metaclass of placeholder classes: calling one (pickle's REDUCE) is refused."""

    def __call__(cls, *args: Any, **kwargs: Any) -> Any:
        raise UnsafeCheckpointError(
            f"the checkpoint asks to call {cls.__stub_name__}(...); only tensors, containers and inert objects are "
            f"rebuilt, so this call is refused and nothing from the file was run"
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


def _stub_class(module: str, name: str) -> type:
    qual = f"{module}.{name}"
    return _StubMeta(name, (Stub,), {"__stub_name__": qual, "__module__": "harness.weights.stubs"})


def stub_class(module: str, name: str) -> type:
    """A placeholder class for a qualified name (each read makes its own, one per name, so names compare equal
    across a file and nothing is kept between files)."""
    return _stub_class(module, name)


# ------------------------------------------------------------------------------------------------ the rebuild list
class _Global:
    """What an allowed global name resolves to: a token (``torch.Tensor`` as ``_rebuild_from_type_v2``'s type
    argument), optionally with a checked implementation run when the file calls it."""

    def __init__(self, name: str, call: Callable[..., Any] | None = None, value: Any = None):
        self.name, self.call, self.value = name, call, value

    def __repr__(self) -> str:
        return f"<global {self.name}>"


_STORAGE_DTYPES = {
    "DoubleStorage": torch.float64, "FloatStorage": torch.float32, "HalfStorage": torch.float16,
    "BFloat16Storage": torch.bfloat16, "LongStorage": torch.int64, "IntStorage": torch.int32,
    "ShortStorage": torch.int16, "CharStorage": torch.int8, "ByteStorage": torch.uint8, "BoolStorage": torch.bool,
    "ComplexFloatStorage": torch.complex64, "ComplexDoubleStorage": torch.complex128,
    "UntypedStorage": torch.uint8,
}
_DTYPES = {name: getattr(torch, name) for name in (
    "float64", "float32", "float16", "bfloat16", "int64", "int32", "int16", "int8", "uint8", "bool",
    "complex64", "complex128", "double", "float", "half", "long", "int", "short")}


class _StorageType:
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


def _dims(value: Any, what: str) -> tuple[int, ...]:
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


def _view(u: "_Unpickler", storage: Any, offset: Any, size: Any, stride: Any) -> torch.Tensor:
    if not isinstance(storage, torch.Tensor):
        raise CheckpointFormatError(f"a tensor is rebuilt from {brief(storage)}, not from a storage")
    size, stride = _dims(size, "size"), _dims(stride, "stride")
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
            f"a tensor of size {size} (stride {stride}) expands to {human(nbytes)}, over {u.limits.of_file()}; "
            f"refused")
    if numel == 0:
        return storage.new_empty(size)
    need = offset + sum((s - 1) * st for s, st in zip(size, stride)) + 1
    if need > storage.numel():
        raise CheckpointFormatError(f"a tensor of size {size} reaches element {need} of a storage of {storage.numel()}")
    # a view: legacy files fill their storages after the object pickle, and views see the bytes once they land
    return storage.as_strided(size, stride, offset)


def _rebuild_tensor(u: "_Unpickler", storage: Any = None, offset: Any = 0, size: Any = (), stride: Any = (),
                    *rest: Any) -> torch.Tensor:
    return _view(u, storage, offset, size, stride)


def _rebuild_tensor_v3(u: "_Unpickler", storage: Any = None, offset: Any = 0, size: Any = (), stride: Any = (),
                       requires_grad: Any = False, hooks: Any = None, dtype: Any = None, *rest: Any) -> torch.Tensor:
    t = storage
    if isinstance(t, torch.Tensor) and isinstance(dtype, torch.dtype) and t.dtype != dtype:
        t = t.view(torch.uint8).view(dtype)
    return _view(u, t, offset, size, stride)


def _rebuild_parameter(u: "_Unpickler", data: Any = None, requires_grad: Any = True, *rest: Any) -> torch.Tensor:
    if not isinstance(data, torch.Tensor):
        raise CheckpointFormatError(f"a parameter is rebuilt from {brief(data)}, not from a tensor")
    return torch.nn.Parameter(data, requires_grad=bool(requires_grad) and data.is_floating_point())


def _rebuild_from_type_v2(u: "_Unpickler", func: Any = None, new_type: Any = None, args: Any = (),
                          state: Any = None) -> Any:
    if func not in (G_REBUILD_TENSOR, G_REBUILD_TENSOR_V2, G_REBUILD_TENSOR_V3, G_REBUILD_PARAMETER) \
            or not isinstance(args, tuple):
        raise UnsafeCheckpointError("the checkpoint rebuilds a tensor subclass through a function outside the "
                                    "rebuild list; refused")
    t = func.call(u, *args)
    return torch.nn.Parameter(t, requires_grad=t.is_floating_point()) if new_type is G_PARAMETER else t


def _items(u: "_Unpickler", iterable: Any, what: str) -> list:
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


def _pairs(u: "_Unpickler", arg: Any, what: str) -> list[tuple[Any, Any]]:
    pairs = _items(u, arg, what)
    if isinstance(arg, dict):
        return pairs
    for p in pairs:
        if not isinstance(p, (tuple, list)) or len(p) != 2:
            raise CheckpointFormatError(f"the checkpoint calls {what} with an item that is not a pair ({brief(p)})")
        u.check_key(p[0])
    u.budget.charge(104 * len(pairs))
    return [tuple(p) for p in pairs]  # type: ignore[misc]


def _call_list(u: "_Unpickler", iterable: Any = ()) -> list:
    return _items(u, iterable, "list()")


def _call_tuple(u: "_Unpickler", iterable: Any = ()) -> tuple:
    return tuple(_items(u, iterable, "tuple()"))


def _call_set(u: "_Unpickler", iterable: Any = ()) -> set:
    items = _items(u, iterable, "set()")
    for k in items:
        u.check_key(k)
    u.budget.charge(104 * len(items))
    return set(items)


def _call_frozenset(u: "_Unpickler", iterable: Any = ()) -> frozenset:
    return frozenset(_call_set(u, iterable))


def _call_dict(u: "_Unpickler", arg: Any = ()) -> dict:
    return dict(_pairs(u, arg, "dict()"))


def _call_ordered_dict(u: "_Unpickler", arg: Any = ()) -> collections.OrderedDict:
    return collections.OrderedDict(_pairs(u, arg, "OrderedDict()"))


def _call_defaultdict(u: "_Unpickler", factory: Any = None, arg: Any = ()) -> collections.defaultdict:
    factories = {None: None, G_LIST: list, G_DICT: dict, G_INT: int, G_FLOAT: float, G_SET: set, G_STR: str,
                 G_TUPLE: tuple}
    if not (factory is None or isinstance(factory, _Global)) or factory not in factories:
        raise UnsafeCheckpointError(f"the checkpoint builds a defaultdict with factory {brief(factory)}; refused")
    return collections.defaultdict(factories[factory], _pairs(u, arg, "defaultdict()"))


def _sized(u: "_Unpickler", ctor: type, args: tuple, what: str) -> Any:
    """``bytes``/``bytearray`` from a size, a string and encoding, bytes, or a list or range of ints."""
    if len(args) >= 1 and isinstance(args[0], int) and not isinstance(args[0], bool):
        u.budget.charge(args[0] + 64)  # before the allocation: bytearray(8e9) is refused here
        return ctor(args[0])
    if len(args) >= 1 and isinstance(args[0], (list, tuple, range)):
        return ctor(_items(u, args[0], what))
    _atoms(args, what)
    u.budget.charge(sum(len(a) for a in args if isinstance(a, (str, bytes))) * 4 + 64)
    return ctor(*args)


def _call_bytes(u: "_Unpickler", *args: Any) -> bytes:
    return _sized(u, bytes, args, "bytes()")


def _call_bytearray(u: "_Unpickler", *args: Any) -> bytearray:
    return _sized(u, bytearray, args, "bytearray()")


def _atomic(ctor: Callable[..., Any], what: str) -> Callable[..., Any]:
    def call(u: "_Unpickler", *args: Any) -> Any:
        _atoms(args, what)
        u.budget.charge(sum(len(a) for a in args if isinstance(a, (str, bytes))) * 4 + 64)
        return ctor(*args)
    return call


def _call_range(u: "_Unpickler", *args: Any) -> range:
    _atoms(args, "range()")
    return range(*args)


def _call_slice(u: "_Unpickler", *args: Any) -> slice:
    return slice(*_atoms(args, "slice()"))


def _call_size(u: "_Unpickler", iterable: Any = ()) -> torch.Size:
    items = _items(u, iterable, "torch.Size()")
    return torch.Size(_dims(items, "torch.Size"))


def _numpy_scalar(u: "_Unpickler", dtype: Any = None, data: Any = b"") -> Any:
    if not isinstance(dtype, np.dtype) or dtype.hasobject or not isinstance(data, bytes) \
            or len(data) < dtype.itemsize:
        raise CheckpointFormatError(f"a NumPy scalar is rebuilt from {brief(dtype)} and {brief(data)}")
    return np.frombuffer(data, dtype=dtype, count=1)[0].copy()


def _numpy_dtype(u: "_Unpickler", spec: Any = None, *rest: Any) -> np.dtype:
    if not isinstance(spec, str) or len(spec) > 64:
        raise CheckpointFormatError(f"a NumPy dtype is rebuilt from {brief(spec)}")
    dt = np.dtype(spec)
    if dt.hasobject or dt.itemsize > u.limits.tensor_bytes:
        raise UnsafeCheckpointError(f"the checkpoint builds the NumPy dtype {spec!r}; refused")
    return dt


def _numpy_reconstruct(u: "_Unpickler", cls: Any = None, *rest: Any) -> np.ndarray:
    if cls is not G_NDARRAY:
        raise UnsafeCheckpointError(f"the checkpoint rebuilds a NumPy array of class {brief(cls)}; refused")
    return np.ndarray.__new__(np.ndarray, (0,), np.uint8)  # filled by BUILD (checked in _Unpickler._build)


def _path(u: "_Unpickler", *parts: Any) -> str:
    if not all(isinstance(p, str) for p in parts):
        raise CheckpointFormatError("a path is rebuilt from something other than strings")
    u.budget.charge(sum(len(p) for p in parts) + 64)
    return str(pathlib.PurePosixPath(*parts))


def _latin1_bytes(u: "_Unpickler", text: Any = None, encoding: Any = "latin1") -> bytes:
    """Protocol-2 pickles write ``bytes`` as ``_codecs.encode(text, 'latin1')``: only that form is rebuilt."""
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
        raise UnsafeCheckpointError("the checkpoint calls _codecs.encode with other than a latin1 string; refused")
    u.budget.charge(len(text) + 64)
    return text.encode("latin1")


def _device(u: "_Unpickler", *args: Any) -> torch.device:
    return torch.device(*_atoms(args, "torch.device()"))


G_REBUILD_TENSOR = _Global("torch._utils._rebuild_tensor", _rebuild_tensor)
G_REBUILD_TENSOR_V2 = _Global("torch._utils._rebuild_tensor_v2", _rebuild_tensor)
G_REBUILD_TENSOR_V3 = _Global("torch._utils._rebuild_tensor_v3", _rebuild_tensor_v3)
G_REBUILD_PARAMETER = _Global("torch._utils._rebuild_parameter", _rebuild_parameter)
G_PARAMETER = _Global("torch.nn.parameter.Parameter")  # a token: calling it is refused
G_TENSOR = _Global("torch.Tensor")
G_NDARRAY = _Global("numpy.ndarray")
G_LIST, G_TUPLE, G_SET = _Global("builtins.list", _call_list), _Global("builtins.tuple", _call_tuple), \
    _Global("builtins.set", _call_set)
G_DICT, G_INT, G_FLOAT, G_STR = _Global("builtins.dict", _call_dict), _Global("builtins.int", _atomic(int, "int()")), \
    _Global("builtins.float", _atomic(float, "float()")), _Global("builtins.str", _atomic(str, "str()"))

#: Every global the unpickler resolves to something real (others become placeholders, and calling them is refused).
REBUILD: dict[tuple[str, str], Any] = {
    ("torch._utils", "_rebuild_tensor"): G_REBUILD_TENSOR,
    ("torch._utils", "_rebuild_tensor_v2"): G_REBUILD_TENSOR_V2,
    ("torch._utils", "_rebuild_tensor_v3"): G_REBUILD_TENSOR_V3,
    ("torch._utils", "_rebuild_parameter"): G_REBUILD_PARAMETER,
    ("torch._utils", "_rebuild_parameter_with_state"): _Global("torch._utils._rebuild_parameter_with_state",
                                                               _rebuild_parameter),
    ("torch._tensor", "_rebuild_from_type_v2"): _Global("torch._tensor._rebuild_from_type_v2", _rebuild_from_type_v2),
    ("torch.nn.parameter", "Parameter"): G_PARAMETER,
    ("torch", "Tensor"): G_TENSOR,
    ("torch", "Size"): _Global("torch.Size", _call_size),
    ("torch", "device"): _Global("torch.device", _device),
    ("collections", "OrderedDict"): _Global("collections.OrderedDict", _call_ordered_dict),
    ("collections", "defaultdict"): _Global("collections.defaultdict", _call_defaultdict),
    ("_codecs", "encode"): _Global("_codecs.encode", _latin1_bytes),
    ("builtins", "set"): G_SET, ("builtins", "frozenset"): _Global("builtins.frozenset", _call_frozenset),
    ("builtins", "list"): G_LIST, ("builtins", "tuple"): G_TUPLE, ("builtins", "dict"): G_DICT,
    ("builtins", "int"): G_INT, ("builtins", "float"): G_FLOAT, ("builtins", "str"): G_STR,
    ("builtins", "bytes"): _Global("builtins.bytes", _call_bytes),
    ("builtins", "bytearray"): _Global("builtins.bytearray", _call_bytearray),
    ("builtins", "bool"): _Global("builtins.bool", _atomic(bool, "bool()")),
    ("builtins", "complex"): _Global("builtins.complex", _atomic(complex, "complex()")),
    ("builtins", "slice"): _Global("builtins.slice", _call_slice),
    ("builtins", "range"): _Global("builtins.range", _call_range),
    ("datetime", "datetime"): _Global("datetime.datetime", _atomic(datetime.datetime, "datetime()")),
    ("datetime", "date"): _Global("datetime.date", _atomic(datetime.date, "date()")),
    ("datetime", "timedelta"): _Global("datetime.timedelta", _atomic(datetime.timedelta, "timedelta()")),
    ("numpy", "dtype"): _Global("numpy.dtype", _numpy_dtype), ("numpy", "ndarray"): G_NDARRAY,
    **{(m, "scalar"): _Global(f"{m}.scalar", _numpy_scalar) for m in ("numpy.core.multiarray",
                                                                       "numpy._core.multiarray")},
    **{(m, "_reconstruct"): _Global(f"{m}._reconstruct", _numpy_reconstruct) for m in ("numpy.core.multiarray",
                                                                                         "numpy._core.multiarray")},
    **{("pathlib", n): _Global(f"pathlib.{n}", _path) for n in ("Path", "PosixPath", "WindowsPath", "PurePath",
                                                                 "PurePosixPath", "PureWindowsPath")},
    **{("torch", n): _StorageType(n) for n in _STORAGE_DTYPES},
    **{("torch", n): d for n, d in _DTYPES.items()},
}


# ------------------------------------------------------------------------------------------------ the unpickler
class _Done(Exception):
    def __init__(self, value: Any):
        self.value = value


class _Source:
    """The pickle's bytes: reads past the end are refused before anything is allocated for them."""

    def __init__(self, f: BinaryIO, nbytes: int):
        self.f, self.left = f, nbytes

    def read(self, n: int = -1) -> bytes:
        if n < 0 or n > self.left:
            raise CheckpointFormatError(f"the pickle asks for {human(max(n, 0))} where {human(self.left)} remain")
        data = self.f.read(n)
        self.left -= len(data)
        return data

    def readline(self) -> bytes:
        line = self.f.readline(self.left)
        self.left -= len(line)
        return line

    def readinto(self, buf: Any) -> int:
        view = memoryview(buf).cast("B")
        if len(view) > self.left:
            raise CheckpointFormatError(f"the pickle asks for {human(len(view))} where {human(self.left)} remain")
        n = self.f.readinto(view)
        self.left -= n
        return n


_OP = {name: getattr(pickle, name)[0] for name in (
    "MARK", "EMPTY_LIST", "LIST", "EMPTY_DICT", "DICT", "EMPTY_SET", "FROZENSET", "TUPLE", "TUPLE1", "TUPLE2",
    "TUPLE3", "NEWOBJ", "NEWOBJ_EX", "OBJ", "INST", "BUILD", "PUT", "BINPUT", "LONG_BINPUT", "MEMOIZE", "GLOBAL",
    "STACK_GLOBAL", "REDUCE", "APPEND", "APPENDS", "SETITEM", "SETITEMS", "ADDITEMS", "STOP", "FRAME", "BINBYTES8",
    "BINUNICODE8", "BYTEARRAY8", "EXT1", "EXT2", "EXT4")}

#: A bound on the bytes of Python objects each opcode makes (variable parts are charged where they are known).
_COST = {_OP[k]: v for k, v in {
    "MARK": 88, "EMPTY_LIST": 72, "LIST": 72, "EMPTY_DICT": 240, "DICT": 240, "EMPTY_SET": 232, "FROZENSET": 232,
    "TUPLE": 56, "TUPLE1": 64, "TUPLE2": 72, "TUPLE3": 80, "NEWOBJ": 400, "NEWOBJ_EX": 400, "OBJ": 400, "INST": 400,
    "BUILD": 64, "PUT": 128, "BINPUT": 128, "LONG_BINPUT": 128, "MEMOIZE": 128, "GLOBAL": 64, "STACK_GLOBAL": 64,
    "REDUCE": 64, "APPEND": 16, "SETITEM": 104}.items()}
_DEFAULT_COST = 40
_FREE_INT = (1 << 61) - 1  # ints below this hash to themselves: a file cannot make them collide


class _Unpickler(pickle._Unpickler):  # the pure-Python opcode handlers: a stack machine, no recursion
    """The restricted, bounded unpickler (module docstring). ``load_storage`` resolves ``('storage', ...)``
    persistent ids; ``placeholders=False`` refuses classes outside the rebuild list instead of making stubs."""

    dispatch = dict(pickle._Unpickler.dispatch)

    def __init__(self, source: _Source, load_storage: Callable[[tuple], torch.Tensor] | None, budget: _Budget,
                 placeholders: bool = True):
        super().__init__(source)
        self._source, self._load_storage, self.budget = source, load_storage, budget
        self.limits, self.placeholders = budget.limits, placeholders
        self.stubs: set[str] = set()
        self._classes: dict[str, type] = {}
        self._risky = 0

    # -------------------------------------------------------------------- the loop
    def load(self) -> Any:
        unframer = pickle._Unframer(self._source.read, self._source.readline)
        self._unframer = unframer
        consumed = [0]

        def read(n: int) -> bytes:
            data = unframer.read(n)
            consumed[0] += len(data)
            return data

        def readline() -> bytes:
            data = unframer.readline()
            consumed[0] += len(data)
            return data

        def readinto(buf: Any) -> int:
            n = unframer.readinto(buf)
            consumed[0] += n
            return n

        self.read, self.readline, self.readinto = read, readline, readinto
        self.metastack, self.stack = [], []
        self.append = self.stack.append
        self.proto = 0
        dispatch, charge, cost = self.dispatch, self.budget.charge, _COST
        try:
            while True:
                key = read(1)
                if not key:
                    raise EOFError("the pickle ends before its STOP opcode")
                op = key[0]
                handler = dispatch.get(op)
                if handler is None:
                    raise pickle.UnpicklingError(f"unknown pickle opcode 0x{op:02x}")
                start = consumed[0]
                handler(self)
                charge(cost.get(op, _DEFAULT_COST) + 2 * (consumed[0] - start))
        except _Done as done:
            return done.value

    def _stop(self) -> None:
        raise _Done(self.stack.pop())

    dispatch[_OP["STOP"]] = _stop

    # -------------------------------------------------------------------- names
    def find_class(self, module: str, name: str) -> Any:
        # protocol-2 files name Python 2 modules (``__builtin__.set``); map them as pickle's own find_class does
        if (module, name) in _compat_pickle.NAME_MAPPING:
            module, name = _compat_pickle.NAME_MAPPING[(module, name)]
        elif module in _compat_pickle.IMPORT_MAPPING:
            module = _compat_pickle.IMPORT_MAPPING[module]
        target = REBUILD.get((module, name))
        if target is not None:
            return target
        qual = f"{module}.{name}"
        if not self.placeholders:
            raise ForeignObjectError(f"it pickles {qual[:100]}, not only tensors and plain containers")
        cls = self._classes.get(qual)
        if cls is None:
            self.budget.charge(2048 + 2 * len(qual))
            cls = self._classes[qual] = _stub_class(module, name)
            self.stubs.add(qual)
        return cls

    def _ext(self) -> None:
        raise UnsafeCheckpointError("the checkpoint uses pickle extension codes (never written by torch.save); "
                                    "refused")

    for _name in ("EXT1", "EXT2", "EXT4"):
        dispatch[_OP[_name]] = _ext

    def persistent_load(self, pid: Any) -> Any:
        if not isinstance(pid, tuple) or not pid or pid[0] != "storage" or self._load_storage is None:
            raise CheckpointFormatError(f"unknown persistent id {brief(pid)}")
        return self._load_storage(pid)

    # -------------------------------------------------------------------- lengths read before they are allocated
    def _length(self, what: str) -> int:
        (n,) = struct.unpack("<Q", self.read(8))
        if n > self._source.left + self._frame_left():
            raise CheckpointFormatError(f"{what} of {human(n)} in a pickle with {human(self._source.left)} left")
        self.budget.charge(n)
        return n

    def _frame_left(self) -> int:
        frame = self._unframer.current_frame
        return 0 if frame is None else len(frame.getbuffer()) - frame.tell()

    def _frame(self) -> None:
        n = self._length("a pickle frame")
        self._unframer.load_frame(n)

    def _binbytes8(self) -> None:
        self.append(self.read(self._length("a bytes object")))

    def _binunicode8(self) -> None:
        self.append(str(self.read(self._length("a string")), "utf-8", "surrogatepass"))

    def _bytearray8(self) -> None:
        n = self._length("a bytearray")
        b = bytearray(n)
        self.readinto(b)
        self.append(b)

    dispatch[_OP["FRAME"]] = _frame
    dispatch[_OP["BINBYTES8"]] = _binbytes8
    dispatch[_OP["BINUNICODE8"]] = _binunicode8
    dispatch[_OP["BYTEARRAY8"]] = _bytearray8

    # -------------------------------------------------------------------- keys
    def check_key(self, key: Any) -> None:
        """Refuse dict keys and set items whose hashing a file could make exponential, crash the interpreter
        (deep tuples) or flood with collisions (numbers and tuples: their hashes are not randomised)."""
        kind = type(key)
        if kind is str or kind is bytes or kind is bool or key is None:
            return
        if kind is int and -_FREE_INT < key < _FREE_INT:
            return
        if kind not in (int, float, complex, tuple, frozenset, torch.Size):
            return  # placeholders, tokens and dtypes hash by identity
        self._risky += 1
        if self._risky > RISKY_KEYS:
            raise CheckpointLimitError(f"more than {RISKY_KEYS} dict keys or set items are numbers beyond 2**61, "
                                       f"floats or tuples (their hashes can be made to collide); refused")
        stack, nodes = [key], 0
        while stack:
            k = stack.pop()
            nodes += 1
            if nodes > KEY_NODES:
                raise CheckpointLimitError(f"a dict key or set item holds more than {KEY_NODES} elements; refused")
            if isinstance(k, int) and k.bit_length() > 4096:
                raise CheckpointLimitError(f"a dict key or set item is an integer of {k.bit_length()} bits; refused")
            if isinstance(k, tuple):
                stack.extend(k)
            elif isinstance(k, frozenset):
                nodes += len(k)  # its hash is cached from its items' hashes, which were checked when it was made

    # -------------------------------------------------------------------- containers
    def _append(self) -> None:
        value = self.stack.pop()
        target = self.stack[-1]
        if type(target) is not list:
            raise CheckpointFormatError(f"the pickle appends to {brief(target)}, not to a list")
        target.append(value)

    def _appends(self) -> None:
        items = self.pop_mark()
        target = self.stack[-1]
        if type(target) is not list:
            raise CheckpointFormatError(f"the pickle appends to {brief(target)}, not to a list")
        self.budget.charge(16 * len(items))
        target.extend(items)

    def _setitem(self) -> None:
        value = self.stack.pop()
        key = self.stack.pop()
        self._put_items(self.stack[-1], [key, value])

    def _setitems(self) -> None:
        items = self.pop_mark()
        self._put_items(self.stack[-1], items)

    def _put_items(self, target: Any, items: list) -> None:
        if not isinstance(target, dict) or len(items) % 2:
            raise CheckpointFormatError(f"the pickle sets items on {brief(target)}, not on a dict")
        self.budget.charge(104 * (len(items) // 2))
        for i in range(0, len(items), 2):
            self.check_key(items[i])
            target[items[i]] = items[i + 1]

    def _additems(self) -> None:
        items = self.pop_mark()
        target = self.stack[-1]
        if type(target) is not set:
            raise CheckpointFormatError(f"the pickle adds items to {brief(target)}, not to a set")
        self.budget.charge(104 * len(items))
        for k in items:
            self.check_key(k)
        target.update(items)

    def _frozenset(self) -> None:
        items = self.pop_mark()
        self.budget.charge(104 * len(items))
        for k in items:
            self.check_key(k)
        self.append(frozenset(items))

    def _dict(self) -> None:
        items = self.pop_mark()
        d: dict = {}
        self._put_items(d, items)
        self.append(d)

    def _list(self) -> None:
        items = self.pop_mark()
        self.budget.charge(16 * len(items))
        self.append(items)

    def _tuple(self) -> None:
        items = self.pop_mark()
        self.budget.charge(8 * len(items))
        self.append(tuple(items))

    dispatch[_OP["APPEND"]] = _append
    dispatch[_OP["APPENDS"]] = _appends
    dispatch[_OP["SETITEM"]] = _setitem
    dispatch[_OP["SETITEMS"]] = _setitems
    dispatch[_OP["ADDITEMS"]] = _additems
    dispatch[_OP["FROZENSET"]] = _frozenset
    dispatch[_OP["DICT"]] = _dict
    dispatch[_OP["LIST"]] = _list
    dispatch[_OP["TUPLE"]] = _tuple

    # -------------------------------------------------------------------- calls and instances
    def _call(self, func: Any, args: Any) -> Any:
        if isinstance(func, type) and issubclass(func, Stub):
            func()  # refuses, naming the class
        if not isinstance(func, _Global) or func.call is None:
            raise UnsafeCheckpointError(f"the checkpoint asks to call {brief(func)}(...); only the tensor-rebuild "
                                        f"list is called, so this call is refused and nothing from the file was run")
        if not isinstance(args, tuple):
            raise CheckpointFormatError(f"the arguments of {func.name} are {brief(args)}, not a tuple")
        return func.call(self, *args)

    def _reduce(self) -> None:
        args = self.stack.pop()
        self.stack[-1] = self._call(self.stack[-1], args)

    def _newobj(self) -> None:
        args = self.stack.pop()
        cls = self.stack.pop()
        self.append(self._new(cls, args, {}))

    def _newobj_ex(self) -> None:
        kwargs = self.stack.pop()
        args = self.stack.pop()
        cls = self.stack.pop()
        self.append(self._new(cls, args, kwargs))

    def _new(self, cls: Any, args: Any, kwargs: Any) -> Any:
        """``cls.__new__(cls, *args)``: a placeholder records its arguments; ``complex`` and the like are called."""
        if isinstance(cls, type) and issubclass(cls, Stub) and isinstance(args, tuple) and isinstance(kwargs, dict):
            return cls.__new__(cls, *args)
        if isinstance(cls, _Global) and cls.call is not None and not kwargs:
            return self._call(cls, args)
        raise UnsafeCheckpointError(f"the checkpoint asks to create {brief(cls)} with __new__; refused")

    def _obj(self) -> None:
        args = self.pop_mark()
        cls = args.pop(0)
        self.append(self._instantiate_checked(cls, tuple(args)))

    def _inst(self) -> None:
        module = self.readline()[:-1].decode("ascii")
        name = self.readline()[:-1].decode("ascii")
        cls = self.find_class(module, name)
        self.append(self._instantiate_checked(cls, tuple(self.pop_mark())))

    def _instantiate_checked(self, cls: Any, args: tuple) -> Any:
        if isinstance(cls, type) and issubclass(cls, Stub) and not args:
            return cls.__new__(cls)
        return self._call(cls, args)

    def _build(self) -> None:
        state = self.stack.pop()
        inst = self.stack[-1]
        if isinstance(inst, Stub):
            inst.__setstate__(state)
        elif type(inst) is np.ndarray:
            _set_array_state(inst, state)
        elif type(inst) is np.dtype or isinstance(inst, np.dtype):
            if not isinstance(state, tuple) or len(state) > 9 or not all(isinstance(s, (str, int, type(None)))
                                                                            for s in state):
                raise CheckpointFormatError(f"a NumPy dtype gets the state {brief(state)}")
            inst.__setstate__(state)
        elif type(inst) is collections.OrderedDict and isinstance(state, dict) \
                and all(type(k) is str for k in state):
            inst.__dict__.update(state)  # a state dict's ``_metadata``
        else:
            raise UnsafeCheckpointError(f"the checkpoint sets the state of {brief(inst)}; refused")

    def _ignore_buffers(self) -> None:
        raise CheckpointFormatError("the pickle refers to out-of-band buffers (never written by torch.save)")

    dispatch[_OP["REDUCE"]] = _reduce
    dispatch[_OP["NEWOBJ"]] = _newobj
    dispatch[_OP["NEWOBJ_EX"]] = _newobj_ex
    dispatch[_OP["OBJ"]] = _obj
    dispatch[_OP["INST"]] = _inst
    dispatch[_OP["BUILD"]] = _build
    dispatch[pickle.NEXT_BUFFER[0]] = _ignore_buffers
    dispatch[pickle.READONLY_BUFFER[0]] = _ignore_buffers
    del _name


def _set_array_state(arr: np.ndarray, state: Any) -> None:
    """``ndarray.__setstate__`` for plain numeric arrays whose bytes are all in the file."""
    if not (isinstance(state, tuple) and len(state) == 5 and isinstance(state[2], np.dtype)
            and not state[2].hasobject and isinstance(state[4], bytes)):
        raise CheckpointFormatError(f"a NumPy array gets the state {brief(state)}")
    shape = _dims(state[1], "NumPy shape")
    if math.prod(shape) * state[2].itemsize != len(state[4]):
        raise CheckpointFormatError(f"a NumPy array of shape {shape} comes with {human(len(state[4]))}")
    arr.__setstate__(state)


# ------------------------------------------------------------------------------------------------ the two formats
def _storage_key(pid: tuple, where: str) -> tuple[_StorageType, str, int | None]:
    _, storage_type, key, _location, numel = (list(pid) + [None] * 5)[:5]
    if not isinstance(storage_type, _StorageType):
        raise CheckpointFormatError(f"{where}: a storage of unknown type {brief(storage_type)}")
    if not isinstance(key, (str, int)) or isinstance(key, bool) or len(str(key)) > 256:
        raise CheckpointFormatError(f"{where}: a storage key {brief(key)}")
    if numel is not None and (not isinstance(numel, int) or numel < 0):
        raise CheckpointFormatError(f"{where}: a storage of {brief(numel)} elements")
    return storage_type, str(key), numel


def _unsafe_member(name: str) -> bool:
    parts = name.replace("\\", "/").split("/")
    return name.startswith(("/", "\\")) or ".." in parts or ":" in parts[0] or "\x00" in name


def _read_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo) -> bytearray:
    """A member's bytes into one buffer of its declared size (checked against the limits before this is called)."""
    buf = bytearray(info.file_size)
    view, pos = memoryview(buf), 0
    with zf.open(info) as m:
        while pos < len(buf):
            chunk = m.read(min(1 << 22, len(buf) - pos))
            if not chunk:
                break
            view[pos:pos + len(chunk)] = chunk
            pos += len(chunk)
    if pos != len(buf):
        raise CheckpointFormatError(f"archive member {info.filename} holds {pos} of its {info.file_size} bytes")
    return buf


def _load_zip(path: Path, zf: zipfile.ZipFile, limits: Limits, placeholders: bool) -> tuple[Any, set[str]]:
    infos = zf.infolist()
    for info in infos:
        if _unsafe_member(info.filename):
            raise CheckpointFormatError(f"{path}: archive member {brief(info.filename, 100)} points outside the "
                                        f"archive; refused")
    declared = sum(info.file_size for info in infos)
    if declared > limits.tensor_bytes:
        big = max(infos, key=lambda i: i.file_size)
        raise CheckpointLimitError(
            f"{path}: its archive members expand to {human(declared)} ({big.filename}: {human(big.file_size)} from "
            f"{human(big.compress_size)}), over {limits.of_file()}; refused before decompressing")
    names = {info.filename: info for info in infos}
    pkl = [n for n in names if n.endswith("data.pkl") and n.count("/") == 1]
    if not pkl:
        raise CheckpointFormatError(f"{path}: a zip file without <archive>/data.pkl; not a torch.save checkpoint")
    prefix = pkl[0][: -len("data.pkl")]
    byteorder = prefix + "byteorder"
    if byteorder in names and bytes(_read_member(zf, names[byteorder])).strip() not in (b"little", b""):
        raise CheckpointFormatError(f"{path}: big-endian checkpoints are not supported")
    cache: dict[str, torch.Tensor] = {}

    def load_storage(pid: tuple) -> torch.Tensor:
        storage_type, key, numel = _storage_key(pid, str(path))
        if key not in cache:
            member = names.get(f"{prefix}data/{key}")
            if member is None:
                raise CheckpointFormatError(f"{path}: storage {key} is missing from the archive")
            raw = _read_member(zf, member)
            itemsize = storage_type.itemsize
            if numel is not None and numel * itemsize > len(raw):
                raise CheckpointFormatError(f"{path}: a storage of {numel} elements has only {len(raw)} bytes")
            count = len(raw) // itemsize
            cache[key] = torch.frombuffer(raw, dtype=storage_type.dtype, count=count) if count \
                else torch.empty(0, dtype=storage_type.dtype)
        return cache[key]

    data = bytes(_read_member(zf, names[pkl[0]]))
    unpickler = _Unpickler(_Source(io.BytesIO(data), len(data)), load_storage, _Budget(limits), placeholders)
    obj = unpickler.load()
    return obj, unpickler.stubs


_LEGACY_MAGIC = 0x1950A86A20F9469CFC6C


def _load_legacy(path: Path, f: BinaryIO, limits: Limits, placeholders: bool) -> tuple[Any, set[str]]:
    """The pre-1.6 format: magic, protocol, sys info, the object, the storage keys, then each storage's bytes.

    Storages are allocated when the object pickle names them, so their declared sizes together must fit in the
    file's bytes; every storage named must then be filled from the file, or the read is refused."""
    source, budget = _Source(f, limits.file_bytes), _Budget(limits)

    def plain() -> Any:
        return _Unpickler(source, None, budget, placeholders=False).load()

    try:
        magic = plain()
    except (HarnessError, *_READ_ERRORS):
        magic = None
    if type(magic) is not int or magic != _LEGACY_MAGIC:
        raise CheckpointFormatError(f"{path}: not a PyTorch checkpoint (no zip archive, no legacy magic number)")
    plain()  # protocol version
    plain()  # sys info
    loaded: dict[str, torch.Tensor] = {}
    declared = [0]

    def load_storage(pid: tuple) -> torch.Tensor:
        storage_type, key, numel = _storage_key(pid, str(path))
        if key not in loaded:
            nbytes = (numel or 0) * storage_type.itemsize
            declared[0] += nbytes
            if declared[0] > limits.file_bytes:
                raise CheckpointLimitError(f"{path}: its storages declare {human(declared[0])}, more than the file's "
                                           f"{human(limits.file_bytes)}; refused before allocating")
            loaded[key] = torch.empty(int(numel or 0), dtype=storage_type.dtype)
        return loaded[key]

    unpickler = _Unpickler(source, load_storage, budget, placeholders)
    obj = unpickler.load()
    keys = plain()
    if not isinstance(keys, (list, tuple)) or not all(isinstance(k, str) for k in keys):
        raise CheckpointFormatError(f"{path}: the storage key list is {brief(keys)}, not a list of names")
    filled: set[str] = set()
    for key in keys:
        raw = source.read(8)
        target = loaded.get(key)
        if len(raw) != 8 or target is None or key in filled \
                or int.from_bytes(raw, "little") != target.numel():
            raise CheckpointFormatError(f"{path}: storage {brief(key)} does not match the checkpoint's references")
        flat = target.view(-1).view(torch.uint8) if target.numel() else target
        if target.numel() and source.readinto(flat.numpy()) != flat.numel():
            raise CheckpointFormatError(f"{path}: truncated storage {key}")
        filled.add(key)
    missing = sorted(set(loaded) - filled)
    if missing:
        raise CheckpointFormatError(
            f"{path}: storage {brief(missing[0])} is referenced but its bytes are not in the file ({len(missing)} "
            f"missing); refused (it would read as uninitialised memory)")
    return obj, unpickler.stubs


_READ_ERRORS = (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, KeyError, IndexError,
                RuntimeError, zipfile.BadZipFile, zlib.error, struct.error, OverflowError, NotImplementedError,
                UnicodeError, LookupError)


def load_checkpoint(path: str | Path, placeholders: bool = True) -> tuple[Any, set[str]]:
    """Read a ``torch.save`` file with the restricted, bounded unpickler; returns ``(object, placeholder class
    names)``. Every failure is a one-line :class:`CheckpointFormatError` (or subclass) naming the file."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointFormatError(f"checkpoint {path} does not exist")
    limits = Limits(path.stat().st_size)
    try:
        if zipfile.is_zipfile(path):
            with zipfile.ZipFile(path) as zf:
                return _load_zip(path, zf, limits, placeholders)
        with open(path, "rb") as f:
            return _load_legacy(path, f, limits, placeholders)
    except HarnessError as exc:
        if str(path) in str(exc):
            raise
        raise type(exc)(f"{path}: {exc}") from None
    except MemoryError:
        raise CheckpointLimitError(f"{path}: ran out of memory while reading it ({human(limits.file_bytes)} on "
                                   f"disk); refused") from None
    except RecursionError:
        raise CheckpointFormatError(f"{path}: nested too deeply to read") from None
    except _READ_ERRORS as exc:
        raise CheckpointFormatError(f"{path}: not a readable PyTorch checkpoint ({type(exc).__name__}: "
                                    f"{str(exc).splitlines()[0][:200] if str(exc) else ''})") from None


def load_plain(path: str | Path) -> Any:
    """A checkpoint of tensors and plain containers only (what ``torch.load(weights_only=True)`` accepts), read
    with the same bounds; a class outside the rebuild list raises :class:`ForeignObjectError`."""
    obj, _ = load_checkpoint(path, placeholders=False)
    return obj
