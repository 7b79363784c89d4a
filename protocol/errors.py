"""Errors raised by the sans-I/O protocol layer."""

from __future__ import annotations

__all__ = ["ProtocolError"]


class ProtocolError(ValueError):
    """A received message is malformed, truncated, inconsistent or over a limit.

    Every decoder in :mod:`protocol` raises this (and only this) for bad input;
    the message names the offending field with the expected and the actual
    value, e.g. ``"header.version: expected 1, got 7"``.
    """
