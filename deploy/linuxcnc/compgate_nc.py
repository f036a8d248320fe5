#!/usr/bin/python3
"""compgate NC axis module for LinuxCNC: a userspace HAL component.

compgate writes each compensated axis's SD43900 / SD43910 / SD43920 as a job into an
NC axis module over Modbus TCP (the register map in docs/reference/registers.md). This
component is that module for one LinuxCNC axis: it serves the job block and the
read-back block, and every 10 ms sets the axis's external offset (the pin `counts`,
netted to axis.L.eoffset-counts in 1 nm counts) as the 840D applies the values:

    offset = SD43900 + SD43910 * (axis.L.pos-cmd - SD43920)

while the machine is on and the axis homed (MD32750 bit 0 the first term, bit 1 the
second). LinuxCNC limits how fast the offset moves with [AXIS_L]OFFSET_AV_RATIO, as
MD32760 does on the 840D. The setting data are retained across restarts in a JSON
file (--state-file), as the 840D retains them.

Started by compgate_nc.tcl, one per axis:
    loadusr -Wn compgate-nc-x ./compgate_nc.py --axis x --joint 0 --port 5020

Needs only Python 3 and LinuxCNC's own `hal` and `linuxcnc` modules. The machine's
linear units must be mm.
"""

import argparse
import json
import math
import os
import signal
import socket
import socketserver
import struct
import sys
import threading
import time

import hal
import linuxcnc

# The register map (crates/ncproto): holding registers, 0-based.
REQ, STATE, DONE, ERROR, STATUS, ERROR_INDEX, JOB_ID, NUM_PAIRS, PAIRS = range(9)
PAIR_REGS, MAX_PAIRS, JOB_ID_DONE, JOB_BLOCK_LEN = 5, 8, 48, 49
READBACK, READBACK_LEN, GAP = 100, 42, range(136, 140)
IDLE, BUSY, JOB_DONE, JOB_ERROR = 0, 1, 2, 3
ACCESS_DENIED, INVALID_ADDRESS, NO_OBJECT, OUT_OF_RANGE = 3, 5, 10, 16
SD43900, SD43910, SD43920 = 43900, 43910, 43920
MACHINE_DATA = (32450, 32750, 32760, 32000)
LIMITS = {SD43900: 10.0, SD43910: 0.1, SD43920: 100000.0}
# Modbus exception codes.
ILLEGAL_FUNCTION, ILLEGAL_ADDRESS, ILLEGAL_VALUE = 1, 2, 3
# mm per count of axis.L.eoffset-counts (compgate_nc.tcl sets eoffset-scale to it).
COUNT_MM = 1e-6
S32_MAX = 2**31 - 1
# Seconds between two updates of the offset: the slope term lags the axis by this,
# SD43910 x feed x 10 ms (0.08 um at 5e-5 and 10 m/min).
PERIOD_S = 0.01


def f64_regs(value):
    return list(struct.unpack(">4H", struct.pack(">d", value)))


def regs_f64(regs):
    return struct.unpack(">d", struct.pack(">4H", *regs))[0]


class ModbusError(Exception):
    def __init__(self, code):
        super().__init__(code)
        self.code = code


