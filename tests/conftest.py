"""Shared pytest fixtures. Keep data small: CI machines have 2 cores and the suite must stay fast."""
from __future__ import annotations
