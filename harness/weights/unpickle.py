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
bounded by the file's own size F (the numbers live in ``harness.weights.bounds``), and a file that asks for more is
refused with a one-line :class:`CheckpointLimitError` before the memory is taken:

* archive members: their declared uncompressed sizes together at most ``ARCHIVE_MULTIPLE`` (2) x F, checked
  before any is read (a deflate bomb is refused up front); a legacy file's storages together at most F, checked
  before they are allocated, and a storage the file leaves out is refused (it would read as uninitialised memory);
* each tensor: at most ``SIZE_MULTIPLE`` (4) x F bytes once materialised as float32 (zero-stride ``expand`` tricks
  are refused);
* the Python objects the pickle rebuilds, with the archive's entry records: at most ``METADATA_FLOOR`` (48 MiB) +
  ``METADATA_MULTIPLE`` (2) x F, charged opcode by opcode as they are made; allowed calls such as ``bytearray(n)``
  or ``list(range(n))`` are charged before they allocate;
* dict keys and set items: small (hashing a deep or shared tuple takes exponential time or crashes the
  interpreter), and at most ``RISKY_KEYS`` keys whose hash a file can choose (numbers beyond 2**61, floats, tuples);
* nothing is walked recursively: the unpickler is a stack machine over ``pickle``'s pure-Python opcode handlers,
  and the walks over its result (``harness.weights.tree``, ``harness.weights.layout``) are iterative and visit a
  shared object once.

With these, a whole import stays within ``PEAK_FLOOR`` (64 MiB) + ``PEAK_MULTIPLE`` (8) x F of memory above the
interpreter's own (``tests/test_weights_hostile.py`` measures it on a corpus of hostile files).

