"""Interrogator I/O: wire protocols, robust readers, virtual interrogators, estimate outputs.

Modules: :mod:`~fbgforce.interrogator.protocol` (native frame, FiSpec commands, load-cell
lines, the plausibility gate; docs/protocol.md), :mod:`~fbgforce.interrogator.hyperion`
(Luna / Micron Optics Hyperion over TCP), :mod:`~fbgforce.interrogator.reader` (pyserial
readers that survive bad bytes and disconnects), :mod:`~fbgforce.interrogator.emulator`
(virtual interrogators on a pseudo-terminal or TCP), :mod:`~fbgforce.interrogator.stream`
(live estimation through the C runtime), :mod:`~fbgforce.interrogator.publish` (UDP datagrams
and LCM messages to a controller), :mod:`~fbgforce.interrogator.record` (calibration logs in
the dataset contract), :mod:`~fbgforce.interrogator.cli` (``emulate``, ``stream``,
``record``; docs/serial.md).
"""
