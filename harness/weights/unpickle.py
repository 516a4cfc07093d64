"""Reading pickled PyTorch checkpoints without executing any code from the file.

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
  parameters and buffers can be found in the recorded state (``harness.weights.tree``);
* **every other callable** is refused: a file that asks to call ``posix.system``, ``builtins.eval`` or any name
  outside the rebuild list raises :class:`UnsafeCheckpointError` naming it, before anything is called.

Placeholders are created with ``NEWOBJ`` (``cls.__new__``), which is how protocol-2 pickles create instances;
calling a placeholder class (the ``REDUCE`` opcode: "call this with these arguments") is the refusal.
"""

from __future__ import annotations

import _compat_pickle
import collections
import datetime
import io
import pathlib
import pickle
import zipfile
from pathlib import Path
from typing import Any, BinaryIO, Callable

import numpy as np
import torch

from harness.errors import HarnessError


class UnsafeCheckpointError(HarnessError):
    """The checkpoint asks for a call outside the tensor-rebuild list (possibly code execution)."""


class CheckpointFormatError(HarnessError):
    """The file is not a readable PyTorch checkpoint."""


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
        return obj

    def __setstate__(self, state: Any) -> None:
        object.__setattr__(self, "__stub_state__", state)

    def __reduce__(self) -> Any:  # never pickled back out
        raise TypeError("placeholders from a restricted checkpoint read cannot be pickled")

    def __repr__(self) -> str:
        return f"<{self.__stub_name__} (placeholder)>"

    @property
    def stub_name(self) -> str:
        return type(self).__stub_name__

    @property
    def state(self) -> dict[str, Any]:
        """The recorded state as a dict (``{}`` when the file gave none or gave a non-dict state)."""
        st = self.__stub_state__  # type: ignore[attr-defined]
        if isinstance(st, tuple) and len(st) == 2 and isinstance(st[0], dict):  # (dict, slotstate)
            return {**st[0], **(st[1] or {})}
        return st if isinstance(st, dict) else {}

    def get(self, key: str, default: Any = None) -> Any:
        return self.state.get(key, default)


_STUBS: dict[str, type] = {}


def stub_class(module: str, name: str) -> type:
    """One placeholder class per qualified name (so identical names compare equal across a file)."""
    qual = f"{module}.{name}"
    cls = _STUBS.get(qual)
    if cls is None:
        cls = _StubMeta(name, (Stub,), {"__stub_name__": qual, "__module__": "harness.weights.stubs"})
        _STUBS[qual] = cls
    return cls


# ------------------------------------------------------------------------------------------------ rebuilders
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


def _view(storage: torch.Tensor, offset: int, size: Any, stride: Any) -> torch.Tensor:
    if not isinstance(storage, torch.Tensor):
        raise CheckpointFormatError(f"a tensor is rebuilt from {type(storage).__name__}, not from a storage")
    size, stride = tuple(int(s) for s in size), tuple(int(s) for s in stride)
    need = int(offset) + sum((s - 1) * st for s, st in zip(size, stride)) + 1 if all(size) else 0
    if need > storage.numel():
        raise CheckpointFormatError(f"a tensor of size {size} reaches element {need} of a storage of {storage.numel()}")
    # a view: legacy files fill their storages after the object pickle, and views see the bytes once they land
    return storage.as_strided(size, stride, int(offset)) if all(size) else storage.new_empty(size)


def _rebuild_tensor(storage: Any, offset: int, size: Any, stride: Any, *rest: Any) -> torch.Tensor:
    return _view(storage, offset, size, stride)


def _rebuild_tensor_v3(storage: Any, offset: int, size: Any, stride: Any, requires_grad: Any, hooks: Any,
                       dtype: Any, *rest: Any) -> torch.Tensor:
    t = storage
    if isinstance(dtype, torch.dtype) and t.dtype != dtype:
        t = t.view(torch.uint8).view(dtype)
    return _view(t, offset, size, stride)


def _rebuild_parameter(data: Any, requires_grad: Any = True, *rest: Any) -> torch.Tensor:
    if not isinstance(data, torch.Tensor):
        raise CheckpointFormatError(f"a parameter is rebuilt from {type(data).__name__}, not from a tensor")
    return torch.nn.Parameter(data, requires_grad=bool(requires_grad))


def _rebuild_from_type_v2(func: Any, new_type: Any, args: Any, state: Any) -> Any:
    if func not in (_rebuild_tensor, _rebuild_tensor_v3, _rebuild_parameter):
        raise UnsafeCheckpointError("the checkpoint rebuilds a tensor subclass through a function outside the "
                                    "rebuild list; refused")
    t = func(*args)
    return torch.nn.Parameter(t) if new_type is torch.nn.Parameter else t


def _ordered_dict(*args: Any) -> collections.OrderedDict:
    return collections.OrderedDict(*args)


def _numpy_scalar(dtype: Any, data: bytes = b"") -> Any:
    return np.frombuffer(data, dtype=np.dtype(dtype))[0].copy()


