"""Run logging: TensorBoard events plus a plain ``scalars.jsonl`` in the run folder.

Every scalar goes to both: TensorBoard for browsing (``tensorboard --logdir outputs``) and one
JSON line per call (``{"step": ..., "time": ..., "<tag>": value, ...}``) for scripts and
tests. A resumed run appends to the same files; TensorBoard drops the events written after the
checkpoint it resumes from (``purge_step``), readers of the JSONL keep the last line per step
(and a line a killed process left unfinished is cut off first).
Only rank 0 logs (:class:`RunLogger` is created disabled elsewhere).
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Mapping
from pathlib import Path

from matplotlib.figure import Figure

SCALARS_FILE = "scalars.jsonl"
TENSORBOARD_DIR = "tensorboard"


class RunLogger:
    """Scalars, text and figures of one run.

    Args:
        run_dir: the run folder.
        tensorboard: write TensorBoard events under ``<run_dir>/tensorboard``.
        enabled: ``False`` makes every method a no-op (non-zero ranks).
        purge_step: resuming at this global step: TensorBoard discards later events.
    """

    def __init__(
        self,
        run_dir: str | Path,
        *,
        tensorboard: bool = True,
        enabled: bool = True,
        purge_step: int | None = None,
    ) -> None:
        self.enabled = enabled
        self.run_dir = Path(run_dir)
        self._writer = None
        self._jsonl = None
        if not enabled:
            return
        self.run_dir.mkdir(parents=True, exist_ok=True)
        _drop_torn_line(self.run_dir / SCALARS_FILE)
        self._jsonl = open(self.run_dir / SCALARS_FILE, "a", encoding="utf-8")
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            self._writer = SummaryWriter(str(self.run_dir / TENSORBOARD_DIR), purge_step=purge_step)

    def scalars(self, values: Mapping[str, float], step: int, prefix: str = "") -> None:
        """Log named scalars at ``step``; tags are ``prefix + name``. Non-finite values are kept."""
        if not self.enabled or not values:
            return
        tagged = {f"{prefix}{name}": float(value) for name, value in values.items()}
        if self._writer is not None:
            for tag, value in tagged.items():
                self._writer.add_scalar(tag, value, step)
        record = {"step": step, "time": round(time.time(), 3)}
        record.update({tag: (value if math.isfinite(value) else str(value)) for tag, value in tagged.items()})
        self._jsonl.write(json.dumps(record) + "\n")
        self._jsonl.flush()

    def text(self, tag: str, text: str, step: int) -> None:
        """Log a text note (e.g. a curriculum stage change) to TensorBoard."""
        if self.enabled and self._writer is not None:
            self._writer.add_text(tag, text, step)

    def figure(self, tag: str, figure: Figure, step: int) -> None:
        """Log a matplotlib figure (rendered to an image) to TensorBoard."""
        if self.enabled and self._writer is not None:
            self._writer.add_figure(tag, figure, step, close=False)

    def flush(self) -> None:
        """Push pending events to disk."""
        if self._writer is not None:
            self._writer.flush()

    def close(self) -> None:
        """Flush and close the files."""
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        if self._jsonl is not None:
            self._jsonl.close()
            self._jsonl = None


def _drop_torn_line(path: Path) -> None:
    """Cut an unfinished last line (a process killed while writing it) off a JSONL file."""
    if not path.is_file():
        return
    with open(path, "rb+") as handle:
        if handle.seek(0, os.SEEK_END) == 0:
            return
        handle.seek(-1, os.SEEK_END)
        if handle.read(1) == b"\n":
            return
        handle.seek(0)
        handle.truncate(handle.read().rfind(b"\n") + 1)


def read_scalars(run_dir: str | Path) -> list[dict]:
    """The records of ``<run_dir>/scalars.jsonl`` in writing order."""
    path = Path(run_dir) / SCALARS_FILE
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]
