"""An independent CANopen node for the vcan tests: python-canopen's LocalNode, a CiA 301
implementation of its own (SDO server, NMT slave, heartbeat producer, PDO encoding), as a
CiA 401 analogue input module.

Usage: canopen_node.py INTERFACE NODE_ID [--event-ms N] [--bustype socketcan]

Object dictionary: 1000h device type (CiA 401), 1001h error register, 1008h device name
(longer than 4 bytes: a segmented upload), 1017h producer heartbeat time (100 ms),
1800h/1A00h TPDO1 (COB-ID 180h + node id, synchronous, 6401h subs 1-4; inhibit time and event timer), 6401h the
analogue inputs 1-8 (INTEGER16). LocalNode has no synchronous PDO service of its own,
so TPDO1 is sent here on every SYNC while the node is operational. With --event-ms
TPDO1 is event-driven instead (transmission type 255, event timer N ms): once the node
is operational python-canopen sends it every N ms, whatever the SYNC.

It boots (boot-up, then pre-operational with its heartbeat) and prints `READY <node id>`.
Commands on standard input, one per line:
    set SUB VALUE     6401h sub SUB (and its place in TPDO1) holds VALUE
    fail SUB CODE     an upload of 6401h sub SUB aborts with CODE (hex)
    silent            no heartbeat and no PDO any more, as a node that lost power
Serves until standard input closes.
"""

import sys

import canopen
from canopen.objectdictionary import (
    INTEGER16,
    UNSIGNED8,
    UNSIGNED16,
    UNSIGNED32,
    VISIBLE_STRING,
    ODArray,
    ODRecord,
    ODVariable,
)
from canopen.sdo.exceptions import SdoAbortedError

HEARTBEAT_MS = 100
INPUTS = 8
IN_TPDO1 = 4


def var(index, sub, name, data_type, default, access="ro"):
    v = ODVariable(name, index, sub)
    v.data_type = data_type
    v.access_type = access
    v.default = default
    return v


def dictionary(node_id):
    od = canopen.ObjectDictionary()
    od.add_object(var(0x1000, 0, "Device type", UNSIGNED32, 0x00040191))
    od.add_object(var(0x1001, 0, "Error register", UNSIGNED8, 0))
    od.add_object(
        var(0x1008, 0, "Manufacturer device name", VISIBLE_STRING, "python-canopen AI")
    )
    od.add_object(
        var(0x1017, 0, "Producer heartbeat time", UNSIGNED16, HEARTBEAT_MS, "rw")
    )
    com = ODRecord("TPDO1 communication parameter", 0x1800)
    com.add_member(var(0x1800, 0, "Highest sub-index supported", UNSIGNED8, 5))
    com.add_member(var(0x1800, 1, "COB-ID", UNSIGNED32, 0x180 + node_id, "rw"))
    com.add_member(var(0x1800, 2, "Transmission type", UNSIGNED8, 1, "rw"))
    com.add_member(var(0x1800, 3, "Inhibit time", UNSIGNED16, 0, "rw"))
    com.add_member(var(0x1800, 5, "Event timer", UNSIGNED16, 0, "rw"))
    od.add_object(com)
    mapping = ODRecord("TPDO1 mapping parameter", 0x1A00)
    mapping.add_member(var(0x1A00, 0, "Number of mapped objects", UNSIGNED8, 0, "rw"))
    for i in range(1, 9):
        mapping.add_member(var(0x1A00, i, f"Mapped object {i}", UNSIGNED32, 0, "rw"))
    od.add_object(mapping)
    inputs = ODArray("Read analogue input 16-bit", 0x6401)
    inputs.add_member(var(0x6401, 0, "Number of inputs", UNSIGNED8, INPUTS))
    for i in range(1, INPUTS + 1):
        inputs.add_member(var(0x6401, i, f"Analogue input {i}", INTEGER16, 0))
    od.add_object(inputs)
    return od


def main():
    args = sys.argv[1:]
    bustype = "socketcan"
    if "--bustype" in args:
        at = args.index("--bustype")
        bustype = args[at + 1]
        del args[at : at + 2]
    event_ms = 0
    if "--event-ms" in args:
        at = args.index("--event-ms")
        event_ms = int(args[at + 1])
        del args[at : at + 2]
    interface, node_id = args[0], int(args[1])

    network = canopen.Network()
    network.connect(interface=bustype, channel=interface)
    node = canopen.LocalNode(node_id, dictionary(node_id))
    network.add_node(node)

    tpdo = node.tpdo[1]
    tpdo.clear()
    slots = {sub: tpdo.add_variable(0x6401, sub) for sub in range(1, IN_TPDO1 + 1)}
    tpdo.cob_id = 0x180 + node_id
    tpdo.trans_type = 255 if event_ms else 1
    if event_ms:
        tpdo.event_timer = event_ms
    tpdo.enabled = True
    # Into the node's own 1800h/1A00h, so an SDO upload shows the mapping it sends.
    tpdo.save()

    failing = {}

    def on_read(index, subindex, od):
        if index == 0x6401 and subindex in failing:
            raise SdoAbortedError(failing[subindex])
        return None

    node.add_read_callback(on_read)

    silent = False
    sending = False

    def on_sync(can_id, data, timestamp):
        if not event_ms and not silent and node.nmt.state == "OPERATIONAL":
            tpdo.transmit()

    def on_nmt(can_id, data, timestamp):
        # After the node's own NMT handler, which was subscribed first.
        nonlocal sending
        if event_ms and not silent and not sending and node.nmt.state == "OPERATIONAL":
            tpdo.start(event_ms / 1000)
            sending = True

    network.subscribe(0x80, on_sync)
    network.subscribe(0, on_nmt)

    node.nmt.send_command(0x81)  # reset node: the boot-up message
    node.nmt.send_command(0x80)  # pre-operational: the heartbeat starts
    print(f"READY {node_id}", flush=True)

    for line in sys.stdin:
        words = line.split()
        if not words:
            continue
        if words[0] == "set":
            sub, value = int(words[1]), int(words[2])
            node.sdo[0x6401][sub].raw = value
            if sub in slots:
                slots[sub].raw = value
                if sending:
                    tpdo.update()
        elif words[0] == "fail":
            failing[int(words[1])] = int(words[2], 16)
        elif words[0] == "silent":
            silent = True
            node.nmt.stop_heartbeat()
            if sending:
                tpdo.stop()
        else:
            print(f"unknown command {line.strip()!r}", file=sys.stderr, flush=True)
            sys.exit(2)
        print("OK", flush=True)

    node.nmt.stop_heartbeat()
    if sending:
        tpdo.stop()
    network.disconnect()


if __name__ == "__main__":
    main()
