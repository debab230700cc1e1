"""The cores this process may use, for the runtime's thread pools."""

from __future__ import annotations

import os


def available_cores() -> int:
    """Cores available to the process: its CPU affinity where the system has one (a
    container or ``taskset`` may give fewer than the machine has), else the count."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1
