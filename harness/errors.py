"""The harness's error types.

Every error a user can cause (bad input file, unknown plugin, malformed config) is a ``HarnessError`` whose
message names the file, field or plugin and says what to do. The CLI prints these without a traceback; any other
exception reaching the CLI is a bug.
"""

from __future__ import annotations


class HarnessError(Exception):
    """Base class for errors caused by input, configuration or plugins (not by bugs in the harness)."""


class PluginError(HarnessError):
    """A plugin is broken, conflicts with another, or registered something invalid."""


class UnknownNameError(HarnessError, KeyError):
    """A detector, dataset or encoding name that no loaded plugin registered."""

    def __init__(self, kind: str, name: str, available: list[str]):
        self.kind, self.name, self.available = kind, name, sorted(available)
        avail = ", ".join(self.available) or "none"
        super().__init__(
            f"unknown {kind} {name!r}; available: {avail}. "
            f"Run `harness list` to see what the loaded plugins provide, `harness plugins` for the plugins."
        )

    def __str__(self) -> str:  # KeyError would quote the message
        return self.args[0]


class ConfigError(HarnessError):
    """A configuration file or override is malformed or names an unknown key."""


class SampleError(HarnessError):
    """An aligned sample breaks the sample contract (shape, dtype, finiteness, boxes in frame)."""


class DataError(HarnessError):
    """A dataset file is missing, unreadable or inconsistent."""


class StoreError(HarnessError):
    """The results store holds something unexpected (a conflicting finished run, a corrupt file)."""


class PartlyDone(Exception):
    """A batch command finished what it could and listed what failed (the message says how many): exit status 1.

    Not a ``HarnessError``: the work that succeeded is done and kept. Raised by commands, after their output.
    """


class ExitCode:
    """The exit statuses of ``harness`` (README, "Exit status"; the same for plugin commands)."""

    DONE = 0  #: everything asked for was done
    PARTLY_DONE = 1  #: a batch finished what it could; what failed is listed (``PartlyDone``)
    USAGE = 2  #: a usage or input error (bad option, ``HarnessError``, unreadable file), said in one line
    BUG = 70  #: an unexpected exception: a bug in the harness or a plugin (EX_SOFTWARE of sysexits.h)
    INTERRUPTED = 130  #: Ctrl-C (128 + SIGINT); finished runs are kept and interrupted ones resume
