"""A PLC for the S7 target's tests: python-snap7's S7 server holds the data block and
a scan loop plays the PLC program of deploy/plc/ on it (the FB3 PUT side).

The block layout is written out here on its own, from the table in
docs/guide/real-nc-s7.md, so the gateway's layout is checked against a second
reading of the same table.

Modes:
  done    answer DONE, copy each value to its read-back slot (as FB3 PUT + FB2 GET
          would), after the program's own checks (pair count, variable id, range)
  error   answer ERROR with --status / --error-index, values untouched
  silent  never answer (the PLC program is not running)

--readback-skew-ulps N makes the read-back of SD43900 differ from the value sent by N
steps of the block's float type, for the read-back tolerance tests.

Prints "PORT <n>" once the server listens; runs until stdin closes or SIGTERM.

    python s7_plc.py --port 0 --db 100 --value-type real --mode done
"""

import argparse
import logging
import math
import signal
import struct
import sys
import threading
import time

from snap7.server import Server
from snap7.type import SrvArea

MAX_PAIRS = 8
# Variable id -> (read-back slot, |limit|): SD43900, SD43910, SD43920 (STATUS 16
# beyond the limit, as the SCL program checks before FB3).
WRITABLE = {43900: (0, 10.0), 43910: (1, 0.1), 43920: (2, 100000.0)}


class Layout:
    def __init__(self, value_type):
        self.w = 4 if value_type == "real" else 8
        self.fmt = ">f" if value_type == "real" else ">d"
        self.req, self.job_id, self.axis, self.num_pairs = 0, 2, 4, 6
        self.var_ids, self.values = 8, 24
        self.state = 24 + 8 * self.w
        self.status = self.state + 2
        self.error_index = self.state + 4
        self.job_id_done = self.state + 6
        self.fb3_state = self.state + 8
        self.md32750 = self.state + 10
        self.referenced = self.state + 12
        self.readback = self.state + 16
        self.length = self.readback + 9 * self.w


class AxisBlock:
    """One axis' block and the state the PLC program keeps for it."""

    def __init__(self, db, base, axis_no, lay, args):
        self.db, self.base, self.axis_no, self.lay, self.args = db, base, axis_no, lay, args
        self.prev_req = 0
        self.busy_scans = 0
        self.latched = b""

    def word(self, off):
        return struct.unpack_from(">H", self.db, self.base + off)[0]

    def set_word(self, off, v):
        struct.pack_into(">H", self.db, self.base + off, v & 0xFFFF)

    def set_real(self, off, v):
        struct.pack_into(self.lay.fmt, self.db, self.base + off, v)

    def init_readback(self):
        """Machine data a real PLC would GET at start-up."""
        lay = self.lay
        self.set_word(lay.md32750, 3)
        self.set_word(lay.referenced, 1)
        for k, v in enumerate([0.0, 0.0, 0.0, 0.01, 10000.0, 0.0, 0.0, 0.0, 0.0]):
            self.set_real(lay.readback + k * lay.w, v)

    def latch(self):
        """The job as it stood at the rising edge of REQ: later writes do not alter it."""
        lay = self.lay
        self.latched = bytes(self.db[self.base + lay.job_id : self.base + lay.state])

    def job_word(self, off):
        return struct.unpack_from(">H", self.latched, off - self.lay.job_id)[0]

    def job_real(self, off):
        return struct.unpack_from(self.lay.fmt, self.latched, off - self.lay.job_id)[0]

    def finish(self, state, status, index):
        lay = self.lay
        self.set_word(lay.status, status)
        self.set_word(lay.error_index, index)
        self.set_word(lay.fb3_state, 0)
        self.set_word(lay.job_id_done, self.job_word(lay.job_id))
        self.set_word(lay.state, state)

    def execute(self):
        """The latched job as FB3 PUT applies it: all pairs or none."""
        lay, a = self.lay, self.args
        if a.mode == "error":
            self.finish(3, a.status, a.error_index)
            return
        n = self.job_word(lay.num_pairs)
        # A job for another axis means the PC and the PLC disagree on the layout.
        if self.job_word(lay.axis) != self.axis_no or not 1 <= n <= MAX_PAIRS:
            self.finish(3, 5, 0)
            return
        pairs = []
        for i in range(n):
            var = self.job_word(lay.var_ids + 2 * i)
            value = self.job_real(lay.values + lay.w * i)
            if var not in WRITABLE:
                self.finish(3, 10, i + 1)
                return
            slot, limit = WRITABLE[var]
            if not math.isfinite(value) or abs(value) > limit:
                self.finish(3, 16, i + 1)
                return
            pairs.append((slot, value))
        for slot, value in pairs:
            self.set_real(lay.readback + slot * lay.w, value)
        if a.readback_skew_ulps:
            # An NC that holds SD43900 a few float steps off what was sent.
            off = self.base + lay.readback
            bits = "I" if lay.w == 4 else "Q"
            (b,) = struct.unpack_from(">" + bits, self.db, off)
            struct.pack_into(">" + bits, self.db, off, b + a.readback_skew_ulps)
        self.finish(2, 0, 0)

    def scan(self):
        lay, a = self.lay, self.args
        req = self.word(lay.req)
        state = self.word(lay.state)
        if state == 0 and req == 1 and self.prev_req == 0:
            self.latch()
            self.set_word(lay.state, 1)
            self.busy_scans = a.busy_scans
        elif state == 1:
            if self.busy_scans > 0:
                self.busy_scans -= 1
            else:
                self.execute()
        elif state in (2, 3) and req == 0:
            self.set_word(lay.state, 0)
        self.prev_req = req


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--port", type=int, default=0)
    p.add_argument("--db", type=int, default=100)
    p.add_argument("--start-byte", type=int, default=0)
    p.add_argument("--stride", type=int, help="bytes from one axis block to the next; default: the block length")
    p.add_argument("--axes", type=int, default=1)
    p.add_argument("--value-type", choices=["real", "lreal"], default="real")
    p.add_argument("--mode", choices=["done", "error", "silent"], default="done")
    p.add_argument("--status", type=int, default=3)
    p.add_argument("--error-index", type=int, default=1)
    p.add_argument("--readback-skew-ulps", type=int, default=0, help="done mode: SD43900's read-back this many float steps above the value sent")
    p.add_argument("--busy-scans", type=int, default=1, help="scans in BUSY, as FB3 takes a few PLC cycles")
    p.add_argument("--cycle-ms", type=float, default=1.0)
    a = p.parse_args()

    lay = Layout(a.value_type)
    if a.stride is None:
        a.stride = lay.length
    db = bytearray(a.start_byte + (a.axes - 1) * a.stride + lay.length)
    blocks = [AxisBlock(db, a.start_byte + i * a.stride, i + 1, lay, a) for i in range(a.axes)]
    for b in blocks:
        b.init_readback()

    # The server warns on stderr about refused reads; the tests provoke those.
    logging.getLogger("snap7").setLevel(logging.ERROR)
    server = Server(log=False)
    server.register_area(SrvArea.DB, a.db, db)
    server.start_to("127.0.0.1", a.port)
    print(f"PORT {server.server_socket.getsockname()[1]}", flush=True)

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
    while not stop.is_set():
        if a.mode != "silent":
            # The scan sees a consistent block: the server writes under the same lock.
            server.lock_area(SrvArea.DB, a.db)
            try:
                for b in blocks:
                    b.scan()
            finally:
                server.unlock_area(SrvArea.DB, a.db)
        time.sleep(a.cycle_ms / 1000.0)
    server.stop()


if __name__ == "__main__":
    main()
