"""The one-line reason a live command got no sample, from what the reader saw.

``fbgforce stream`` and ``record`` end with this error (exit 2) instead of an empty success
when the interrogator never delivered a frame: the message says what was tried (port,
protocol, how long, how often the port opened) and what to check.
"""
from __future__ import annotations

from typing import Any

from fbgforce.errors import InputError

#: How long a run with a stop condition (--duration, --samples, --idle-timeout) waits for its
#: first sample when --start-timeout is not given: such a run is meant to end on its own.
DEFAULT_START_TIMEOUT_S = 5.0
#: URL schemes of sources reached over the network (no serial device, no dialout group).
NETWORK_SCHEMES = ("socket", "rfc2217", "hyperion", "tcp")


def start_timeout_for(start_timeout: float | None, duration: float | None,
                      samples: int | None, idle_timeout: float | None) -> float | None:
    """The start timeout a run uses: the given one; else, for a run with a stop condition,
    :data:`DEFAULT_START_TIMEOUT_S` (or the duration / idle timeout if longer); else none
    (an open-ended stream waits for its device until stopped)."""
    if start_timeout is not None:
        return start_timeout
    if duration is None and samples is None and idle_timeout is None:
        return None
    return max(DEFAULT_START_TIMEOUT_S, duration or 0.0, idle_timeout or 0.0)


def no_data_error(port: str, protocol: str, waited_s: float, stats: dict[str, Any],
                  last_error: str | None, *, baud: int | None = None,
                  interrupted: bool = False) -> InputError:
    """The :class:`InputError` for "no valid sample from ``port``".

    ``stats`` is the reader's :meth:`stats` (link counters ``opens``, ``open_failures``,
    ``bytes_read``; decoder counters such as ``crc_errors``, ``header_errors``,
    ``bad_replies``, ``polls``).
    """
    when = "before the run was interrupted" if interrupted else f"within {waited_s:.3g} s"
    line = f"{protocol} protocol" + (f", {baud} baud" if baud else "")
    opens, failures = int(stats.get("opens", 0)), int(stats.get("open_failures", 0))
    nbytes = int(stats.get("bytes_read", 0))
    if opens == 0:
        error = (last_error or "unknown error").replace("\n", " ").strip()
        reason = (f"could not open it ({failures} attempt{'s' if failures != 1 else ''}; "
                  f"last error: {error})")
        if port.split("://", 1)[0] in NETWORK_SCHEMES:
            check = ("check the host and port, that the instrument is on and reachable from "
                     "here (ping, firewall) and that it accepts connections on that port")
        else:
            check = ("check the device path or URL, that the interrogator is plugged in and "
                     "on, and that you may open it (e.g. the dialout group)")
    elif nbytes == 0:
        polls = int(stats.get("polls", 0))
        reason = "the port opened but no byte arrived" + (f" ({polls} polls unanswered)" if polls else "")
        check = ("check that the interrogator is acquiring, that --protocol matches it (native "
                 "devices push frames, fispec devices answer polls) and --baud for a real UART")
    else:
        bad = {k: int(stats[k]) for k in ("header_errors", "crc_errors", "bad_replies",
                                           "discarded_bytes", "timeouts") if stats.get(k)}
        detail = ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in bad.items())
        reason = (f"{nbytes} bytes arrived but none formed a valid {protocol} frame"
                  + (f" ({detail})" if detail else ""))
        check = ("check --protocol (native, fispec or hyperion), --channels and, for a real "
                 "UART, --baud")
    return InputError(f"no sample from {port} {when} ({line}): {reason}; {check}",
                      column="--port")
