"""H.264 NAL-unit helpers for Annex-B access units (start-code prefixed NAL units)."""
from __future__ import annotations

import re

__all__ = ["NAL_IDR_SLICE", "NAL_SEI", "nal_unit_types", "contains_idr", "user_data_nal", "take_user_data"]

NAL_IDR_SLICE = 5
"""nal_unit_type of a coded slice of an IDR picture."""

NAL_SEI = 6
"""nal_unit_type of supplemental enhancement information."""

_USER_DATA_UNREGISTERED = 5     # the SEI payload type that carries a UUID and any bytes
_EMULATION = re.compile(rb"\x00\x00(?=[\x00-\x03])")
_EMULATION_PREVENTED = re.compile(rb"\x00\x00\x03")
_START_CODE = re.compile(rb"\x00\x00\x01")

_START_CODE_NAL_HEADER = re.compile(rb"\x00\x00\x01(.)", re.DOTALL)


def nal_unit_types(access_unit: bytes) -> list[int]:
    """NAL unit types (0..31) of the start-code-prefixed NAL units in ``access_unit``."""
    return [header[0] & 0x1F for header in _START_CODE_NAL_HEADER.findall(access_unit)]


def contains_idr(access_unit: bytes) -> bool:
    """Whether an Annex-B access unit holds an IDR slice NAL unit."""
    return NAL_IDR_SLICE in nal_unit_types(access_unit)


def user_data_nal(uuid: bytes, data: bytes) -> bytes:
    """An SEI NAL unit (with a 4-byte start code) holding one user_data_unregistered message: ``uuid`` (16 bytes)
    then ``data``, with emulation prevention so no start code appears inside."""
    if len(uuid) != 16:
        raise ValueError(f"user data needs a 16-byte UUID, got {len(uuid)} bytes")
    size = 16 + len(data)
    rbsp = bytes([_USER_DATA_UNREGISTERED]) + b"\xff" * (size // 255) + bytes([size % 255]) + uuid + data + b"\x80"
    return b"\x00\x00\x00\x01" + bytes([NAL_SEI]) + _EMULATION.sub(b"\x00\x00\x03", rbsp)


def take_user_data(access_unit: bytes, uuid: bytes) -> tuple[bytes | None, bytes]:
    """The ``data`` of the first SEI NAL unit of ``access_unit`` that is exactly one user_data_unregistered message
    with ``uuid`` (:func:`user_data_nal`), and the access unit without that NAL unit; (None, access_unit) when
    there is none."""
    starts = [m.start() for m in _START_CODE.finditer(access_unit)]
    for i, start in enumerate(starts):
        head = start + 3
        if head >= len(access_unit) or access_unit[head] & 0x1F != NAL_SEI:
            continue
        end = starts[i + 1] if i + 1 < len(starts) else len(access_unit)
        if i + 1 < len(starts) and end > 0 and access_unit[end - 1] == 0:
            end -= 1                                    # the next start code has four bytes
        rbsp = _EMULATION_PREVENTED.sub(b"\x00\x00", access_unit[head + 1:end])
        if not rbsp or rbsp[0] != _USER_DATA_UNREGISTERED:
            continue
        pos, size = 1, 0
        while pos < len(rbsp) and rbsp[pos] == 0xFF:
            size, pos = size + 255, pos + 1
        if pos >= len(rbsp):
            continue
        size, pos = size + rbsp[pos], pos + 1
        if size < 16 or rbsp[pos:pos + 16] != uuid or rbsp[pos + size:] != b"\x80":
            continue
        nal_start = start - 1 if start > 0 and access_unit[start - 1] == 0 else start
        return rbsp[pos + 16:pos + size], access_unit[:nal_start] + access_unit[end:]
    return None, access_unit