def _numpy_dtype(spec: Any, *rest: Any) -> np.dtype:
    if not isinstance(spec, str):
        raise CheckpointFormatError(f"a NumPy dtype is rebuilt from {type(spec).__name__}")
    return np.dtype(spec)


def _numpy_reconstruct(cls: Any, shape: Any, dtype_code: Any) -> np.ndarray:
    if cls is not np.ndarray:
        raise UnsafeCheckpointError(f"the checkpoint rebuilds a NumPy array of class {cls!r}; refused")
    return np.ndarray.__new__(np.ndarray, (0,), np.uint8)  # filled by BUILD (ndarray.__setstate__: data only)


def _path(*parts: Any) -> str:
    return str(pathlib.PurePosixPath(*[str(p) for p in parts]))


def _latin1_bytes(text: Any, encoding: Any = "latin1") -> bytes:
    """Protocol-2 pickles write ``bytes`` as ``_codecs.encode(text, 'latin1')``: only that form is rebuilt."""
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
        raise UnsafeCheckpointError("the checkpoint calls _codecs.encode with other than a latin1 string; refused")
    return text.encode("latin1")


def _defaultdict(factory: Any = None, *rest: Any) -> collections.defaultdict:
    if factory not in (None, list, dict, int, float, set, str, tuple):
        raise UnsafeCheckpointError(f"the checkpoint builds a defaultdict with factory {factory!r}; refused")
    return collections.defaultdict(factory, *rest)


#: Every global the unpickler resolves to something real (others become placeholders, and calling them is refused).
REBUILD: dict[tuple[str, str], Any] = {
    ("torch._utils", "_rebuild_tensor"): _rebuild_tensor,
    ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor,
    ("torch._utils", "_rebuild_tensor_v3"): _rebuild_tensor_v3,
    ("torch._utils", "_rebuild_parameter"): _rebuild_parameter,
    ("torch._utils", "_rebuild_parameter_with_state"): _rebuild_parameter,
    ("torch._tensor", "_rebuild_from_type_v2"): _rebuild_from_type_v2,
    ("torch.nn.parameter", "Parameter"): torch.nn.Parameter,
    ("torch", "Tensor"): torch.Tensor,
    ("torch", "Size"): torch.Size,
    ("torch", "device"): torch.device,
    ("collections", "OrderedDict"): _ordered_dict,
    ("_codecs", "encode"): _latin1_bytes,
    ("collections", "defaultdict"): _defaultdict,
    ("builtins", "set"): set, ("builtins", "frozenset"): frozenset, ("builtins", "list"): list,
    ("builtins", "dict"): dict, ("builtins", "tuple"): tuple, ("builtins", "int"): int, ("builtins", "float"): float,
    ("builtins", "str"): str, ("builtins", "bytes"): bytes, ("builtins", "bytearray"): bytearray,
    ("builtins", "bool"): bool, ("builtins", "complex"): complex, ("builtins", "slice"): slice,
    ("builtins", "range"): range,
    ("datetime", "datetime"): datetime.datetime, ("datetime", "date"): datetime.date,
    ("datetime", "timedelta"): datetime.timedelta,
    ("numpy", "dtype"): _numpy_dtype, ("numpy", "ndarray"): np.ndarray,
    ("numpy.core.multiarray", "scalar"): _numpy_scalar, ("numpy._core.multiarray", "scalar"): _numpy_scalar,
    ("numpy.core.multiarray", "_reconstruct"): _numpy_reconstruct,
    ("numpy._core.multiarray", "_reconstruct"): _numpy_reconstruct,
    **{("pathlib", n): _path for n in ("Path", "PosixPath", "WindowsPath", "PurePath", "PurePosixPath",
                                       "PureWindowsPath")},
    **{("torch", n): _StorageType(n) for n in _STORAGE_DTYPES},
    **{("torch", n): d for n, d in _DTYPES.items()},
}


class _RestrictedUnpickler(pickle.Unpickler):
    def __init__(self, file: BinaryIO, load_storage: Callable[[tuple], torch.Tensor], where: str):
        super().__init__(file)
        self._load_storage, self._where = load_storage, where
        self.stubs: set[str] = set()

    def find_class(self, module: str, name: str) -> Any:
        # protocol-2 files name Python 2 modules (``__builtin__.set``); map them as pickle's own find_class does
        if (module, name) in _compat_pickle.NAME_MAPPING:
            module, name = _compat_pickle.NAME_MAPPING[(module, name)]
        elif module in _compat_pickle.IMPORT_MAPPING:
            module = _compat_pickle.IMPORT_MAPPING[module]
        target = REBUILD.get((module, name))
        if target is not None:
            return target
        self.stubs.add(f"{module}.{name}")
        return stub_class(module, name)

    def persistent_load(self, pid: Any) -> Any:
        if not isinstance(pid, tuple) or not pid or pid[0] != "storage":
            raise CheckpointFormatError(f"{self._where}: unknown persistent id {str(pid)[:80]}")
        return self._load_storage(pid)


