"""The cores this process may use for its threads: its affinity (a container's or `taskset`'s
share of the machine), or fewer where whoever started it says so in LIGHTPLAN_CORES (the test
suite gives each of its worker processes cores // workers, so that the workers' kernel threads do
not outnumber the cores). No Warp here: the CLI checks the setting before any work."""
import os

CORES_VARIABLE = "LIGHTPLAN_CORES"


def available_cores() -> int:
    """min(affinity, LIGHTPLAN_CORES) when set, else the affinity; a ValueError of one line
    naming the variable when it is not a whole number of at least 1."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:                      # no affinity on this OS
        cores = os.cpu_count() or 1
    raw = os.environ.get(CORES_VARIABLE)
    if raw is None:
        return cores
    try:
        granted = int(raw)
    except ValueError:
        granted = 0
    if granted < 1:
        raise ValueError(f"environment: {CORES_VARIABLE}: found {raw!r}, expected a whole number of cores, "
                         "at least 1 (or unset: every core this process may run on)")
    return min(cores, granted)
