"""A corpus of hostile checkpoint files, written by code (no binary is committed).

``build_corpus(folder, marker)`` writes every file and returns :class:`Case` records: the file, what importing it
must give (``expect``: ``None`` for a successful import, else a regex the one-line error must match) and why it is
hostile. Every payload that could run code would create ``marker``; nothing may ever create it.

Pickles are assembled opcode by opcode (:class:`Pk`) where Python's own pickler cannot write them (a 100,000-deep
list, a storage of 10**12 elements, a call of ``bytearray(8e9)``), or written by ``torch.save`` from objects whose
``__reduce__`` names the payload. Genuine-looking checkpoints come from the Ultralytics and ICAFusion stand-ins of
``weights_standins``, with the payload added to the checkpoint or inside the model.

Kept in one module: the corpus is one list of cases, each next to the opcodes that build it.
"""

from __future__ import annotations

import io
import os
import pickle
import random
import struct
import subprocess
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import torch

import weights_standins as ws
from weights_standins import save_yolov5_style


@dataclass
class Case:
    name: str
    path: Path
    expect: str | None  # None: imports; else a regex the error message matches
    why: str
    plain: bool = True  # also read it as ``--init`` and resuming would (skipped for the slow floods)
    kind: str = ""


# ------------------------------------------------------------------------------------------------ pickle assembly
class Pk:
    """A pickle written opcode by opcode (protocol 2 unless ``proto`` says otherwise)."""

    def __init__(self, proto: int = 2):
        self.b = bytearray(b"\x80" + bytes([proto]))

    def raw(self, data: bytes) -> "Pk":
        self.b += data
        return self

    def glob(self, module: str, name: str) -> "Pk":
        return self.raw(b"c" + module.encode() + b"\n" + name.encode() + b"\n")

    def s(self, text: str) -> "Pk":
        data = text.encode("utf-8")
        return self.raw(b"X" + struct.pack("<I", len(data)) + data)

    def i(self, n: int) -> "Pk":
        if 0 <= n < 256:
            return self.raw(b"K" + bytes([n]))
        if -(2**31) <= n < 2**31:
            return self.raw(b"J" + struct.pack("<i", n))
        data = n.to_bytes((n.bit_length() >> 3) + 1, "little", signed=True)
        if len(data) < 256:
            return self.raw(b"\x8a" + bytes([len(data)]) + data)
        return self.raw(b"\x8b" + struct.pack("<i", len(data)) + data)

    def put(self, idx: int) -> "Pk":
        return self.raw(b"r" + struct.pack("<I", idx))

    def get(self, idx: int) -> "Pk":
        return self.raw(b"j" + struct.pack("<I", idx))

    def tup(self, *items: Callable[["Pk"], Any]) -> "Pk":
        self.raw(b"(")
        for item in items:
            item(self)
        return self.raw(b"t")

    def ints(self, values: tuple[int, ...]) -> "Pk":
        self.raw(b"(")
        for v in values:
            self.i(v)
        return self.raw(b"t")

    def storage(self, key: str, numel: int, kind: str = "FloatStorage") -> "Pk":
        self.raw(b"(").s("storage").glob("torch", kind).s(key).s("cpu").i(numel).raw(b"t")
        return self.raw(b"Q")  # BINPERSID

    def tensor(
        self,
        key: str,
        numel: int,
        size: tuple[int, ...],
        stride: tuple[int, ...],
        offset: int = 0,
        kind: str = "FloatStorage",
    ) -> "Pk":
        self.glob("torch._utils", "_rebuild_tensor_v2").raw(b"(")
        self.storage(key, numel, kind).i(offset).ints(size).ints(stride).raw(b"\x89")
        self.glob("collections", "OrderedDict").raw(b")R")
        return self.raw(b"tR")

    def doubled(self, levels: int, base: int = 1_000_000, kind: str = "list") -> "Pk":
        """A list (or tuple) that holds the previous level twice, ``levels`` times: 2**levels leaves, a few bytes
        a level."""
        self.i(0).put(base)
        for k in range(1, levels + 1):
            self.raw(b"0")  # POP: only the last level stays on the stack
            if kind == "list":
                self.raw(b"]").put(base + k).raw(b"(").get(base + k - 1).get(base + k - 1).raw(b"e")
            else:
                self.get(base + k - 1).get(base + k - 1).raw(b"\x86").put(base + k)
        return self

    def dict_of(self, *pairs: tuple[str, Callable[["Pk"], Any]]) -> "Pk":
        self.raw(b"}(")
        for key, value in pairs:
            self.s(key)
            value(self)
        return self.raw(b"u")

    def stop(self) -> bytes:
        return bytes(self.b + b".")


