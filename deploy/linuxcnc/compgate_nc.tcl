# compgate NC axis modules for LinuxCNC: HAL file (haltcl), [HAL]HALFILE = compgate_nc.tcl
# after the machine's own HAL files, with compgate_nc.py beside it in the configuration
# directory. One module per axis in [COMPGATE]AXES: compgate writes that axis's SD43900,
# SD43910 and SD43920 over Modbus TCP into it, and it sets the axis's external offset
#   offset = SD43900 + SD43910 * (axis.L.pos-cmd - SD43920)
# every 10 ms, in counts of 1 nm. The INI file:
#   [COMPGATE]
#   AXES = X Z
#   [COMPGATE_X]
#   JOINT = 0        (the joint whose homed flag is the axis's "referenced")
#   PORT = 5020      (Modbus TCP; 0: any free one, shown on the pin compgate-nc-x.port)
#   MD32750 = 3      (bit 0 applies SD43900, bit 1 SD43910)
#   [AXIS_X]OFFSET_AV_RATIO = 0.1   (the share of velocity and acceleration the offset may take)
# The modules read LinuxCNC's pins by name, so no signal of the machine's HAL changes.
# More: docs/guide/real-nc-linuxcnc.md.

proc compgate_ini {section key} {
    upvar #0 ::$section values
    if {![info exists values($key)]} {
        error "compgate_nc.tcl: \[$section\]$key is missing from the INI file"
    }
    return [lindex $values($key) 0]
}

# The signal `pin` is on, or "".
proc compgate_signal {pin} {
    set name [string map {. \\.} $pin]
    if {[regexp -line "\\s$name\\s+(==>|<==|<=>) (\\S+)" [hal show pin $pin] -> _ sig]} {
        return $sig
    }
    return ""
}

# An input of LinuxCNC's that the module drives: refused when the machine's HAL
# drives it already.
proc compgate_drive {pin} {
    set sig [compgate_signal $pin]
    if {$sig ne ""} {
        error "compgate_nc.tcl: $pin is on signal $sig already; the compgate module drives it: take it off that signal"
    }
    return $pin
}

set compgate_axes [compgate_ini COMPGATE AXES]
foreach a [string tolower $compgate_axes] {
    if {![regexp {^[a-z]$} $a]} {
        error "compgate_nc.tcl: \[COMPGATE\]AXES = $compgate_axes: expected axis letters separated by spaces, e.g. X Z"
    }
}
foreach a [string tolower $compgate_axes] {
    set A [string toupper $a]
    loadusr -Wn compgate-nc-$a ./compgate_nc.py --axis $a \
        --joint [compgate_ini COMPGATE_$A JOINT] --port [compgate_ini COMPGATE_$A PORT] \
        --md32750 [compgate_ini COMPGATE_$A MD32750]
    net compgate-$a-counts compgate-nc-$a.counts => [compgate_drive axis.$a.eoffset-counts]
    setp [compgate_drive axis.$a.eoffset-scale] 0.000001
    # A machine whose HAL switches the offsets (a panel's button) keeps that switch.
    if {[compgate_signal axis.$a.eoffset-enable] eq ""} {
        setp axis.$a.eoffset-enable 1
    }
}
