"""Progress bars for people only: ``tqdm`` that stays silent when nobody watches.

A bar is drawn only when its stream (stderr) is a terminal and ``CI`` is not set to a true value, so CI
logs, ``dvc repro`` logs and redirected output carry no carriage-return noise. ``disable=True`` still turns
a bar off; ``RLSAC_PROGRESS=1`` forces bars on (e.g. under ``script``), ``RLSAC_PROGRESS=0`` off.
"""

from __future__ import annotations

import os
import sys

from tqdm import tqdm as _tqdm

_FALSE = ("", "0", "false", "no", "off")


def enabled(stream=None) -> bool:
    """Whether a bar on ``stream`` (default stderr) should be drawn."""
    forced = os.environ.get("RLSAC_PROGRESS")
    if forced is not None and forced.strip() != "":
        return forced.strip().lower() not in _FALSE
    if os.environ.get("CI", "").strip().lower() not in _FALSE:
        return False
    stream = sys.stderr if stream is None else stream
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def tqdm(*args, **kwargs):
    """``tqdm.tqdm`` with ``disable`` forced on when :func:`enabled` says nobody watches."""
    if not enabled(kwargs.get("file")):
        kwargs["disable"] = True
    elif kwargs.get("disable") is None:
        kwargs["disable"] = False  # tqdm's None means "not a tty": decided above already (RLSAC_PROGRESS=1)
    return _tqdm(*args, **kwargs)
