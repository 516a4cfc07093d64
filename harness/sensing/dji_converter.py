"""The converter route: DJI's own Thermal SDK (or any other converter the user names), run out of process per file.

For the formats the harness does not decode itself (``hirp``, ``girp``, the Zenmuse XT S, and iirp files whose
correction needs tables only DJI's SDK holds), the user may name a converter:

* ``dji_irp``: the command-line sample of DJI Thermal SDK (``utility/bin/<os>/release_x64/dji_irp``), found on
  ``PATH`` or at the path given with ``--dji-irp`` / ``sensing.radiometry.dji_irp`` (the program, or its folder).
  It is called as ``dji_irp -s IN -a measure -o OUT --measurefmt float32 --distance D --humidity H --emissivity E
  --reflection R``, with the measurement parameters the harness read from the file (or the user's overrides), and
  writes width x height little-endian float32 C with no header.
* a command template: any text holding ``{input}`` and ``{output}``, e.g. ``my-converter --in {input} --out
  {output} --emissivity {emissivity}``. The placeholders ``{width}``, ``{height}``, ``{emissivity}``,
  ``{distance}``, ``{humidity}``, ``{reflected}`` and ``{ambient}`` are filled from the file; the command must write
  the same float32 layout. The template is split like a shell line but run without a shell.

Nothing of DJI's is shipped with or downloaded by the harness. Each run gets its own temporary folder (removed
afterwards, whatever happens); a converter that cannot be started is a ``ConfigError`` (a setting, wrong for every
file); one that fails, outlasts its time-out (it is stopped, with any process it started) or writes the wrong
amount of data is a ``DataError`` naming the file. Values at or below -273 C (the SDK's "cannot measure") and
non-finite values come back as missing (NaN), and so do values outside the plausible range
(``radiometry.PLAUSIBLE_C``, -100..800 C; counted as ``implausible`` in the record and on the console); an output
that is no temperature map in C (``harness.sensing.plausible``: more than 5 % outside, big-endian floats, Kelvin,
8-bit counts) is a ``DataError`` naming the file.
"""

from __future__ import annotations

import os
import shlex
import shutil
import signal
import subprocess
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from harness.errors import ConfigError, DataError

DJI_IRP = "dji_irp"
DEFAULT_TIMEOUT_S = 120.0
#: the file's parameters as dji_irp's options name them
DJI_IRP_OPTIONS = (
    ("distance", "--distance"),
    ("humidity", "--humidity"),
    ("emissivity", "--emissivity"),
    ("reflected", "--reflection"),
)
PLACEHOLDERS = ("input", "output", "width", "height", "emissivity", "distance", "humidity", "reflected", "ambient")
#: at or below this a converter's value means "not measured"
NO_MEASUREMENT_C = -273.0


@dataclass(frozen=True)
class Converter:
    """An out-of-process converter: DJI's ``dji_irp`` (``kind == "dji_irp"``, ``program`` its path) or a user's
    command ``template``."""

    kind: str
    program: str = ""
    template: str = ""
    timeout_s: float = DEFAULT_TIMEOUT_S
    env: Mapping[str, str] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return DJI_IRP if self.kind == DJI_IRP else "command"

    def describe(self) -> str:
        return f"DJI Thermal SDK dji_irp ({self.program})" if self.kind == DJI_IRP else f"command {self.template!r}"


def _find_dji_irp(setting: str | None) -> Path:
    names = ("dji_irp", "dji_irp.exe")
    if setting:
        p = Path(setting).expanduser()
        candidates = [p / n for n in names] if p.is_dir() else [p]
        for c in candidates:
            if c.is_file():
                return c.resolve()
        raise ConfigError(
            f"DJI Thermal SDK's dji_irp not found at {setting} (sensing.radiometry.dji_irp / "
            "--dji-irp: the program or its folder)"
        )
    for n in names:
        found = shutil.which(n)
        if found:
            return Path(found).resolve()
    raise ConfigError(
        "the converter 'dji_irp' was asked for, but DJI Thermal SDK's dji_irp is not on PATH; install "
        "DJI Thermal SDK (a download from DJI; its utility/bin/<os>/release_x64/ folder holds dji_irp) "
        "and put that folder on PATH, or give its path with --dji-irp "
        "(sensing.radiometry.dji_irp)"
    )


def resolve(spec: str | None, dji_irp: str | None = None, timeout_s: float | None = None) -> Converter | None:
    """The converter a setting names: ``None``/empty for none, ``"dji_irp"`` for DJI's tool (``dji_irp`` a path to
    it), else a command template holding ``{input}`` and ``{output}``. A wrong setting is a ``ConfigError``."""
    if spec is None or not str(spec).strip():
        if dji_irp:
            spec = DJI_IRP
        else:
            return None
    spec = str(spec).strip()
    timeout = float(DEFAULT_TIMEOUT_S if timeout_s is None else timeout_s)
    if not timeout > 0:
        raise ConfigError(f"converter time-out must be positive, got {timeout_s}")
    if spec == DJI_IRP:
        program = _find_dji_irp(dji_irp)
        # DJI's Linux build loads its libraries (libdirp, libv_*) from beside the program
        old = os.environ.get("LD_LIBRARY_PATH", "")
        env = {"LD_LIBRARY_PATH": str(program.parent) + (os.pathsep + old if old else "")}
        return Converter(DJI_IRP, program=str(program), timeout_s=timeout, env=env)
    if "{input}" not in spec or "{output}" not in spec:
        raise ConfigError(
            f"converter {spec!r}: give 'dji_irp' or a command template holding {{input}} and "
            "{output} (e.g. 'my-converter {input} {output}')"
        )
    try:
        tokens = shlex.split(spec)
    except ValueError as exc:
        raise ConfigError(f"converter template {spec!r} cannot be split into arguments ({exc})") from None
    for token in tokens:
        for name in _names(token):
            if name not in PLACEHOLDERS:
                raise ConfigError(
                    f"converter template {spec!r}: unknown placeholder {{{name}}}; known: "
                    f"{', '.join('{' + p + '}' for p in PLACEHOLDERS)}"
                )
    return Converter("template", template=spec, timeout_s=timeout)


