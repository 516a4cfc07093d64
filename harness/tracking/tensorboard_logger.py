"""The ``tensorboard`` tracker: one TensorBoard event-file folder per run (``pip install 'rgbt-harness[tensorboard]'``).

Folders: ``tracking.tensorboard_dir`` (default ``<store>/tensorboard``) / ``<dataset>/<detector>/<encoding>/<fold>/
seed<N>`` for runs and ``report`` for reports, so ``tensorboard --logdir <store>/tensorboard`` shows every run of a
store side by side. Per epoch: one scalar per metric (``loss/box``, ``val/mAP50`` ...) at the epoch number; the final
held-out metrics at the last epoch; the configuration and text artefacts (the report) as text summaries. Written
with ``torch.utils.tensorboard``, which needs the ``tensorboard`` package but not TensorFlow.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Mapping

from harness.hookspecs import hookimpl
from harness.tracking import TrackingOptions, builtin_spec

#: text artefacts up to this size are copied into the event file; larger or binary ones are named only
MAX_TEXT_BYTES = 200_000
TEXT_SUFFIXES = {".md", ".txt", ".csv", ".json", ".yaml"}
#: the description of this tracker in its ``LoggerSpec``
DESCRIPTION = "TensorBoard event files under <store>/tensorboard (tracking.tensorboard_dir)"


class TensorBoardLogger:
    def __init__(self, options: TrackingOptions):
        self.root = Path(options.tensorboard_dir) if options.tensorboard_dir else options.store / "tensorboard"
        self.group = options.group
        self.writer: Any = None
        self.step = 0

    def start(self, name: str, params: Mapping[str, Any], tags: Mapping[str, str]) -> None:
        from torch.utils.tensorboard import SummaryWriter

        folder = "report" if self.group == "report" else re.sub(r"[^\w.+/-]+", "_", name)
        self.writer = SummaryWriter(log_dir=str(self.root / folder))
        rows = "\n".join(f"| {k} | {v} |" for k, v in {**tags, **params}.items())
        self.writer.add_text("config", f"| key | value |\n|---|---|\n{rows}", 0)

    def log_epoch(self, step: int, metrics: Mapping[str, float]) -> None:
        self.step = int(step)
        for k, v in metrics.items():
            self.writer.add_scalar(k, float(v), self.step)

    def log_final(self, metrics: Mapping[str, float]) -> None:
        for k, v in metrics.items():
            self.writer.add_scalar(k, float(v), self.step)

    def log_artifact(self, path: Path) -> None:
        path = Path(path)
        if path.suffix in TEXT_SUFFIXES and path.stat().st_size <= MAX_TEXT_BYTES:
            body = path.read_text(encoding="utf-8", errors="replace")
            text = body if path.suffix == ".md" else "    " + body.replace("\n", "\n    ")
        else:
            text = f"`{path}` ({path.stat().st_size} bytes)"
        self.writer.add_text(f"artifact/{path.name}", text, self.step)

    def finish(self, status: str) -> None:
        if self.writer is not None:
            self.writer.add_text("status", status, self.step)
            self.writer.close()
            self.writer = None


@hookimpl
def register_loggers(register):
    register(builtin_spec("tensorboard", TensorBoardLogger, DESCRIPTION))