Kept in one module: the restricted unpickler and the two file layouts it reads charge the same ``Limits`` and
``Budget`` at every step; what a pickle may rebuild is ``harness.weights.rebuild``.
"""

from __future__ import annotations

import _compat_pickle
import collections
import io
import math
import pickle
import struct
import zipfile
import zlib
from pathlib import Path
from typing import Any, BinaryIO, Callable

import numpy as np
import torch

from harness.errors import HarnessError
from harness.weights.bounds import (
    ARCHIVE_MULTIPLE,
    KEY_NODES,
    METADATA_FLOOR,
    METADATA_MULTIPLE,
    PEAK_FLOOR,
    PEAK_MULTIPLE,
    PIECE_BYTES,
    RISKY_KEYS,
    SIZE_MULTIPLE,
    ZIP_ENTRY_BYTES,
    Budget,
    CheckpointFormatError,
    CheckpointLimitError,
    ForeignObjectError,
    Limits,
    MiB,
    UnsafeCheckpointError,
    human,
)
from harness.weights.rebuild import REBUILD, StorageType, Stub, Token, brief, out_itemsize, stub_class, tensor_dims

__all__ = [
    "load_checkpoint",
    "load_plain",
    "Stub",
    "stub_class",
    "REBUILD",
    "CheckpointFormatError",
    "CheckpointLimitError",
    "ForeignObjectError",
    "UnsafeCheckpointError",
    "Limits",
    "brief",
    "human",
    "out_itemsize",
    "MiB",
    "SIZE_MULTIPLE",
    "ARCHIVE_MULTIPLE",
    "METADATA_FLOOR",
    "METADATA_MULTIPLE",
    "PEAK_FLOOR",
    "PEAK_MULTIPLE",
    "PIECE_BYTES",
    "KEY_NODES",
    "RISKY_KEYS",
]


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


_OP = {
    name: getattr(pickle, name)[0]
    for name in (
        "MARK",
        "EMPTY_LIST",
        "LIST",
        "EMPTY_DICT",
        "DICT",
        "EMPTY_SET",
        "FROZENSET",
        "TUPLE",
        "TUPLE1",
        "TUPLE2",
        "TUPLE3",
        "NEWOBJ",
        "NEWOBJ_EX",
        "OBJ",
        "INST",
        "BUILD",
        "PUT",
        "BINPUT",
        "LONG_BINPUT",
        "MEMOIZE",
        "GLOBAL",
        "STACK_GLOBAL",
        "REDUCE",
        "APPEND",
        "APPENDS",
        "SETITEM",
        "SETITEMS",
        "ADDITEMS",
        "STOP",
        "FRAME",
        "BINBYTES8",
        "BINUNICODE8",
        "BYTEARRAY8",
        "EXT1",
        "EXT2",
        "EXT4",
    )
}

#: A bound on the bytes of Python objects each opcode makes (variable parts are charged where they are known).
_COST = {
    _OP[k]: v
    for k, v in {
        "MARK": 88,
        "EMPTY_LIST": 72,
        "LIST": 72,
        "EMPTY_DICT": 240,
        "DICT": 240,
        "EMPTY_SET": 232,
        "FROZENSET": 232,
        "TUPLE": 56,
        "TUPLE1": 64,
        "TUPLE2": 72,
        "TUPLE3": 80,
        "NEWOBJ": 400,
        "NEWOBJ_EX": 400,
        "OBJ": 400,
        "INST": 400,
        "BUILD": 64,
        "PUT": 128,
        "BINPUT": 128,
        "LONG_BINPUT": 128,
        "MEMOIZE": 128,
        "GLOBAL": 64,
        "STACK_GLOBAL": 64,
        "REDUCE": 64,
        "APPEND": 16,
        "SETITEM": 104,
    }.items()
}
_DEFAULT_COST = 40
_FREE_INT = (1 << 61) - 1  # ints below this hash to themselves: a file cannot make them collide


def _handles(*names: str) -> Callable[[Callable[..., None]], Callable[..., None]]:
    """Mark an ``_Unpickler`` method as the handler of the pickle opcodes ``names``; the class's dispatch table is
    filled from these marks."""

    def mark(handler: Callable[..., None]) -> Callable[..., None]:
        setattr(handler, "opcodes", tuple(getattr(pickle, name)[0] for name in names))
        return handler

    return mark


class _Unpickler(pickle._Unpickler):  # the pure-Python opcode handlers: a stack machine, no recursion
    """The restricted, bounded unpickler (module docstring). ``load_storage`` resolves ``('storage', ...)``
    persistent ids; ``placeholders=False`` refuses classes outside the rebuild list instead of making stubs."""

    dispatch = dict(pickle._Unpickler.dispatch)

    def __init__(
        self,
        source: _Source,
        load_storage: Callable[[tuple], torch.Tensor] | None,
        budget: Budget,
        placeholders: bool = True,
    ):
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
        self.metastack: list[list[Any]] = []
        self.stack: list[Any] = []
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
                handler(self)  # type: ignore[arg-type]
                charge(cost.get(op, _DEFAULT_COST) + 2 * (consumed[0] - start))
        except _Done as done:
            return done.value

    @_handles("STOP")
    def _stop(self) -> None:
        raise _Done(self.stack.pop())

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
            cls = self._classes[qual] = stub_class(module, name)
            self.stubs.add(qual)
        return cls

    @_handles("EXT1", "EXT2", "EXT4")
    def _ext(self) -> None:
        raise UnsafeCheckpointError("the checkpoint uses pickle extension codes (never written by torch.save); refused")

    def persistent_load(self, pid: Any) -> Any:
        if isinstance(pid, tuple) and len(pid) == 4 and pid[0] == "module" and self._load_storage is not None:
            # a pre-1.6 whole-model file names each module class with ('module', class, source file, source);
            # the class came through find_class (a placeholder or a rebuild-list name): nothing else is used
            if not isinstance(pid[1], type):
                raise CheckpointFormatError(f"a module persistent id names {brief(pid[1])}, not a class")
            return pid[1]
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

    @_handles("FRAME")
    def _frame(self) -> None:
        n = self._length("a pickle frame")
        self._unframer.load_frame(n)

    @_handles("BINBYTES8")
    def _binbytes8(self) -> None:
        self.append(self.read(self._length("a bytes object")))

    @_handles("BINUNICODE8")
    def _binunicode8(self) -> None:
        self.append(str(self.read(self._length("a string")), "utf-8", "surrogatepass"))

    @_handles("BYTEARRAY8")
    def _bytearray8(self) -> None:
        n = self._length("a bytearray")
        b = bytearray(n)
        self.readinto(b)
        self.append(b)

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
            raise CheckpointLimitError(
                f"more than {RISKY_KEYS} dict keys or set items are numbers beyond 2**61, "
                f"floats or tuples (their hashes can be made to collide); refused"
            )
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
    def _target(self, kind: type, verb: str) -> Any:
        """The container on top of the stack, which the pickle ``verb`` (e.g. "appends to"): it must be a ``kind``."""
        target = self.stack[-1]
        if type(target) is not kind:
            raise CheckpointFormatError(f"the pickle {verb} {brief(target)}, not to a {kind.__name__}")
        return target

    def _set_items(self, items: list) -> list:
        """``items`` for a set: charged to the budget, each checked as a key (``check_key``)."""
        self.budget.charge(104 * len(items))
        for k in items:
            self.check_key(k)
        return items

    @_handles("APPEND")
    def _append(self) -> None:
        value = self.stack.pop()
        self._target(list, "appends to").append(value)

    @_handles("APPENDS")
    def _appends(self) -> None:
        items = self.pop_mark()
        target = self._target(list, "appends to")
        self.budget.charge(16 * len(items))
        target.extend(items)

    @_handles("SETITEM")
    def _setitem(self) -> None:
        value = self.stack.pop()
        key = self.stack.pop()
        self._put_items(self.stack[-1], [key, value])

    @_handles("SETITEMS")
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

    @_handles("ADDITEMS")
    def _additems(self) -> None:
        items = self.pop_mark()
        target = self._target(set, "adds items to")
        target.update(self._set_items(items))

    @_handles("FROZENSET")
    def _frozenset(self) -> None:
        self.append(frozenset(self._set_items(self.pop_mark())))

    @_handles("DICT")
    def _dict(self) -> None:
        items = self.pop_mark()
        d: dict = {}
        self._put_items(d, items)
        self.append(d)

    @_handles("LIST")
    def _list(self) -> None:
        items = self.pop_mark()
        self.budget.charge(16 * len(items))
        self.append(items)

    @_handles("TUPLE")
    def _tuple(self) -> None:
        items = self.pop_mark()
        self.budget.charge(8 * len(items))
        self.append(tuple(items))

    # -------------------------------------------------------------------- calls and instances
    def _call(self, func: Any, args: Any) -> Any:
        if isinstance(func, type) and issubclass(func, Stub):
            func()  # refuses, naming the class
        if not isinstance(func, Token) or func.call is None:
            raise UnsafeCheckpointError(
                f"the checkpoint asks to call {brief(func)}(...); only the tensor-rebuild "
                f"list is called, so this call is refused and nothing from the file was run"
            )
        if not isinstance(args, tuple):
            raise CheckpointFormatError(f"the arguments of {func.name} are {brief(args)}, not a tuple")
        return func.call(self, *args)

    @_handles("REDUCE")
    def _reduce(self) -> None:
        args = self.stack.pop()
        self.stack[-1] = self._call(self.stack[-1], args)

    @_handles("NEWOBJ")
    def _newobj(self) -> None:
        args = self.stack.pop()
        cls = self.stack.pop()
        self.append(self._new(cls, args, {}))

    @_handles("NEWOBJ_EX")
    def _newobj_ex(self) -> None:
        kwargs = self.stack.pop()
        args = self.stack.pop()
        cls = self.stack.pop()
        self.append(self._new(cls, args, kwargs))

    def _new(self, cls: Any, args: Any, kwargs: Any) -> Any:
        """``cls.__new__(cls, *args)``: a placeholder records its arguments; ``complex`` and the like are called."""
        if isinstance(cls, type) and issubclass(cls, Stub) and isinstance(args, tuple) and isinstance(kwargs, dict):
            return cls.__new__(cls, *args)
        if isinstance(cls, Token) and cls.call is not None and not kwargs:
            return self._call(cls, args)
        raise UnsafeCheckpointError(f"the checkpoint asks to create {brief(cls)} with __new__; refused")

    @_handles("OBJ")
    def _obj(self) -> None:
        args = self.pop_mark()
        cls = args.pop(0)
        self.append(self._instantiate_checked(cls, tuple(args)))

    @_handles("INST")
    def _inst(self) -> None:
        module = self.readline()[:-1].decode("ascii")
        name = self.readline()[:-1].decode("ascii")
        cls = self.find_class(module, name)
        self.append(self._instantiate_checked(cls, tuple(self.pop_mark())))

    def _instantiate_checked(self, cls: Any, args: tuple) -> Any:
        if isinstance(cls, type) and issubclass(cls, Stub) and not args:
            return cls.__new__(cls)
        return self._call(cls, args)

    @_handles("BUILD")
    def _build(self) -> None:
        state = self.stack.pop()
        inst = self.stack[-1]
        if isinstance(inst, Stub):
            inst.__setstate__(state)
        elif type(inst) is np.ndarray:
            _set_array_state(inst, state)
        elif type(inst) is np.dtype or isinstance(inst, np.dtype):
            if (
                not isinstance(state, tuple)
                or len(state) > 9
                or not all(isinstance(s, (str, int, type(None))) for s in state)
            ):
                raise CheckpointFormatError(f"a NumPy dtype gets the state {brief(state)}")
            inst.__setstate__(state)
        elif type(inst) is collections.OrderedDict and isinstance(state, dict) and all(type(k) is str for k in state):
            inst.__dict__.update(state)  # a state dict's ``_metadata``
        else:
            raise UnsafeCheckpointError(f"the checkpoint sets the state of {brief(inst)}; refused")

    @_handles("NEXT_BUFFER", "READONLY_BUFFER")
    def _ignore_buffers(self) -> None:
        raise CheckpointFormatError("the pickle refers to out-of-band buffers (never written by torch.save)")


for _handler in list(vars(_Unpickler).values()):
    for _opcode in getattr(_handler, "opcodes", ()):
        _Unpickler.dispatch[_opcode] = _handler
del _handler, _opcode


def _set_array_state(arr: np.ndarray, state: Any) -> None:
    """``ndarray.__setstate__`` for plain numeric arrays whose bytes are all in the file."""
    if not (
        isinstance(state, tuple)
        and len(state) == 5
        and isinstance(state[2], np.dtype)
        and not state[2].hasobject
        and isinstance(state[4], bytes)
    ):
        raise CheckpointFormatError(f"a NumPy array gets the state {brief(state)}")
    shape = tensor_dims(state[1], "NumPy shape")
    if math.prod(shape) * state[2].itemsize != len(state[4]):
        raise CheckpointFormatError(f"a NumPy array of shape {shape} comes with {human(len(state[4]))}")
    arr.__setstate__(state)


# ------------------------------------------------------------------------------------------------ the two formats
def _storage_key(pid: tuple, where: str) -> tuple[StorageType, str, int | None]:
    _, storage_type, key, _location, numel = (list(pid) + [None] * 5)[:5]
    if not isinstance(storage_type, StorageType):
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
            view[pos : pos + len(chunk)] = chunk
            pos += len(chunk)
    if pos != len(buf):
        raise CheckpointFormatError(
            f"archive member {brief(info.filename, 80)} holds {pos} of its {info.file_size} bytes"
        )
    return buf


def _load_zip(path: Path, zf: zipfile.ZipFile, limits: Limits, placeholders: bool) -> tuple[Any, set[str]]:
    infos = zf.infolist()
    for info in infos:
        if _unsafe_member(info.filename):
            raise CheckpointFormatError(
                f"{path}: archive member {brief(info.filename, 100)} points outside the archive; refused"
            )
    budget = Budget(limits)
    budget.charge(sum(ZIP_ENTRY_BYTES + len(i.filename) + len(i.extra) + len(i.comment) for i in infos))
    declared = sum(info.file_size for info in infos)
    if declared > limits.archive_bytes:
        big = max(infos, key=lambda i: i.file_size)
        raise CheckpointLimitError(
            f"{path}: its archive members expand to {human(declared)} ({brief(big.filename, 80)[1:-1]}: "
            f"{human(big.file_size)} from {human(big.compress_size)}), over {limits.of_file(ARCHIVE_MULTIPLE)}; "
            f"refused before decompressing"
        )
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
            cache[key] = (
                torch.frombuffer(raw, dtype=storage_type.dtype, count=count)
                if count
                else torch.empty(0, dtype=storage_type.dtype)
            )
        return cache[key]

    data = bytes(_read_member(zf, names[pkl[0]]))
    unpickler = _Unpickler(_Source(io.BytesIO(data), len(data)), load_storage, budget, placeholders)
    obj = unpickler.load()
    return obj, unpickler.stubs


_LEGACY_MAGIC = 0x1950A86A20F9469CFC6C


def _what_else(path: Path) -> str:
    """Why a file that is neither a zip archive nor a legacy checkpoint was refused: what its first bytes say it is
    where they say it (a zip archive cut short, a safetensors file), else that it is not a PyTorch checkpoint."""
    with open(path, "rb") as f:
        head = f.read(9)
    size = path.stat().st_size
    if size == 0:
        return (
            "an empty file (0 bytes), not a PyTorch checkpoint: an interrupted download or copy? Fetch or copy it again"
        )
    if head.startswith(b"PK\x03\x04"):
        return (
            f"a zip archive (as torch.save writes) cut short: its end-of-archive record is missing ({human(size)} on "
            "disk), so the file is truncated (an interrupted download or copy?); fetch or copy it again"
        )
    if len(head) == 9 and head[8:] == b"{" and 2 <= int.from_bytes(head[:8], "little") <= size - 8:
        return (
            "a safetensors file (a plain state dict, as `harness weights import` writes), not a torch.save "
            "checkpoint: it needs no import; use it as it is, named *.safetensors (e.g. --init FILE.safetensors)"
        )
    return "not a PyTorch checkpoint (no zip archive, no legacy magic number)"


def _load_legacy(path: Path, f: BinaryIO, limits: Limits, placeholders: bool) -> tuple[Any, set[str]]:
    """The pre-1.6 format: magic, protocol, sys info, the object, the storage keys, then each storage's bytes.

    Storages are allocated when the object pickle names them, so their declared sizes together must fit in the
    file's bytes; every storage named must then be filled from the file, or the read is refused."""
    source, budget = _Source(f, limits.file_bytes), Budget(limits)

    def plain() -> Any:
        return _Unpickler(source, None, budget, placeholders=False).load()

    try:
        magic = plain()
    except (HarnessError, *_READ_ERRORS):
        magic = None
    if type(magic) is not int or magic != _LEGACY_MAGIC:
        raise CheckpointFormatError(f"{path}: {_what_else(path)}")
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
                raise CheckpointLimitError(
                    f"{path}: its storages declare {human(declared[0])}, more than the file's "
                    f"{human(limits.file_bytes)}; refused before allocating"
                )
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
        if len(raw) != 8 or target is None or key in filled or int.from_bytes(raw, "little") != target.numel():
            raise CheckpointFormatError(f"{path}: storage {brief(key)} does not match the checkpoint's references")
        flat = target.view(-1).view(torch.uint8) if target.numel() else target
        if target.numel() and source.readinto(flat.numpy()) != flat.numel():
            raise CheckpointFormatError(f"{path}: truncated storage {key}")
        filled.add(key)
    missing = sorted(set(loaded) - filled)
    if missing:
        raise CheckpointFormatError(
            f"{path}: storage {brief(missing[0])} is referenced but its bytes are not in the file ({len(missing)} "
            f"missing); refused (it would read as uninitialised memory)"
        )
    return obj, unpickler.stubs


_READ_ERRORS = (
    pickle.UnpicklingError,
    EOFError,
    ValueError,
    TypeError,
    AttributeError,
    KeyError,
    IndexError,
    RuntimeError,
    zipfile.BadZipFile,
    zlib.error,
    struct.error,
    OverflowError,
    NotImplementedError,
    UnicodeError,
    LookupError,
)


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
        raise CheckpointLimitError(
            f"{path}: ran out of memory while reading it ({human(limits.file_bytes)} on disk); refused"
        ) from None
    except RecursionError:
        raise CheckpointFormatError(f"{path}: nested too deeply to read") from None
    except _READ_ERRORS as exc:
        raise CheckpointFormatError(
            f"{path}: not a readable PyTorch checkpoint ({type(exc).__name__}: "
            f"{str(exc).splitlines()[0][:200] if str(exc) else ''})"
        ) from None


def load_plain(path: str | Path) -> Any:
    """A checkpoint of tensors and plain containers only (what ``torch.load(weights_only=True)`` accepts), read
    with the same bounds; a class outside the rebuild list raises :class:`ForeignObjectError`."""
    obj, _ = load_checkpoint(path, placeholders=False)
    return obj
