"""Frames built from docs/protocol.md alone (COBS, CRC-16/CCITT-FALSE, the header), not with the host's
encoder: the bytes a check that does not trust this project's code would write, and a reader of the replies."""

import struct

VERSION = 7  # docs/protocol.md, "Version"


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final XOR."""
    c = 0xFFFF
    for b in data:
        c ^= b << 8
        for _ in range(8):
            c = ((c << 1) ^ 0x1021) if c & 0x8000 else c << 1
            c &= 0xFFFF
    return c


def cobs(data: bytes) -> bytes:
    out, block = bytearray(), bytearray()
    for b in data:
        if b == 0:
            out += bytes([len(block) + 1]) + block
            block.clear()
        else:
            block.append(b)
            if len(block) == 254:
                out += bytes([255]) + block
                block.clear()
    return bytes(out + bytes([len(block) + 1]) + block)


def uncobs(data: bytes) -> bytes:
    out, i = bytearray(), 0
    while i < len(data):
        code = data[i]
        out += data[i + 1:i + code]
        i += code
        if code != 255 and i < len(data):
            out.append(0)
    return bytes(out)


def frame(msg_id: int, seq: int, body: bytes = b"") -> bytes:
    payload = struct.pack("<BBH", VERSION, msg_id, seq) + body
    return b"\x00" + cobs(payload + struct.pack("<H", crc16(payload))) + b"\x00"


def parse(data: bytes) -> list[tuple[int, int, bytes]]:
    """(msg_id, seq, body) of every frame with a good CRC."""
    out = []
    for chunk in data.split(b"\x00"):
        if not chunk:
            continue
        p = uncobs(chunk)
        if len(p) >= 6 and crc16(p[:-2]) == struct.unpack("<H", p[-2:])[0]:
            out.append((p[1], struct.unpack("<H", p[2:4])[0], p[4:-2]))
    return out