def torch_zip(
    path: Path,
    pkl: bytes,
    storages: dict[str, bytes] | None = None,
    names: str = "archive",
    compress: dict[str, int] | None = None,
    claim: dict[str, int] | None = None,
) -> Path:
    """A ``torch.save``-style archive; ``compress`` deflates the named storages, ``claim`` makes the central
    directory declare another uncompressed size for them (what a forged header says)."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
        z.writestr(f"{names}/data.pkl", pkl)
        z.writestr(f"{names}/byteorder", "little")
        for key, data in (storages or {}).items():
            method = zipfile.ZIP_DEFLATED if key in (compress or {}) else zipfile.ZIP_STORED
            z.writestr(
                zipfile.ZipInfo(f"{names}/data/{key}"),
                data,
                compress_type=method,
                compresslevel=(compress or {}).get(key),
            )
            if key in (claim or {}):
                z.filelist[-1].file_size = claim[key]  # the central directory is written from this at close
        z.writestr(f"{names}/version", "3\n")
    return path


def legacy_file(path: Path, obj_pkl: bytes, storages: list[tuple[str, int, bytes]], keys: Any = None) -> Path:
    """The pre-1.6 format: magic, protocol, sys info, the object, the key list, then ``numel`` + bytes per key."""
    out = io.BytesIO()
    out.write(pickle.dumps(0x1950A86A20F9469CFC6C, protocol=2))
    out.write(pickle.dumps(1001, protocol=2))
    out.write(
        pickle.dumps(
            {"protocol_version": 1001, "little_endian": True, "type_sizes": {"short": 2, "int": 4, "long": 4}},
            protocol=2,
        )
    )
    out.write(obj_pkl)
    out.write(
        keys
        if isinstance(keys, bytes)
        else pickle.dumps([k for k, _, _ in storages] if keys is None else keys, protocol=2)
    )
    for _, numel, data in storages:
        out.write(struct.pack("<q", numel))
        out.write(data)
    path.write_bytes(out.getvalue())
    return path


def _w(pk: Pk) -> Pk:
    """A small plain state dict ``{'w': tensor of 4 floats}`` under ``model``: the import finds a model."""
    return pk.dict_of(("w", lambda p: p.tensor("0", 4, (4,), (1,))))


W_BYTES = struct.pack("<4f", 1, 2, 3, 4)


def _with_model(extra: Callable[[Pk], Any], key: str = "train_args") -> bytes:
    """``{'model': {'w': ...}, key: <extra>}``."""
    return Pk().dict_of(("model", _w), (key, extra)).stop()


# ------------------------------------------------------------------------------------------------ payload objects
class _Shell:
    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


class _Popen:
    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (subprocess.Popen, (["touch", str(self.marker)],))


class _Eval:
    def __init__(self, code: str):
        self.code = code

    def __reduce__(self):
        return (eval, (self.code,))


class _Exec(_Eval):
    def __reduce__(self):
        return (exec, (self.code,))


def _ours(seed: int = 0) -> torch.nn.Module:
    from adapters.detectors import ours

    torch.manual_seed(seed)
    return ours.build(3, in_channels=3, scale="n").eval()


def _icafusion(seed: int = 0) -> torch.nn.Module:
    from adapters.detectors import icafusion

    torch.manual_seed(seed)
    return icafusion.build(3, width=0.125, depth=0.33, tokens=(4, 2, 2)).eval()


class _Tiny(torch.nn.Module):
    """A module tree shaped like Ultralytics' ``DetectionModel`` (``model`` is a ``Sequential`` of layers), small
    enough that reading it takes milliseconds."""

    def __init__(self) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.model = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 3), torch.nn.BatchNorm2d(4))
        self.nc, self.scale = 3, "n"


NAMES = {0: "window", 1: "crack", 2: "vent"}


def _ultralytics(
    path: Path,
    model: torch.nn.Module,
    top: dict[str, Any] | None = None,
    attrs: dict[str, Any] | None = None,
    inner: Any = None,
) -> Path:
    """A stand-in Ultralytics trainer checkpoint (as ``weights_standins.save_ultralytics`` writes it) with ``top``
    added to the checkpoint dict, ``attrs`` set on the model and ``inner`` set as an attribute of the model's first
    layer (a payload inside the module tree)."""
    m = ws.half_copy(model)
    m.yaml = {"nc": int(model.nc), "scale": str(model.scale)}
    m.names = dict(NAMES)
    m.args = {"imgsz": 640, "epochs": 3}
    for k, v in (attrs or {}).items():
        setattr(m, k, v)
    if inner is not None:
        m.model[0].__dict__["payload"] = inner
    ckpt = {
        "epoch": 2,
        "best_fitness": 0.25,
        "date": "2024-05-01T12:00:00",
        "version": "8.2.0",
        "train_args": {"imgsz": 640, "data": "facade.yaml"},
        "optimizer": None,
        "updates": 123,
        "model": None,
        "ema": m,
        **(top or {}),
    }
    with ws.standin_classes(m, ws.ULTRALYTICS_MODULES, ("ultralytics.nn.tasks", "DetectionModel")):
        torch.save(ckpt, path)
    return path


# ------------------------------------------------------------------------------------------------ the corpus
def build_corpus(folder: Path, marker: Path) -> list[Case]:
    folder.mkdir(parents=True, exist_ok=True)
    cases: list[Case] = []

    kind = ["code execution"]

    def add(name: str, expect: str | None, why: str, plain: bool = True) -> Path:
        path = folder / f"{name}.pt"
        cases.append(Case(name, path, expect, why, plain, kind[0]))
        return path

    # --- code that would run ------------------------------------------------------------------------------
    torch.save(
        {"model": {"w": torch.ones(4)}, "x": _Shell(marker)},
        add("reduce_os_system", r"posix\.system.*refused", "__reduce__ -> os.system"),
    )
    torch.save(
        {"model": {"w": torch.ones(4)}, "x": _Eval(f"open({str(marker)!r}, 'w')")},
        add("reduce_eval", r"builtins\.eval.*refused", "__reduce__ -> eval"),
    )
    torch.save(
        {"model": {"w": torch.ones(4)}, "x": _Exec(f"open({str(marker)!r}, 'w')")},
        add("reduce_exec", r"builtins\.exec.*refused", "__reduce__ -> exec"),
    )
    torch.save(
        {"model": {"w": torch.ones(4)}, "x": _Popen(marker)},
        add("reduce_popen", r"subprocess\.Popen.*refused", "__reduce__ -> subprocess.Popen"),
    )
    getattr_chain = (
        Pk()
        .glob("builtins", "getattr")
        .raw(b"(")
        .glob("builtins", "__import__")
        .raw(b"(")
        .s("os")
        .raw(b"tR")
        .s("system")
        .raw(b"tR")
        .raw(b"(")
        .s(f"touch {marker}")
        .raw(b"tR")
    )
    torch_zip(
        add(
            "getattr_import_chain",
            r"builtins\.(getattr|__import__).*refused",
            "getattr(__import__('os'), 'system')(...)",
        ),
        getattr_chain.stop(),
    )
    torch_zip(
        add("protocol0_inst", r"(os|posix)\.system.*refused", "protocol-0 INST os.system"),
        b"(S'touch " + str(marker).encode() + b"'\nios\nsystem\n.",
    )
    torch_zip(
        add("torch_tensor_call", r"torch\.Tensor.*refused", "torch.Tensor(100000, 100000): 40 GB"),
        _with_model(lambda p: p.glob("torch", "Tensor").ints((100000, 100000)).raw(b"R")),
        {"0": W_BYTES},
    )
    torch_zip(
        add("torch_tensor_newobj", r"torch\.Tensor.*refused", "NEWOBJ torch.Tensor(100000, 100000)"),
        _with_model(lambda p: p.glob("torch", "Tensor").ints((100000, 100000)).raw(b"\x81")),
        {"0": W_BYTES},
    )
    torch_zip(
        add(
            "numpy_object_array", r"NumPy dtype.*refused", "a NumPy object array (its items would be arbitrary objects)"
        ),
        _with_model(
            lambda p: (
                p.glob("numpy", "dtype")
                .tup(lambda q: q.s("O"), lambda q: q.raw(b"\x89"), lambda q: q.raw(b"\x88"))
                .raw(b"R")
            )
        ),
        {"0": W_BYTES},
    )
    torch_zip(
        add("build_on_tensor", r"sets the state of <tensor.*refused", "BUILD (setstate) on a tensor"),
        _with_model(lambda p: p.tensor("0", 4, (4,), (1,)).dict_of(("data", lambda q: q.s("x"))).raw(b"b")),
        {"0": W_BYTES},
    )
    torch_zip(
        add("extension_code", r"extension code", "EXT1 opcode (copyreg registry)"),
        _with_model(lambda p: p.raw(b"\x82\x01")),
        {"0": W_BYTES},
    )
    torch_zip(
        add("defaultdict_factory", r"defaultdict.*refused", "defaultdict(os.system)"),
        _with_model(lambda p: p.glob("collections", "defaultdict").raw(b"(").glob("os", "system").raw(b"tR")),
        {"0": W_BYTES},
    )
    # --- persistent_load tricks -----------------------------------------------------------------------------
    kind[0] = "persistent_load"
    torch_zip(
        add("persid_text", r"unknown persistent id", "protocol-0 PERSID string"),
        Pk().dict_of(("model", lambda p: p.raw(b"Pstorage\n"))).stop(),
    )
    torch_zip(
        add("persid_stub_type", r"storage of unknown type", "a storage whose type is posix.system"),
        Pk()
        .dict_of(("model", lambda p: p.raw(b"(").s("storage").glob("posix", "system").s("0").s("cpu").i(4).raw(b"tQ")))
        .stop(),
        {"0": W_BYTES},
    )
    torch_zip(
        add("persid_key_traversal", r"storage \.\./\.\./etc/passwd is missing", "storage key ../../etc/passwd"),
        Pk()
        .dict_of(("model", lambda p: p.dict_of(("w", lambda q: q.tensor("../../etc/passwd", 4, (4,), (1,))))))
        .stop(),
        {"0": W_BYTES},
    )
    torch_zip(
        add("persid_key_doubled", r"storage key <list", "storage key a list doubled 40 times (str() hangs)"),
        Pk()
        .dict_of(
            (
                "model",
                lambda p: p.raw(b"(").s("storage").glob("torch", "FloatStorage").doubled(40).s("cpu").i(4).raw(b"tQ"),
            )
        )
        .stop(),
        {"0": W_BYTES},
    )
    torch_zip(
        add("persid_reduce_payload", r"posix\.system.*refused", "a persistent id built by os.system"),
        Pk()
        .dict_of(("model", lambda p: p.glob("posix", "system").tup(lambda q: q.s(f"touch {marker}")).raw(b"RQ")))
        .stop(),
    )
    # --- genuine-looking checkpoints with a payload ----------------------------------------------------------------
    kind[0] = "genuine checkpoints"
    model, tiny = _ours(), _Tiny()
    _ultralytics(
        add("ultralytics_payload_top", r"posix\.system.*refused", "Ultralytics checkpoint + os.system"),
        model,
        top={"callbacks": _Shell(marker)},
    )
    _ultralytics(
        add(
            "ultralytics_payload_in_model",
            r"subprocess\.Popen.*refused",
            "Ultralytics checkpoint, Popen inside its first layer",
        ),
        model,
        inner=_Popen(marker),
    )
    _ultralytics(
        add(
            "ultralytics_payload_attr",
            r"builtins\.eval.*refused",
            "Ultralytics-style checkpoint, eval as a model attribute",
        ),
        tiny,
        attrs={"args": {"imgsz": 640, "hook": _Eval(f"open({str(marker)!r}, 'w')")}},
    )
    ica = _icafusion()
    save_yolov5_style(
        ica,
        add("icafusion_payload_opt", r"posix\.system.*refused", "ICAFusion checkpoint + os.system in opt"),
        extra={"opt": _Shell(marker)},
    )
    _ultralytics(add("ultralytics_clean", None, "control: a genuine Ultralytics checkpoint"), model)
    save_yolov5_style(ica, add("icafusion_clean", None, "control: a genuine ICAFusion checkpoint"))
    torch.save(
        {"model": {"w": torch.ones(4), "big": torch.zeros(1 << 21)}},
        add("plain_state_dict", None, "control: an 8 MB plain state dict"),
    )
    # --- archive tricks -------------------------------------------------------------------------------------------
    kind[0] = "archive"
    torch_zip(
        add("zip_traversal_names", r"points outside the archive", "member names ../data.pkl, ../data/0"),
        _with_model(lambda p: p.raw(b"N")),
        {"0": W_BYTES},
        names="..",
    )
    with zipfile.ZipFile(add("zip_absolute_name", r"points outside the archive", "a member named /tmp/..."), "w") as z:
        z.writestr("archive/data.pkl", _with_model(lambda p: p.raw(b"N")))
        z.writestr("archive/data/0", W_BYTES)
        z.writestr(str(folder / "evil" / "x"), b"x")
    torch_zip(
        add(
            "zip_deflate_bomb",
            r"expand to .*refused before decompressing",
            "a storage of 32 MiB of zeros deflated to 32 KiB",
        ),
        Pk().dict_of(("model", lambda p: p.dict_of(("w", lambda q: q.tensor("0", 8 << 20, (8 << 20,), (1,)))))).stop(),
        {"0": bytes(32 << 20)},
        compress={"0": 9},
    )
    torch_zip(
        add(
            "zip_claims_6gb",
            r"expand to 5\.6 GiB.*refused before decompressing",
            "a member whose central directory declares 6 GB",
        ),
        _with_model(lambda p: p.raw(b"N")),
        {"0": W_BYTES, "1": bytes(1 << 20)},
        compress={"1": 9},
        claim={"1": 6_000_000_000},
    )
    with zipfile.ZipFile(add("zip_20000_entries", None, "20,000 empty archive members besides a model"), "w") as z:
        z.writestr("archive/data.pkl", Pk().dict_of(("model", _w)).stop())
        z.writestr("archive/data/0", W_BYTES)
        for i in range(20_000):
            z.writestr(f"archive/junk/{i}", b"")
    cut_said = r"the file is truncated|not a PyTorch checkpoint|not a readable|holds \d+ of"
    cut = add("zip_cut", cut_said, "an archive cut in the middle")
    data = torch_zip(cut, _with_model(lambda p: p.raw(b"N")), {"0": W_BYTES}).read_bytes()
    cut.write_bytes(data[: len(data) * 2 // 3])
    # --- sizes --------------------------------------------------------------------------------------------------
    kind[0] = "tensor sizes"
    torch_zip(
        add("storage_1e12_zip", r"storage of 1000000000000 elements has only", "a 10**12-element storage"),
        Pk().dict_of(("model", lambda p: p.dict_of(("w", lambda q: q.tensor("0", 10**12, (10**12,), (1,)))))).stop(),
        {"0": W_BYTES},
    )
    torch_zip(
        add("tensor_1e12_view", r"expands to .*refused|reaches element", "a 10**12-element view of 4 floats"),
        Pk().dict_of(("model", lambda p: p.dict_of(("w", lambda q: q.tensor("0", 4, (10**6, 10**6), (1, 1)))))).stop(),
        {"0": W_BYTES},
    )
    torch_zip(
        add("expand_40gb", r"expands to 37\.3 GiB.*refused", "expand(1e5, 1e5) of one float: 40 GB"),
        Pk().dict_of(("model", lambda p: p.dict_of(("w", lambda q: q.tensor("0", 4, (10**5, 10**5), (0, 0)))))).stop(),
        {"0": W_BYTES},
    )
    torch_zip(
        add("expand_64mib", r"expands to 64\.0 MiB.*refused", "expand(4096, 4096) of one float in a 1 KB file"),
        Pk().dict_of(("model", lambda p: p.dict_of(("w", lambda q: q.tensor("0", 4, (4096, 4096), (0, 0)))))).stop(),
        {"0": W_BYTES},
    )

    def many_views(p: Pk) -> None:
        p.raw(b"}(")
        for i in range(1000):
            p.s(f"w{i}").tensor("0", 4, (100, 100), (0, 0))
        p.raw(b"u")

    torch_zip(
        add("expand_many_views", r"add up to .*refused", "1,000 zero-stride views of one float, 40 KB each"),
        Pk().dict_of(("model", many_views)).stop(),
        {"0": W_BYTES},
    )
    torch_zip(
        add("tensor_65_dims", r"at most 64 ints", "a tensor of 65 dimensions"),
        Pk().dict_of(("model", lambda p: p.dict_of(("w", lambda q: q.tensor("0", 4, (1,) * 65, (1,) * 65))))).stop(),
        {"0": W_BYTES},
    )
    torch_zip(
        add("negative_stride", r"negative", "a negative stride"),
        Pk().dict_of(("model", lambda p: p.dict_of(("w", lambda q: q.tensor("0", 4, (4,), (-1,)))))).stop(),
        {"0": W_BYTES},
    )
    # --- allowed calls asked for huge results, and opcode floods ------------------------------------------------
    kind[0] = "allowed calls and floods"
    for name, ctor, arg in (("bytearray_8e9", "bytearray", 8 * 10**9), ("bytes_8e9", "bytes", 8 * 10**9)):
        torch_zip(
            add(name, r"needs more than .*refused", f"{ctor}(8e9)"),
            _with_model(lambda p, c=ctor, a=arg: p.glob("builtins", c).raw(b"(").i(a).raw(b"tR")),
            {"0": W_BYTES},
        )
    for name, ctor in (("list_range_5e8", "list"), ("set_range_5e8", "set"), ("size_range_5e8", "Size")):
        module = "torch" if ctor == "Size" else "builtins"
        torch_zip(
            add(name, r"needs more than .*refused", f"{ctor}(range(5e8))"),
            _with_model(
                lambda p, m=module, c=ctor: (
                    p.glob(m, c).raw(b"(").glob("builtins", "range").raw(b"(").i(5 * 10**8).raw(b"tR").raw(b"tR")
                )
            ),
            {"0": W_BYTES},
        )
    torch_zip(
        add("str_of_doubled", r"calls str\(\) with <list.*refused", "str() of a list doubled 40 times"),
        _with_model(lambda p: p.glob("builtins", "str").raw(b"(").doubled(40).raw(b"tR")),
        {"0": W_BYTES},
    )
    torch_zip(
        add("binbytes8_8gb", r"a bytes object of 7\.5 GiB", "BINBYTES8 declaring 8 GB"),
        _with_model(lambda p: p.raw(b"\x8e" + struct.pack("<Q", 8 * 10**9) + b"abc")),
        {"0": W_BYTES},
    )
    torch_zip(
        add("bytearray8_8gb", r"a bytearray of 7\.5 GiB", "BYTEARRAY8 (protocol 5) declaring 8 GB"),
        _with_model(lambda p: p.raw(b"\x96" + struct.pack("<Q", 8 * 10**9) + b"abc")),
        {"0": W_BYTES},
    )
    torch_zip(
        add("frame_2_62", r"frame", "a FRAME declaring 2**62 bytes"), b"\x80\x04\x95" + struct.pack("<Q", 2**62) + b"N."
    )
    torch_zip(
        add("empty_set_flood", r"needs more than .*refused", "320 KB of EMPTY_SET: 70 MB of sets", plain=False),
        b"\x80\x04](" + b"\x8f" * 320_000 + b"e.",
    )

    def class_flood(p: Pk) -> None:
        p.raw(b"]")
        for i in range(40_000):
            p.glob("evil", f"C{i}").raw(b"a")

    torch_zip(
        add("stub_class_flood", r"needs more than .*refused", "40,000 distinct class names: a class each", plain=False),
        _with_model(class_flood),
        {"0": W_BYTES},
    )
    torch_zip(
        add("memo_flood", r"needs more than .*refused|no model found", "600 KB of MEMOIZE: 60 MB of memo", plain=False),
        b"\x80\x04N" + b"\x94" * 600_000 + b".",
    )
    # --- shared and nested structures ------------------------------------------------------------------------------
    kind[0] = "shared and nested"
    torch_zip(
        add("doubled_40_small_file", None, "train_args: a list doubled 40 times, in a 2 KB file"),
        _with_model(lambda p: p.doubled(40)),
        {"0": W_BYTES},
    )
    doubled: Any = [0]
    for _ in range(40):
        doubled = [doubled, doubled]
    _ultralytics(
        add("ultralytics_doubled_train_args", None, "Ultralytics checkpoint, train_args doubled 40 times"),
        model,
        top={"train_args": {"imgsz": 640, "x": doubled}},
    )
    _ultralytics(
        add("ultralytics_doubled_names", None, "Ultralytics-style checkpoint, names doubled 40 times"),
        tiny,
        attrs={"names": doubled},
    )
    _ultralytics(
        add("ultralytics_doubled_yaml", None, "Ultralytics-style checkpoint, yaml anchors doubled 40 times"),
        tiny,
        attrs={"yaml": {"nc": 3, "scale": "n", "anchors": doubled}},
    )
    selfref: list = [1]
    selfref.append(selfref)
    selfdict: dict = {"a": 1}
    selfdict["me"] = selfdict
    _ultralytics(
        add(
            "ultralytics_self_reference", None, "Ultralytics-style checkpoint, a list and a dict containing themselves"
        ),
        tiny,
        top={"train_args": {"l": selfref, "d": selfdict}},
    )
    torch_zip(
        add("deep_list_20k", None, "train_args: a list nested 20,000 deep"),
        _with_model(lambda p: p.raw(b"]" * 20_000 + b"a" * 19_999)),
        {"0": W_BYTES},
    )
    torch_zip(
        add("deep_module_tree_3000", None, "a module tree 3,000 deep (Ultralytics classes)"),
        _deep_modules(3000),
        {"0": W_BYTES},
    )
    torch_zip(add("module_cycle", None, "a module that is its own child"), _cyclic_module(), {"0": W_BYTES})
    torch_zip(
        add("module_dag_doubled", None, "a module tree doubled 40 times (each level holds its child twice)"),
        _doubled_modules(40),
        {"0": W_BYTES},
    )
    torch_zip(
        add("class_name_1mb", None, "a placeholder class with a 1 MB name in the metadata"),
        _with_model(lambda p: p.glob("evil", "C" * (1 << 20)).raw(b")\x81")),
        {"0": W_BYTES},
    )
    torch_zip(
        add(
            "deep_tuple_key",
            r"dict key or set item holds more than",
            "a dict key nested 200,000 deep (hashing it crashes CPython)",
            plain=False,
        ),
        _with_model(lambda p: p.raw(b"}").raw(b")" + b"\x85" * 200_000).i(1).raw(b"s")),
        {"0": W_BYTES},
    )
    torch_zip(
        add(
            "doubled_tuple_key",
            r"dict key or set item holds more than",
            "a dict key: a tuple doubled 40 times (hashing it takes 2**40 steps)",
        ),
        _with_model(lambda p: p.raw(b"}").doubled(40, kind="tuple").i(1).raw(b"s")),
        {"0": W_BYTES},
    )

    def collisions(p: Pk) -> None:
        p.raw(b"}(")
        for k in range(1, 50_001):
            p.i(k * ((1 << 61) - 1)).raw(b"N")
        p.raw(b"u")

    torch_zip(
        add(
            "hash_collision_keys",
            r"more than 1000 dict keys.*refused",
            "50,000 int keys that all hash to 0 (quadratic dict inserts)",
        ),
        _with_model(collisions),
        {"0": W_BYTES},
    )
    _ultralytics(
        add("ultralytics_huge_int", None, "Ultralytics-style checkpoint, epoch = 2**100000"),
        tiny,
        top={"epoch": 2**100_000},
    )
    _ultralytics(
        add("ultralytics_names_mixed", None, "Ultralytics-style checkpoint, names {0: ..., 'x': ...}"),
        tiny,
        attrs={"names": {0: "window", "x": "crack"}},
    )
    _ultralytics(
        add("ultralytics_names_giant_index", None, "Ultralytics-style checkpoint, a 5,000-digit name index"),
        tiny,
        attrs={"names": {"9" * 5000: "window"}},
    )
    torch.save({1: 2, "a": 3}, add("no_model_mixed_keys", r"no model found", "no model, keys of mixed types"))
    torch_zip(
        add("param_name_not_a_string", r"names a tensor 5, not a string", "a parameter named 5"),
        _module_with_param_name(),
        {"0": W_BYTES},
    )
    # --- the legacy format --------------------------------------------------------------------------------------
    kind[0] = "legacy format"
    two = (
        Pk()
        .dict_of(
            (
                "model",
                lambda p: p.dict_of(
                    ("a", lambda q: q.tensor("0", 4, (4,), (1,))), ("b", lambda q: q.tensor("1", 4, (4,), (1,)))
                ),
            )
        )
        .stop()
    )
    legacy_file(
        add("legacy_clean", None, "control: a legacy-format checkpoint"), two, [("0", 4, W_BYTES), ("1", 4, W_BYTES)]
    )
    legacy_file(
        add(
            "legacy_missing_storage",
            r"storage '1' is referenced but its bytes are not in the file",
            "a legacy file that leaves storage 1 out (uninitialised memory)",
        ),
        two,
        [("0", 4, W_BYTES)],
    )
    legacy_file(
        add(
            "legacy_storage_4gb",
            r"declare 3\.7 GiB.*refused before allocating",
            "a legacy storage of 10**9 floats in a 1 KB file",
        ),
        Pk().dict_of(("model", lambda p: p.dict_of(("w", lambda q: q.tensor("0", 10**9, (4,), (1,)))))).stop(),
        [("0", 4, W_BYTES)],
    )
    legacy_file(
        add("legacy_keys_doubled", r"key list is <list", "a legacy key list doubled 40 times"),
        Pk().dict_of(("model", _w)).stop(),
        [("0", 4, W_BYTES)],
        keys=Pk().doubled(40).stop(),
    )
    # --- not checkpoints at all --------------------------------------------------------------------------------
    kind[0] = "not checkpoints"
    add("empty_file", r"not a (readable )?PyTorch checkpoint", "an empty file").write_bytes(b"")
    add("random_bytes", r"not a (readable )?PyTorch checkpoint", "random bytes").write_bytes(
        random.Random(0).randbytes(4096)
    )
    return cases


def _module_level(p: Pk, child: Callable[[Pk], Any] | None, params: Callable[[Pk], Any] | None, cls: str) -> None:
    p.glob(*cls.rsplit(".", 1)).raw(b")\x81")  # NEWOBJ: a placeholder instance
    p.raw(b"}(").s("_parameters")
    p.raw(b"}") if params is None else params(p)
    p.s("_buffers").raw(b"}").s("_modules")
    p.raw(b"}") if child is None else (p.raw(b"}").s("0"), child(p), p.raw(b"s"))
    p.raw(b"ub")


def _deep_modules(depth: int) -> bytes:
    """``{'model': None, 'ema': DetectionModel -> Sequential -> ... (depth levels) -> Conv with a weight}``, written
    without recursion (the stream of a level wraps the next one's)."""
    head, tail = Pk(), []
    head.raw(b"}(").s("model").raw(b"N").s("epoch").i(1).s("ema")
    for level in range(depth):
        cls = "ultralytics.nn.tasks.DetectionModel" if level == 0 else "torch.nn.modules.container.Sequential"
        head.glob(*cls.rsplit(".", 1)).raw(b")\x81").raw(b"}(").s("_parameters").raw(b"}").s("_buffers").raw(b"}")
        head.s("_modules").raw(b"}").s("0")
        tail.append(b"sub")
    _module_level(
        head,
        None,
        lambda p: p.dict_of(("weight", lambda q: q.tensor("0", 4, (4,), (1,)))),
        "ultralytics.nn.modules.conv.Conv",
    )
    return bytes(head.b + b"".join(reversed(tail)) + b"u.")


def _cyclic_module() -> bytes:
    p = Pk().raw(b"}(").s("ema")
    p.glob("ultralytics.nn.tasks", "DetectionModel").raw(b")\x81").put(500)
    p.raw(b"}(").s("_parameters").dict_of(("weight", lambda q: q.tensor("0", 4, (4,), (1,))))
    p.s("_buffers").raw(b"}").s("_modules").raw(b"}").s("self").get(500).raw(b"s").raw(b"ub")
    return p.raw(b"u").stop()


def _doubled_modules(levels: int) -> bytes:
    """``ema``: a module whose ``_modules`` hold the level below twice, ``levels`` times; a weight at the bottom."""
    p = Pk().raw(b"}(").s("ema")
    _module_level(
        p,
        None,
        lambda q: q.dict_of(("weight", lambda r: r.tensor("0", 4, (4,), (1,)))),
        "ultralytics.nn.modules.conv.Conv",
    )
    p.put(2_000_000)
    for k in range(1, levels + 1):
        p.raw(b"0")
        cls = "ultralytics.nn.tasks.DetectionModel" if k == levels else "torch.nn.modules.container.Sequential"
        p.glob(*cls.rsplit(".", 1)).raw(b")\x81").raw(b"}(").s("_parameters").raw(b"}").s("_buffers").raw(b"}")
        p.s("_modules").raw(b"}(").s("a").get(2_000_000 + k - 1).s("b").get(2_000_000 + k - 1).raw(b"uub")
        p.put(2_000_000 + k)
    return p.raw(b"u").stop()


def _module_with_param_name() -> bytes:
    p = Pk().raw(b"}(").s("ema")
    _module_level(
        p, None, lambda q: q.raw(b"}").i(5).tensor("0", 4, (4,), (1,)).raw(b"s"), "ultralytics.nn.tasks.DetectionModel"
    )
    return p.raw(b"u").stop()
