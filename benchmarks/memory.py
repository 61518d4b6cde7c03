"""The process's resident memory (RSS) and its peak, from Linux /proc (NaN / no-op elsewhere)."""
from __future__ import annotations


def rss_mb(field: str = "VmRSS") -> float:
    """A memory field of /proc/self/status in MB: ``VmRSS`` (resident now) or ``VmHWM`` (peak since start or
    since :func:`reset_peak_rss`); NaN where /proc has no such field."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def reset_peak_rss() -> None:
    """Reset the peak (VmHWM) to the current RSS, so that a later peak measures only what follows."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass
