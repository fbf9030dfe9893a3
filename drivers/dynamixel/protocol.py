"""Dynamixel Protocol 2.0 packets: CRC-16, byte stuffing, encoding and a stream parser.

Packet: ``FF FF FD 00 | ID | LEN_L LEN_H | INST | params... | CRC_L CRC_H`` where LEN
counts INST + params + CRC (after stuffing), and the CRC-16 (polynomial 0x8005, initial
value 0, not reflected: CRC-16/UMTS) covers everything from the header to the last
parameter. Inside INST+params every ``FF FF FD`` is followed by an extra ``FD``
("byte stuffing") so the header never appears in a payload.

The driver side of the wire is dynamixel-sdk; this module is the device side used by the
bus emulator, and a checked reference for tests (its CRC agrees with the SDK's bytes).
"""

from __future__ import annotations

from dataclasses import dataclass

HEADER = b"\xff\xff\xfd\x00"
BROADCAST_ID = 0xFE
MAX_ID = 0xFC
#: the largest LEN a device accepts (dynamixel-sdk's RXPACKET_MAX_LEN)
MAX_LENGTH = 1024

# instructions
PING, READ, WRITE, REG_WRITE, ACTION, FACTORY_RESET, REBOOT, CLEAR = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06, 0x08, 0x10
STATUS, SYNC_READ, SYNC_WRITE, BULK_READ, BULK_WRITE = 0x55, 0x82, 0x83, 0x92, 0x93
INSTRUCTION_NAMES = {PING: "ping", READ: "read", WRITE: "write", REG_WRITE: "reg_write", ACTION: "action",
                     FACTORY_RESET: "factory_reset", REBOOT: "reboot", CLEAR: "clear", STATUS: "status",
                     SYNC_READ: "sync_read", SYNC_WRITE: "sync_write", BULK_READ: "bulk_read",
                     BULK_WRITE: "bulk_write"}

# status error codes (low 7 bits of the status packet's error byte)
ERR_RESULT_FAIL, ERR_INSTRUCTION, ERR_CRC, ERR_DATA_RANGE, ERR_DATA_LENGTH, ERR_DATA_LIMIT, ERR_ACCESS = range(1, 8)
ERR_ALERT = 0x80


def _crc_table() -> tuple[int, ...]:
    table = []
    for i in range(256):
        c = i << 8
        for _ in range(8):
            c = ((c << 1) ^ 0x8005) if c & 0x8000 else (c << 1)
        table.append(c & 0xFFFF)
    return tuple(table)


_CRC_TABLE = _crc_table()


def crc16(data: bytes | bytearray, crc: int = 0) -> int:
    """CRC-16 of Protocol 2.0 (poly 0x8005, init 0, MSB first, no final xor)."""
    for b in data:
        crc = ((crc << 8) ^ _CRC_TABLE[((crc >> 8) ^ b) & 0xFF]) & 0xFFFF
    return crc


def stuff(body: bytes) -> bytes:
    """Insert ``FD`` after every ``FF FF FD`` in INST+params."""
    out = bytearray()
    for b in body:
        out.append(b)
        if b == 0xFD and len(out) >= 3 and out[-3] == 0xFF and out[-2] == 0xFF:
            out.append(0xFD)
    return bytes(out)


def unstuff(body: bytes) -> bytes:
    """Remove the ``FD`` inserted after every ``FF FF FD``."""
    out = bytearray()
    i = 0
    while i < len(body):
        b = body[i]
        out.append(b)
        if b == 0xFD and len(out) >= 3 and out[-3] == 0xFF and out[-2] == 0xFF \
                and i + 1 < len(body) and body[i + 1] == 0xFD:
            i += 1  # skip the stuffed byte
        i += 1
    return bytes(out)


def encode(dxl_id: int, instruction: int, params: bytes = b"") -> bytes:
    """One complete packet (header, stuffing, CRC)."""
    if not 0 <= dxl_id <= 0xFE:
        raise ValueError(f"Dynamixel ID {dxl_id} out of range 0..254")
    body = stuff(bytes([instruction]) + bytes(params))
    n = len(body) + 2
    pkt = HEADER + bytes([dxl_id, n & 0xFF, n >> 8]) + body
    c = crc16(pkt)
    return pkt + bytes([c & 0xFF, c >> 8])


def encode_status(dxl_id: int, error: int = 0, params: bytes = b"") -> bytes:
    """A status packet: INST 0x55, then the error byte, then the data."""
    return encode(dxl_id, STATUS, bytes([error & 0xFF]) + bytes(params))


@dataclass(frozen=True)
class Packet:
    dxl_id: int
    instruction: int
    params: bytes

    @property
    def name(self) -> str:
        return INSTRUCTION_NAMES.get(self.instruction, f"0x{self.instruction:02x}")


class Parser:
    """Incremental parser: feed bytes as they arrive, get whole packets out.

    Garbage before a header is skipped (counted in ``garbage_bytes``); a packet whose CRC
    does not match is dropped (``crc_errors``) and the search restarts one byte after its
    header, so a corrupt length field cannot swallow the good packets behind it.
    """

    def __init__(self, max_length: int = MAX_LENGTH):
        self.buf = bytearray()
        self.max_length = max_length
        self.packets = 0
        self.crc_errors = 0
        self.garbage_bytes = 0
        self.bad_length = 0

    def feed(self, data: bytes) -> list[Packet]:
        self.buf += data
        out: list[Packet] = []
        while True:
            i = self.buf.find(HEADER[:3])
            if i < 0:
                # keep a possible partial header at the end
                keep = 2 if self.buf.endswith(b"\xff\xff") else (1 if self.buf.endswith(b"\xff") else 0)
                self.garbage_bytes += len(self.buf) - keep
                del self.buf[: len(self.buf) - keep]
                return out
            if i:
                self.garbage_bytes += i
                del self.buf[:i]
            if len(self.buf) < 7:
                return out
            if self.buf[3] != 0x00:  # FF FF FD FD is a stuffed payload, not a header
                self.garbage_bytes += 1
                del self.buf[:1]
                continue
            n = self.buf[5] | (self.buf[6] << 8)
            if n < 3 or n > self.max_length:
                self.bad_length += 1
                self.garbage_bytes += 1
                del self.buf[:1]
                continue
            total = 7 + n
            if len(self.buf) < total:
                return out
            raw = bytes(self.buf[:total])
            if crc16(raw[:-2]) != (raw[-2] | (raw[-1] << 8)):
                self.crc_errors += 1
                del self.buf[:1]
                continue
            del self.buf[:total]
            body = unstuff(raw[7:-2])
            self.packets += 1
            out.append(Packet(raw[4], body[0], body[1:]))