class Module:
    """The job block, the setting data and the read-back block of one axis."""

    def __init__(self, comp, pins, state_file, md32750, md32760, max_velo_mm_per_min, md32450_mm):
        self.comp = comp
        self.state_file = state_file
        # LinuxCNC's pins, read by name (no signal of the machine's HAL is touched).
        self.pins = pins
        self.target_mm = 0.0
        self.counts = 0
        self.lock = threading.Lock()
        self.job = [0] * JOB_BLOCK_LEN
        self.sd = load_setting_data(state_file)
        self.md32750 = md32750
        self.md32760 = md32760
        self.max_velo_mm_per_min = max_velo_mm_per_min
        self.md32450_mm = md32450_mm

    def check_pair(self, var_id, value):
        if var_id in LIMITS:
            # NaN fails the comparison, infinities the limit.
            return 0 if abs(value) <= LIMITS[var_id] else OUT_OF_RANGE
        return ACCESS_DENIED if var_id in MACHINE_DATA else NO_OBJECT

    def execute(self):
        """Runs the latched job: every pair checked, then all applied or none."""
        n = self.job[NUM_PAIRS]
        if not 1 <= n <= MAX_PAIRS:
            return INVALID_ADDRESS, 0
        pairs = []
        for i in range(n):
            at = PAIRS + PAIR_REGS * i
            var_id, value = self.job[at], regs_f64(self.job[at + 1 : at + 5])
            status = self.check_pair(var_id, value)
            if status:
                return status, i + 1
            pairs.append((var_id, value))
        self.sd.update(pairs)
        # Retained as the 840D retains setting data: the job is done once it is stored.
        try:
            save_setting_data(self.state_file, self.sd)
        except OSError as e:
            print(f"compgate_nc: cannot store the setting data in {self.state_file}: {e}", file=sys.stderr)
        return 0, 0

    def write(self, address, words):
        end = address + len(words)
        only_req = address == REQ and len(words) == 1
        if not (only_req or (address >= JOB_ID and end <= JOB_ID_DONE)):
            raise ModbusError(ILLEGAL_ADDRESS)
        if not only_req:
            self.job[address:end] = words
            return
        old_req, self.job[REQ] = self.job[REQ], words[0]
        state = self.job[STATE]
        if state == IDLE and old_req == 0 and words[0] != 0:
            status, index = self.execute()
            self.job[STATE] = JOB_ERROR if status else JOB_DONE
            self.job[DONE : ERROR_INDEX + 1] = [int(not status), int(bool(status)), status, index]
            self.job[JOB_ID_DONE] = self.job[JOB_ID]
        elif state in (JOB_DONE, JOB_ERROR) and words[0] == 0:
            self.job[STATE] = IDLE
            self.job[DONE : ERROR_INDEX + 1] = [0, 0, 0, 0]

    def readback(self):
        regs = []
        for value in (
            self.sd[SD43900],
            self.sd[SD43910],
            self.sd[SD43920],
            self.md32760,
            self.max_velo_mm_per_min,
            hal.get_value(self.pins["pos"]),
            hal.get_value(self.pins["applied"]),
            self.target_mm,
            self.md32450_mm,
        ):
            regs += f64_regs(value)
        return regs + [0] * 4 + [self.md32750, int(hal.get_value(self.pins["homed"]))]

    def read(self, address, count):
        end = address + count
        if end <= JOB_BLOCK_LEN:
            return self.job[address:end]
        if address >= READBACK and end <= READBACK + READBACK_LEN and not (
            address < GAP.stop and GAP.start < end
        ):
            return self.readback()[address - READBACK : end - READBACK]
        raise ModbusError(ILLEGAL_ADDRESS)

    def pdu(self, pdu):
        """The reply PDU to a request PDU (function codes 3, 6 and 16)."""
        fc = pdu[0]
        try:
            if fc == 3 and len(pdu) == 5:
                address, count = struct.unpack(">HH", pdu[1:5])
                if not 1 <= count <= 125:
                    raise ModbusError(ILLEGAL_VALUE)
                with self.lock:
                    regs = self.read(address, count)
                return struct.pack(">BB%dH" % count, 3, 2 * count, *regs)
            if fc == 6 and len(pdu) == 5:
                address, word = struct.unpack(">HH", pdu[1:5])
                with self.lock:
                    self.write(address, [word])
                return pdu
            if fc == 16 and len(pdu) >= 6:
                address, count, nbytes = struct.unpack(">HHB", pdu[1:6])
                if not 1 <= count <= 123 or nbytes != 2 * count or len(pdu) != 6 + nbytes:
                    raise ModbusError(ILLEGAL_VALUE)
                with self.lock:
                    self.write(address, list(struct.unpack(">%dH" % count, pdu[6:])))
                return pdu[:5]
            raise ModbusError(ILLEGAL_VALUE if fc in (3, 6, 16) else ILLEGAL_FUNCTION)
        except ModbusError as e:
            return bytes([fc | 0x80, e.code])

    def update(self):
        """Moves the axis's requested offset to the formula at its position now.

        LinuxCNC takes eoffset-counts as steps: it adds a change of the counts to the
        requested offset, and drops the change while a joint is not homed or the offset
        is switched off (eoffset-enable). So the counts follow the difference between
        the formula and what LinuxCNC requests, not the formula itself, and only while
        LinuxCNC takes them; a dropped change is made up at the next update. With the
        machine off the counts go to zero: LinuxCNC restarts its offset from zero at
        the next machine on."""
        get = hal.get_value
        pos_mm = get(self.pins["pos"])
        on, homed, enabled = get(self.pins["on"]), get(self.pins["all_homed"]), get(self.pins["enable"])
        with self.lock:
            target_mm = 0.0
            if on and homed:
                if self.md32750 & 1:
                    target_mm += self.sd[SD43900]
                if self.md32750 & 2:
                    target_mm += self.sd[SD43910] * (pos_mm - self.sd[SD43920])
            self.target_mm = target_mm
        if not on:
            self.counts = 0
        elif homed and enabled:
            step = round((target_mm - get(self.pins["request"])) / COUNT_MM)
            self.counts = max(-S32_MAX, min(S32_MAX, self.counts + step))
        self.comp["counts"] = self.counts
        self.comp["target-mm"] = target_mm


