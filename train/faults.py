"""A test-only kill switch: SIGKILL the training process at a chosen point, as a pre-empted job.

``LINEREG_KILL_AT=<point>:<n>`` in the environment kills the process with SIGKILL (nothing is
flushed, no handler runs) when it reaches ``<point>`` for the ``n``-th time:

* ``step:<n>``: after global step ``n`` is logged (and its step checkpoint, if any, written);
* ``checkpoint:<n>``: inside this process's ``n``-th checkpoint write, once the temporary file
  is complete and before it replaces the checkpoint.

The kill-and-resume tests (``tests/test_train_kill_resume.py``) use it; unset, it does nothing.
"""

from __future__ import annotations

import os
import signal
from collections import Counter

ENVIRONMENT_VARIABLE = "LINEREG_KILL_AT"
_passes: Counter[str] = Counter()


def kill_point(point: str, count: int | None = None) -> None:
    """Kill this process if ``LINEREG_KILL_AT`` names ``point`` at ``count`` (``None``: the number of
    times this process has reached ``point``)."""
    wanted = os.environ.get(ENVIRONMENT_VARIABLE)
    if not wanted:
        return
    name, _, target = wanted.partition(":")
    if name != point:
        return
    _passes[point] += 1
    if (_passes[point] if count is None else count) == int(target):
        os.kill(os.getpid(), signal.SIGKILL)
