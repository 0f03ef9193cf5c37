"""Interrogator I/O over serial: wire protocols, a robust reader, a virtual interrogator.

Modules: :mod:`~fbgforce.interrogator.protocol` (native frame, FiSpec commands, load-cell
lines; docs/protocol.md), :mod:`~fbgforce.interrogator.reader` (pyserial reader that survives
bad bytes and disconnects), :mod:`~fbgforce.interrogator.emulator` (virtual interrogator on a
pseudo-terminal), :mod:`~fbgforce.interrogator.stream` (live estimation through the C
runtime), :mod:`~fbgforce.interrogator.record` (calibration logs in the dataset contract),
:mod:`~fbgforce.interrogator.cli` (``emulate``, ``stream``, ``record``; docs/serial.md).
"""