def _storage_from_bytes(raw: bytes, storage_type: Any, numel: Any, where: str) -> torch.Tensor:
    if not isinstance(storage_type, _StorageType):
        raise CheckpointFormatError(f"{where}: a storage of unknown type {storage_type!r}")
    dtype = storage_type.dtype
    itemsize = torch.empty((), dtype=dtype).element_size()
    if storage_type.name == "UntypedStorage":
        itemsize = 1
    count = len(raw) // itemsize
    if numel is not None and int(numel) * itemsize > len(raw):
        raise CheckpointFormatError(f"{where}: a storage of {numel} elements has only {len(raw)} bytes")
    if count == 0:
        return torch.empty(0, dtype=dtype)
    return torch.frombuffer(bytearray(raw[: count * itemsize]), dtype=dtype)


def _load_zip(path: Path, zf: zipfile.ZipFile) -> tuple[Any, set[str]]:
    names = zf.namelist()
    pkl = [n for n in names if n.endswith("data.pkl") and n.count("/") == 1]
    if not pkl:
        raise CheckpointFormatError(f"{path}: a zip file without <archive>/data.pkl; not a torch.save checkpoint")
    prefix = pkl[0][: -len("data.pkl")]
    byteorder = prefix + "byteorder"
    if byteorder in names and zf.read(byteorder).strip() not in (b"little", b""):
        raise CheckpointFormatError(f"{path}: big-endian checkpoints are not supported")
    cache: dict[str, torch.Tensor] = {}

    def load_storage(pid: tuple) -> torch.Tensor:
        _, storage_type, key, _location, numel = (list(pid) + [None] * 5)[:5]
        key = str(key)
        if key not in cache:
            member = f"{prefix}data/{key}"
            if member not in names:
                raise CheckpointFormatError(f"{path}: storage {key} is missing from the archive")
            cache[key] = _storage_from_bytes(zf.read(member), storage_type, numel, str(path))
        return cache[key]

    unpickler = _RestrictedUnpickler(io.BytesIO(zf.read(pkl[0])), load_storage, str(path))
    obj = unpickler.load()
    return obj, unpickler.stubs


_LEGACY_MAGIC = 0x1950A86A20F9469CFC6C


def _load_legacy(path: Path, f: BinaryIO) -> tuple[Any, set[str]]:
    """The pre-1.6 format: magic, protocol, sys info, the object, the storage keys, then each storage's bytes."""
    def plain() -> Any:
        u = _RestrictedUnpickler(f, lambda pid: None, str(path))  # type: ignore[arg-type,return-value]
        return u.load()

    if plain() != _LEGACY_MAGIC:
        raise CheckpointFormatError(f"{path}: not a PyTorch checkpoint (no zip archive, no legacy magic number)")
    plain()  # protocol version
    plain()  # sys info
    loaded: dict[str, torch.Tensor] = {}

    def load_storage(pid: tuple) -> torch.Tensor:
        _, storage_type, key, _location, numel = (list(pid) + [None] * 5)[:5]
        key = str(key)
        if key not in loaded:
            if not isinstance(storage_type, _StorageType):
                raise CheckpointFormatError(f"{path}: a storage of unknown type {storage_type!r}")
            loaded[key] = torch.empty(int(numel or 0), dtype=storage_type.dtype)
        return loaded[key]

    unpickler = _RestrictedUnpickler(f, load_storage, str(path))
    obj = unpickler.load()
    keys = plain()
    for key in keys:
        raw_numel = int.from_bytes(f.read(8), "little")
        target = loaded.get(str(key))
        if target is None or raw_numel != target.numel():
            raise CheckpointFormatError(f"{path}: storage {key} does not match the checkpoint's references")
        nbytes = raw_numel * target.element_size()
        data = f.read(nbytes)
        if len(data) != nbytes:
            raise CheckpointFormatError(f"{path}: truncated storage {key}")
        if nbytes:
            target.copy_(torch.frombuffer(bytearray(data), dtype=target.dtype))
    return obj, unpickler.stubs


def load_checkpoint(path: str | Path) -> tuple[Any, set[str]]:
    """Read a ``torch.save`` file with the restricted unpickler; returns ``(object, placeholder class names)``."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointFormatError(f"checkpoint {path} does not exist")
    try:
        if zipfile.is_zipfile(path):
            with zipfile.ZipFile(path) as zf:
                return _load_zip(path, zf)
        with open(path, "rb") as f:
            return _load_legacy(path, f)
    except HarnessError as exc:
        if str(path) in str(exc):
            raise
        raise type(exc)(f"{path}: {exc}") from None
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, KeyError, IndexError,
            RuntimeError, zipfile.BadZipFile) as exc:
        raise CheckpointFormatError(f"{path}: not a readable PyTorch checkpoint ({type(exc).__name__}: "
                                    f"{str(exc).splitlines()[0] if str(exc) else ''})") from None
