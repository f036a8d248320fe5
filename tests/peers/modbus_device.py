"""A field ADC module from another vendor for the Modbus source's tests: pymodbus'
server holding fixed registers, over Modbus TCP or Modbus RTU.

The register contents are written out here on their own (Python's struct packs each
value in its byte order), so the gateway's decoding is checked against a second
implementation. tests/modbus_peer.rs holds the same table.

Input registers (function 0x04), 0-based, 0..=9 exist:
  0, 1, 2  u16  12-bit ADC counts of 4-20 mA transmitters: 1775, 2457, 2600
  3        i16  -123 (a module reporting 0.1 degC steps)
Holding registers (function 0x03), 0..=39 exist (a gap read across the unused ones
answers zeros):
  10  f32 ABCD  23.45       12  f32 CDAB  41.7
  14  f32 BADC  18.52       16  f32 DCBA  -7.37
  20  u32 CDAB  3000000123  22  i32 ABCD  -98765
Any other address answers exception 0x02 (illegal data address).

Modes:
  tcp   listen on 127.0.0.1:--port (0 = any) and print "PORT <n>"
  rtu   make two pseudo-terminal pairs, relay bytes between their masters (a serial
        cable), serve RTU on one slave and print "PATH <other slave>" for the gateway

Runs until stdin closes or SIGTERM.

    python modbus_device.py tcp --port 0 --unit 1
    python modbus_device.py rtu --unit 17 --baud 115200
"""

import argparse
import asyncio
import logging
import os
import signal
import struct
import sys
import threading
import tty

from pymodbus.framer import FramerType
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

INPUT_COUNT = 10
HOLDING_COUNT = 40


def words(fmt, value, order):
    """`value` packed big-endian as `fmt`, as registers in byte order `order`."""
    b = struct.pack(fmt, value)
    if order in ("BADC", "DCBA"):
        b = bytes(b[i ^ 1] for i in range(len(b)))
    w = [int.from_bytes(b[i : i + 2], "big") for i in range(0, len(b), 2)]
    if order in ("CDAB", "DCBA"):
        w.reverse()
    return w


def registers():
    ir = [0] * INPUT_COUNT
    ir[0:3] = [1775, 2457, 2600]
    ir[3:4] = words(">h", -123, "ABCD")
    hr = [0] * HOLDING_COUNT
    hr[10:12] = words(">f", 23.45, "ABCD")
    hr[12:14] = words(">f", 41.7, "CDAB")
    hr[14:16] = words(">f", 18.52, "BADC")
    hr[16:18] = words(">f", -7.37, "DCBA")
    hr[20:22] = words(">I", 3000000123, "CDAB")
    hr[22:24] = words(">i", -98765, "ABCD")
    return ir, hr


def device(unit):
    ir, hr = registers()
    block = lambda values: [SimData(0, values=values, datatype=DataType.REGISTERS)]
    # Separate tables (coils, discrete inputs, holding, input), as an ADC module has;
    # pymodbus wants at least one entry in each.
    bits = [SimData(0, values=False, datatype=DataType.BITS)]
    return SimDevice(unit, simdata=(bits, bits, block(hr), block(ir)))


def pty_pair():
    """A pseudo-terminal pair in raw mode: (master fd, slave fd, slave path)."""
    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    return master, slave, os.ttyname(slave)


def relay(loop, src, dst):
    """Copies what `src` brings to `dst`; what `dst` refuses is lost, as on a line."""

    def pump():
        try:
            data = os.read(src, 4096)
        except (BlockingIOError, OSError):
            return
        try:
            os.write(dst, data)
        except OSError:
            pass

    loop.add_reader(src, pump)


async def main():
    p = argparse.ArgumentParser()
    p.add_argument("mode", choices=["tcp", "rtu"])
    p.add_argument("--port", type=int, default=0)
    p.add_argument("--unit", type=int, default=1)
    p.add_argument("--baud", type=int, default=115200)
    a = p.parse_args()
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    loop = asyncio.get_running_loop()

    if a.mode == "tcp":
        server = ModbusTcpServer(device(a.unit), address=("127.0.0.1", a.port))
        await server.serve_forever(background=True)
        port = server.transport.sockets[0].getsockname()[1]
        print(f"PORT {port}", flush=True)
    else:
        m_dev, s_dev, dev_path = pty_pair()
        m_gw, s_gw, gw_path = pty_pair()
        relay(loop, m_dev, m_gw)
        relay(loop, m_gw, m_dev)
        server = ModbusSerialServer(
            device(a.unit),
            framer=FramerType.RTU,
            port=dev_path,
            # A pty carries bytes, not bits: baud, parity and stop bits never reach the
            # bytes, and pyserial's PARENB on a pty fails (EINVAL). The gateway opens
            # its end with its config's settings.
            baudrate=a.baud,
            parity="N",
            stopbits=1,
            bytesize=8,
        )
        await server.serve_forever(background=True)
        # The slave fds stay open: a pty whose slave is closed fails its master's reads.
        print(f"PATH {gw_path}", flush=True)

    done = asyncio.Event()
    loop.add_signal_handler(signal.SIGTERM, done.set)
    threading.Thread(
        target=lambda: (sys.stdin.read(), loop.call_soon_threadsafe(done.set)),
        daemon=True,
    ).start()
    await done.wait()
    await server.shutdown()


if __name__ == "__main__":
    asyncio.run(main())
