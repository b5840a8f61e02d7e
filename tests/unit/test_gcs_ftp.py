"""MAVLink FTP is refused at once (ground stations then fall back to the parameter and mission
protocols): a NAK to the sender for the request's opcode."""
from __future__ import annotations

from gcs_support import from_gcs
from pymavlink.dialects.v20 import common as M

from aeroperception.services.mavlink import ftp


def test_ftp_is_nakked():
    req = from_gcs(M.MAVLink_file_transfer_protocol_message(0, 1, 1, [7, 0, 0, 4] + [0] * 247))
    nak = ftp.nak(req, ftp.ERR_FILE_NOT_FOUND)
    assert nak.payload[3] == 129 and nak.payload[5] == 4 and nak.payload[0] == 8 and nak.target_system == 255
