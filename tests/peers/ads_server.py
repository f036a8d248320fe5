"""ADS peer for compgate's tests: pyads' own test server (pyads.testserver), holding
LREAL or REAL variables at given index group / offset, on 127.0.0.1 and a free port.

Usage: ads_server.py [--lreal G:O=V ...] [--real G:O=V ...] [--read-only G:O ...]
                     [--delay-s S]

G and O are integers (0x.. allowed). Prints "PORT <n>" once listening, then serves
until its standard input closes. A write (or sum-up write) touching a read-only
variable is refused as a whole with ADS error 0x704 (reading/writing not permitted);
an unknown index answers 0x703 (invalid index offset) instead of dropping the
connection. --delay-s delays every answer (a slow control).
"""

import argparse
import struct
import sys
import time

from pyads import constants
from pyads.testserver import AdsTestServer, AdvancedHandler, PLCVariable
from pyads.testserver.handler import AmsResponseData

ERR_INVALID_OFFSET = 0x703
ERR_NOT_PERMITTED = 0x704


def addr(text):
    g, o = text.split(":")
    return int(g, 0), int(o, 0)


class Handler(AdvancedHandler):
    def __init__(self, read_only, delay_s):
        super().__init__()
        self.read_only = read_only
        self.delay_s = delay_s

    def refuse(self, request, code):
        state = struct.unpack("<H", request.ams_header.state_flags)[0] | 0x0001
        return AmsResponseData(
            struct.pack("<H", state),
            request.ams_header.error_code,
            struct.pack("<I", code),
        )

    def touched(self, request):
        """(index group, offset) pairs a write request would change."""
        command = struct.unpack("<H", request.ams_header.command_id)[0]
        data = request.ams_header.data
        if command == constants.ADSCOMMAND_WRITE:
            return [struct.unpack("<II", data[:8])]
        if command == constants.ADSCOMMAND_READWRITE:
            group, offset = struct.unpack("<II", data[:8])
            if group == constants.ADSIGRP_SUMUP_WRITE:
                body = data[16:]
                return [struct.unpack("<II", body[i : i + 8]) for i in range(0, offset * 12, 12)]
        return []

    def handle_request(self, request):
        if self.delay_s:
            time.sleep(self.delay_s)
        for key in self.touched(request):
            if key in self.read_only:
                return self.refuse(request, ERR_NOT_PERMITTED)
            if key not in self._data:
                return self.refuse(request, ERR_INVALID_OFFSET)
        try:
            return super().handle_request(request)
        except KeyError:
            return self.refuse(request, ERR_INVALID_OFFSET)


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--lreal", action="append", default=[])
    p.add_argument("--real", action="append", default=[])
    p.add_argument("--read-only", action="append", default=[])
    p.add_argument("--delay-s", type=float, default=0.0)
    a = p.parse_args()
    handler = Handler({addr(x) for x in a.read_only}, a.delay_s)
    for specs, ads_type, name in (
        (a.lreal, constants.ADST_REAL64, "LREAL"),
        (a.real, constants.ADST_REAL32, "REAL"),
    ):
        for spec in specs:
            where, value = spec.split("=")
            g, o = addr(where)
            handler.add_variable(
                PLCVariable(f"v_{g:x}_{o:x}", float(value), ads_type, name, g, o)
            )
    server = AdsTestServer(handler=handler, ip_address="127.0.0.1", port=0, logging=False)
    server.start()
    print(f"PORT {server.server.getsockname()[1]}", flush=True)
    sys.stdin.read()
    server.close()


if __name__ == "__main__":
    main()
