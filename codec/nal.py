"""H.264 NAL-unit helpers for Annex-B access units (start-code prefixed NAL units)."""
from __future__ import annotations

import re

__all__ = ["NAL_IDR_SLICE", "nal_unit_types", "contains_idr"]

NAL_IDR_SLICE = 5
"""nal_unit_type of a coded slice of an IDR picture."""

_START_CODE_NAL_HEADER = re.compile(rb"\x00\x00\x01(.)", re.DOTALL)


def nal_unit_types(access_unit: bytes) -> list[int]:
    """NAL unit types (0..31) of the start-code-prefixed NAL units in ``access_unit``."""
    return [header[0] & 0x1F for header in _START_CODE_NAL_HEADER.findall(access_unit)]


def contains_idr(access_unit: bytes) -> bool:
    """Whether an Annex-B access unit holds an IDR slice NAL unit."""
    return NAL_IDR_SLICE in nal_unit_types(access_unit)
