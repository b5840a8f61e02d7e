"""MAVLink FTP (FILE_TRANSFER_PROTOCOL) refused at once.

Neither gcs nor the simulated flight controller serves files. Every request is answered with a
NAK right away, so ground stations (MAVProxy, QGC) fall back to the plain parameter and mission
protocols instead of waiting for a timeout (MAVProxy waits ~11 s otherwise).
"""
from __future__ import annotations

from pymavlink.dialects.v20 import common as M

OPCODE_NAK = 129
ERR_UNKNOWN_COMMAND = 7
ERR_FILE_NOT_FOUND = 10
PAYLOAD_LEN = 251


def nak_payload(request: bytes | bytearray | list[int], error: int) -> list[int]:
    """The payload of the NAK answering one request payload: the next sequence number, the same
    session, the request's opcode, and one data byte, `error`."""
    req = bytes(request)
    seq = int.from_bytes(req[0:2], "little") if len(req) >= 2 else 0
    payload = bytearray(PAYLOAD_LEN)
    payload[0:2] = ((seq + 1) & 0xFFFF).to_bytes(2, "little")
    payload[2] = req[2] if len(req) > 2 else 0     # session
    payload[3] = OPCODE_NAK
    payload[4] = 1                                 # data size
    payload[5] = req[3] if len(req) > 3 else 0     # the request's opcode
    payload[12] = error
    return list(payload)


def nak(request, error: int) -> M.MAVLink_file_transfer_protocol_message:
    """The NAK answering a received FILE_TRANSFER_PROTOCOL message, addressed to its sender."""
    return M.MAVLink_file_transfer_protocol_message(0, request.get_srcSystem(), request.get_srcComponent(),
                                                    nak_payload(request.payload, error))
