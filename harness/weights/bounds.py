"""The bounds of a checkpoint read: every size a file can ask for, held to a multiple of the file's own size.

The numbers and what they bound are described in ``harness.weights.unpickle``; this module holds them, the error
types of a read, and two helpers that are safe on anything a hostile file can build (``brief``, ``human``).
"""

from __future__ import annotations

from dataclasses import dataclass

from harness.errors import HarnessError


class CheckpointFormatError(HarnessError):
    """The file is not a readable PyTorch checkpoint."""


class UnsafeCheckpointError(CheckpointFormatError):
    """The checkpoint asks for a call outside the tensor-rebuild list (possibly code execution)."""


class ForeignObjectError(UnsafeCheckpointError):
    """A plain read (``load_plain``) met a class outside the rebuild list: the file pickles objects, not tensors."""


class CheckpointLimitError(CheckpointFormatError):
    """The file asks for more memory or work than its own size allows."""


MiB = 1 << 20
#: each tensor as float32, and the imported output: at most this many times the file's bytes
SIZE_MULTIPLE = 4
#: an archive's members, decompressed, together: at most this many times the file's bytes (torch.save stores them
#: uncompressed; a re-zipped checkpoint of weights deflates by far less than half)
ARCHIVE_MULTIPLE = 2
#: bytes an archive entry's record takes in memory (``zipfile.ZipInfo``), charged to the rebuilt objects' budget
ZIP_ENTRY_BYTES = 512
#: the Python objects the pickle rebuilds: at most METADATA_FLOOR + METADATA_MULTIPLE x the file's bytes
METADATA_FLOOR = 48 * MiB
METADATA_MULTIPLE = 2
#: elements of one dict key or set item (a tuple key nested or shared beyond this is refused)
KEY_NODES = 64
#: the import converts and writes a tensor in pieces of at most this many bytes
PIECE_BYTES = 16 * MiB
#: What the whole import is held to (the tests measure it on every hostile file): peak memory above the
#: interpreter's at most PEAK_FLOOR + PEAK_MULTIPLE x the file's bytes F. It follows from the bounds above: the
#: archive's entry records and the rebuilt objects together (48 MiB + 2 F, or at most 5 F of records), the
#: decompressed members (2 F), one piece being converted (16 MiB): at most 64 MiB + 7 F.
PEAK_FLOOR = 64 * MiB
PEAK_MULTIPLE = 8
#: keys whose hash the file can choose (ints beyond +-2**61, floats, tuples): at most this many per file
RISKY_KEYS = 1000
#: dimensions of one tensor (PyTorch's own limit)
MAX_DIMS = 64


def human(n: int | float) -> str:
    """``1536 -> '1.5 KiB'``."""
    n = float(n)
    for unit in ("bytes", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{int(n)} bytes" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1024
    raise AssertionError  # pragma: no cover


@dataclass(frozen=True)
class Limits:
    """The bounds of one read, from the file's size (``harness.weights.unpickle`` describes them)."""

    file_bytes: int

    @property
    def tensor_bytes(self) -> int:
        """One tensor materialised as float32, the archive's members together, and the imported output."""
        return SIZE_MULTIPLE * max(self.file_bytes, 1)

    @property
    def archive_bytes(self) -> int:
        """An archive's members, decompressed, together."""
        return ARCHIVE_MULTIPLE * max(self.file_bytes, 1)

    @property
    def metadata_bytes(self) -> int:
        return METADATA_FLOOR + METADATA_MULTIPLE * self.file_bytes

    def of_file(self, multiple: int = SIZE_MULTIPLE) -> str:
        return f"{multiple} x the file's {human(self.file_bytes)}"


class Budget:
    """Memory the rebuilt Python objects may take; ``charge`` refuses the step that would exceed it."""

    def __init__(self, limits: Limits):
        self.limits, self.left = limits, limits.metadata_bytes

    def charge(self, nbytes: int) -> None:
        self.left -= nbytes
        if self.left < 0:
            raise CheckpointLimitError(
                f"rebuilding the checkpoint's objects needs more than {human(self.limits.metadata_bytes)} of memory "
                f"(the limit is {human(METADATA_FLOOR)} + {self.limits.of_file(METADATA_MULTIPLE)}); refused"
            )
