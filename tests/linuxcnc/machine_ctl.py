#!/usr/bin/python3
"""Display program of the test mill: releases the E-stop, switches the machine on and
homes it, then runs the commands of its standard input, one per line (`mdi G-CODE`,
`off`, `on`). LinuxCNC shuts down when its input closes and this program ends."""
import sys

import linuxcnc

c = linuxcnc.command()


def state(s):
    c.state(s)
    c.wait_complete()


state(linuxcnc.STATE_ESTOP_RESET)
state(linuxcnc.STATE_ON)
c.mode(linuxcnc.MODE_MANUAL)
c.wait_complete()
c.teleop_enable(0)
c.wait_complete()
c.home(-1)
c.wait_complete()
for line in sys.stdin:
    cmd, _, arg = line.strip().partition(" ")
    if cmd == "mdi":
        c.mode(linuxcnc.MODE_MDI)
        c.wait_complete()
        c.mdi(arg)
        c.wait_complete()
    elif cmd in ("off", "on"):
        state(linuxcnc.STATE_OFF if cmd == "off" else linuxcnc.STATE_ON)