def _names(token: str) -> list[str]:
    import string

    try:
        return [f for _, f, _, _ in string.Formatter().parse(token) if f is not None]
    except ValueError as exc:
        raise ConfigError(f"converter template argument {token!r}: {exc}") from None


def arguments(
    conv: Converter, source: Path, output: Path, width: int, height: int, params: Mapping[str, float]
) -> list[str]:
    """The command line for one file (no shell). ``params``: the measurement parameters to pass (``emissivity``,
    ``distance``, ``humidity`` in %, ``reflected`` and ``ambient`` in C); for ``dji_irp`` those present are passed
    as options; a template placeholder whose value the file does not state is a ``DataError``."""
    if conv.kind == DJI_IRP:
        argv = [conv.program, "-s", str(source), "-a", "measure", "-o", str(output), "--measurefmt", "float32"]
        for key, option in DJI_IRP_OPTIONS:
            if key in params:
                argv += [option, f"{float(params[key]):g}"]
        return argv
    values: dict[str, Any] = {"input": str(source), "output": str(output), "width": width, "height": height}
    values.update({k: f"{float(v):g}" for k, v in params.items()})
    argv = []
    for token in shlex.split(conv.template):
        missing = [n for n in _names(token) if n not in values]
        if missing:
            raise DataError(
                f"{source}: the converter template uses {{{missing[0]}}}, which this file does not "
                "state; give it as an override or drop it from the template"
            )
        argv.append(token.format(**values))
    return argv


def _stop(proc: subprocess.Popen) -> None:
    """Stop ``proc`` and anything it started (its process group), then reap it."""
    try:
        if hasattr(os, "killpg"):
            os.killpg(proc.pid, signal.SIGKILL)
        else:  # pragma: no cover - Windows
            proc.kill()
    except (ProcessLookupError, PermissionError):
        pass
    try:
        proc.communicate(timeout=10)
    except subprocess.TimeoutExpired:  # pragma: no cover - pipes held by something outside the group
        pass


def _tail(text: bytes) -> str:
    lines = [ln.strip() for ln in text.decode("utf-8", "replace").splitlines() if ln.strip()]
    return lines[-1][:200] if lines else ""


def convert(
    conv: Converter, source: str | Path, width: int, height: int, params: Mapping[str, float]
) -> tuple[np.ndarray, dict[str, Any]]:
    """Run ``conv`` on ``source`` and read back its ``height`` x ``width`` float32 temperatures (C).

    Returns (temperatures, record): the record names the converter, the arguments (the temporary output shown as
    ``<output>``) and the parameters passed. Errors as the module docstring says."""
    source = Path(source).resolve()
    with tempfile.TemporaryDirectory(prefix="harness-convert-") as tmp:
        output = Path(tmp) / "temperature.raw"
        argv = arguments(conv, source, output, width, height, params)
        env = {**os.environ, **conv.env}
        cwd = str(Path(conv.program).parent) if conv.kind == DJI_IRP else tmp
        try:
            proc = subprocess.Popen(
                argv,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                cwd=cwd,
                env=env,
                start_new_session=True,
            )
        except OSError as exc:
            raise ConfigError(f"converter {conv.describe()} cannot be started: {exc.strerror or exc}") from None
        try:
            out, err = proc.communicate(timeout=conv.timeout_s)
        except subprocess.TimeoutExpired:
            _stop(proc)
            raise DataError(
                f"{source}: the converter ({conv.name}) did not finish within {conv.timeout_s:g} s and "
                "was stopped; raise the time-out (--converter-timeout, "
                "sensing.radiometry.converter_timeout_s) if the file is large"
            ) from None
        except BaseException:
            _stop(proc)
            raise
        if proc.returncode != 0:
            said = _tail(err) or _tail(out)
            raise DataError(
                f"{source}: the converter ({conv.name}) failed with exit status {proc.returncode}"
                f"{': ' + said if said else ''}"
            )
        if not output.is_file():
            raise DataError(f"{source}: the converter ({conv.name}) exited without writing its output file")
        data = output.read_bytes()
    expected = width * height * 4
    if len(data) != expected:
        raise DataError(
            f"{source}: the converter ({conv.name}) wrote {len(data)} bytes, expected {expected} "
            f"({width}x{height} float32 temperatures)"
        )
    temp = np.frombuffer(data, dtype="<f4").reshape(height, width).astype(np.float32)
    temp = np.where(np.isfinite(temp) & (temp > NO_MEASUREMENT_C), temp, np.float32(np.nan)).astype(np.float32)
    from harness.sensing import plausible

    # random bytes, big-endian floats or 8-bit counts: refused; a few values outside: missing, on the console. Kelvin
    # is refused after this against the file's own blackbody reading (``radiometry``), which says by how much. Not
    # Fahrenheit: as C it reads as a 50..115 C scene, which a sunlit roof of solar panels can be
    implausible = plausible.check(temp, str(source), f"the converter ({conv.name})", units=("counts8",))
    shown = ["<output>" if a == str(output) else a for a in argv]
    record = {
        "converter": conv.name,
        "program": conv.program or None,
        "arguments": shown[1:] if conv.kind == DJI_IRP else shown,
        "params": {k: float(v) for k, v in params.items()},
        "timeout_s": conv.timeout_s,
        **({"implausible": implausible} if implausible else {}),
    }
    return temp, record