def load_setting_data(path):
    """The setting data stored by the last job, zeros when none was stored yet; an
    unreadable file or a value beyond the limits stops the module, naming the file."""
    try:
        with open(path) as f:
            stored = json.load(f)
    except FileNotFoundError:
        return {SD43900: 0.0, SD43910: 0.0, SD43920: 0.0}
    except (OSError, ValueError) as e:
        sys.exit(f"compgate_nc: setting data file {path}: {e}; move it away to start from zero")
    sd = {}
    for var_id, limit in LIMITS.items():
        value = stored.get(f"SD{var_id}") if isinstance(stored, dict) else None
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        if not number or not math.isfinite(value) or abs(value) > limit:
            sys.exit(f"compgate_nc: setting data file {path}: SD{var_id} = {value!r} is not a number within +-{limit}; move the file away to start from zero")
        sd[var_id] = float(value)
    return sd


def save_setting_data(path, sd):
    """Writes the setting data atomically: a crash leaves the old file or the new."""
    tmp = f"{path}.tmp"
    with open(tmp, "w") as f:
        json.dump({f"SD{var_id}": value for var_id, value in sd.items()}, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def serve(module, bind, port):
    class Handler(socketserver.BaseRequestHandler):
        def handle(self):
            sock = self.request
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            while True:
                head = recv_exact(sock, 7)
                if head is None:
                    return
                tid, proto, length, unit = struct.unpack(">HHHB", head)
                body = recv_exact(sock, length - 1) if 2 <= length <= 254 else None
                if proto != 0 or not body:
                    return  # not Modbus TCP: drop the connection
                reply = module.pdu(body)
                sock.sendall(struct.pack(">HHHB", tid, 0, len(reply) + 1, unit) + reply)

    socketserver.ThreadingTCPServer.allow_reuse_address = True
    socketserver.ThreadingTCPServer.daemon_threads = True
    try:
        server = socketserver.ThreadingTCPServer((bind, port), Handler)
    except OSError as e:
        sys.exit(f"compgate_nc: cannot listen on {bind}:{port}: {e.strerror} (another module or program on that port?)")
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server.server_address[1]


def recv_exact(sock, n):
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            return None
        data += chunk
    return data


def ini_float(ini, section, key, default=None):
    text = ini.find(section, key)
    if text is None:
        if default is None:
            sys.exit(f"compgate_nc: [{section}]{key} is missing from the INI file")
        return default
    try:
        return float(text)
    except ValueError:
        sys.exit(f"compgate_nc: [{section}]{key} = {text!r} is not a number")


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--axis", required=True, help="axis letter: x, y, z, ...")
    p.add_argument("--joint", type=int, required=True, help="joint of the axis: its homed flag and [JOINT_N]BACKLASH")
    p.add_argument("--port", type=int, default=5020, help="Modbus TCP port (0: any free one, see the port pin)")
    p.add_argument("--bind", default="0.0.0.0", help="address to listen on (default: every interface)")
    p.add_argument("--md32750", type=int, default=3, choices=range(4), help="bit 0 SD43900, bit 1 SD43910 applied")
    p.add_argument("--name", help="HAL component name (default compgate-nc-AXIS)")
    p.add_argument("--state-file", help="where the setting data are retained (default compgate-nc-AXIS.json in the working directory)")
    args = p.parse_args()
    axis = args.axis.upper()

    ini = linuxcnc.ini(os.environ["INI_FILE_NAME"])
    units = (ini.find("TRAJ", "LINEAR_UNITS") or "").lower()
    if units not in ("mm", "metric"):
        sys.exit(f"compgate_nc: [TRAJ]LINEAR_UNITS = {units!r}; compgate writes mm, so the machine must be set up in mm")
    coordinates = (ini.find("TRAJ", "COORDINATES") or "").upper()
    if axis not in coordinates:
        sys.exit(f"compgate_nc: axis {axis} in [COMPGATE]AXES is not in [TRAJ]COORDINATES = {coordinates}")
    ratio = ini_float(ini, f"AXIS_{axis}", "OFFSET_AV_RATIO")
    if not 0 < ratio <= 0.9:
        sys.exit(f"compgate_nc: [AXIS_{axis}]OFFSET_AV_RATIO = {ratio}: external offsets need 0 < ratio <= 0.9")

    comp = hal.component(args.name or f"compgate-nc-{args.axis.lower()}")
    a = args.axis.lower()
    pins = {
        "pos": f"axis.{a}.pos-cmd",
        "applied": f"axis.{a}.eoffset",
        "request": f"axis.{a}.eoffset-request",
        "enable": f"axis.{a}.eoffset-enable",
        "homed": f"joint.{args.joint}.homed",
        "all_homed": "motion.is-all-homed",
        "on": "motion.motion-enabled",
    }
    for pin in pins.values():
        try:
            hal.get_value(pin)
        except RuntimeError:
            sys.exit(
                f"compgate_nc: LinuxCNC has no pin {pin}: check [COMPGATE_{axis}]JOINT = {args.joint}, "
                "and that compgate_nc.tcl comes after the HAL file that loads motmod"
            )
    comp.newpin("counts", hal.HAL_S32, hal.HAL_OUT)
    comp.newpin("target-mm", hal.HAL_FLOAT, hal.HAL_OUT)
    comp.newpin("port", hal.HAL_S32, hal.HAL_OUT)
    module = Module(
        comp,
        pins,
        args.state_file or f"compgate-nc-{a}.json",
        md32750=args.md32750,
        md32760=ratio,
        max_velo_mm_per_min=ini_float(ini, f"AXIS_{axis}", "MAX_VELOCITY") * 60.0,
        md32450_mm=ini_float(ini, f"JOINT_{args.joint}", "BACKLASH", 0.0),
    )
    comp["port"] = serve(module, args.bind, args.port)
    comp.ready()
    # halcmd unload (LinuxCNC's shutdown) ends the component with SIGTERM.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    try:
        while True:
            module.update()
            time.sleep(PERIOD_S)
    except KeyboardInterrupt:
        pass


if __name__ == "__main__":
    main()
