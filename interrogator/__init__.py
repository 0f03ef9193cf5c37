"""Interrogator I/O over serial: wire protocols, a robust reader, a virtual interrogator."""
