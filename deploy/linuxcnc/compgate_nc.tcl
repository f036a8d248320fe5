# compgate NC axis modules for LinuxCNC: HAL file (haltcl), [HAL]HALFILE = compgate_nc.tcl
# after the machine's own HAL files, with compgate_nc.py beside it in the configuration
# directory. One module per axis in [COMPGATE]AXES: compgate writes that axis's SD43900,
# SD43910 and SD43920 over Modbus TCP into it, and the servo thread applies
#   offset = SD43900 + SD43910 * (axis.L.pos-cmd - SD43920)
# as the axis's external offset, in counts of 1 nm. The INI file:
#   [COMPGATE]
#   AXES = X Z
#   [COMPGATE_X]
#   JOINT = 0        (the joint whose homed flag is the axis's "referenced")
#   PORT = 5020      (Modbus TCP; 0: any free one, shown on the pin compgate-nc-x.port)
#   MD32750 = 3      (bit 0 applies SD43900, bit 1 SD43910)
#   [AXIS_X]OFFSET_AV_RATIO = 0.1   (the share of velocity and acceleration the offset may take)
# LinuxCNC's outputs read here (axis.L.pos-cmd, axis.L.eoffset, joint.N.homed,
# motion.motion-enabled) join the signal the machine's HAL already put them on, if any.
# More: docs/guide/real-nc-linuxcnc.md.

proc compgate_ini {section key} {
    upvar #0 ::$section values
    if {![info exists values($key)]} {
        error "compgate_nc.tcl: \[$section\]$key is missing from the INI file"
    }
    return [lindex $values($key) 0]
}

set compgate_axes [string tolower [compgate_ini COMPGATE AXES]]

# The signal `pin` is on, or "".
proc compgate_signal {pin} {
    set name [string map {. \\.} $pin]
    if {[regexp -line "\\s$name\\s+(==>|<==|<=>) (\\S+)" [hal show pin $pin] -> _ sig]} {
        return $sig
    }
    return ""
}

# Nets LinuxCNC's output `pin` to `readers`: on the signal it is on already (a pin is
# on one signal at most), else on a new signal `name`.
proc compgate_read {name pin args} {
    set sig [compgate_signal $pin]
    if {$sig eq ""} {
        net $name $pin {*}$args
    } else {
        net $sig {*}$args
    }
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

# The 840D's formula in the servo thread, after motion-controller: the offset follows
# the axis's position within a servo period. One loadrt per kind for every axis.
proc compgate_names {suffixes} {
    set names {}
    foreach a $::compgate_axes {
        foreach s $suffixes { lappend names compgate-$a-$s }
    }
    return [join $names ,]
}
loadrt sum2 names=[compgate_names {dx sum}]
loadrt mult2 names=[compgate_names slope]
loadrt scale names=[compgate_names nm]
loadrt conv_float_s32 names=[compgate_names counts]

foreach a $compgate_axes {
    set A [string toupper $a]
    set m compgate-nc-$a
    set joint [compgate_ini COMPGATE_$A JOINT]
    loadusr -Wn $m ./compgate_nc.py --axis $a --joint $joint \
        --port [compgate_ini COMPGATE_$A PORT] --md32750 [compgate_ini COMPGATE_$A MD32750]
    foreach f {dx slope sum nm counts} { addf compgate-$a-$f servo-thread }

    compgate_read compgate-$a-pos axis.$a.pos-cmd compgate-$a-dx.in0 $m.pos-mm
    net compgate-$a-ref      $m.ref-mm                => compgate-$a-dx.in1
    setp compgate-$a-dx.gain1 -1
    net compgate-$a-dx       compgate-$a-dx.out       => compgate-$a-slope.in0
    net compgate-$a-tanb     $m.slope                 => compgate-$a-slope.in1
    net compgate-$a-abs      $m.abs-mm                => compgate-$a-sum.in0
    net compgate-$a-slope-mm compgate-$a-slope.out    => compgate-$a-sum.in1
    net compgate-$a-target   compgate-$a-sum.out      => compgate-$a-nm.in $m.target-mm
    setp compgate-$a-nm.gain 1000000
    net compgate-$a-nm       compgate-$a-nm.out       => compgate-$a-counts.in
    net compgate-$a-counts   compgate-$a-counts.out   => [compgate_drive axis.$a.eoffset-counts]
    setp [compgate_drive axis.$a.eoffset-scale] 0.000001
    # A machine whose HAL switches the offsets (a panel's button) keeps that switch.
    if {[compgate_signal axis.$a.eoffset-enable] eq ""} {
        setp axis.$a.eoffset-enable 1
    }

    # What the module reports back to compgate.
    compgate_read compgate-$a-applied axis.$a.eoffset $m.applied-mm
    compgate_read compgate-$a-homed joint.$joint.homed $m.homed
    compgate_read compgate-machine-on motion.motion-enabled $m.machine-on
}
