"""Estimation problems behind one protocol, in one registry (rlsac.tasks.registry). A new task is one new module
here that decorates its class with ``@register_task`` (and is imported at the bottom of this file); evaluate,
train, the CLI and the tables find it through ``TASKS``.
"""

from __future__ import annotations

# the registry and its look-ups (rlsac.tasks.registry), re-exported: callers import them from rlsac.tasks
from rlsac.tasks.registry import (  # noqa: F401
    TASKS,
    Task,
    as_numpy,
    get_task,
    load,
    opencv_threshold,
    prefiltered,
    read_batch,
    register_task,
    task_class,
    task_for,
    task_from,
    task_names,
)

# isort: split
from rlsac.tasks import line, fundamental, essential  # noqa: E402,F401,I001  (each registers itself; this order in --help)
