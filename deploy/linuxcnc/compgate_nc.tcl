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
# A pin netted here that the machine's HAL already nets (joint.N.homed,
# motion.motion-enabled, axis.L.eoffset-*) must join that signal instead.
# More: docs/guide/real-nc-linuxcnc.md.

proc compgate_ini {section key} {
    upvar #0 ::$section values
    if {![info exists values($key)]} {
        error "compgate_nc.tcl: \[$section\]$key is missing from the INI file"
    }
    return [lindex $values($key) 0]
}

set compgate_axes [string tolower [compgate_ini COMPGATE AXES]]

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

    net compgate-$a-pos      axis.$a.pos-cmd          => compgate-$a-dx.in0 $m.pos-mm
    net compgate-$a-ref      $m.ref-mm                => compgate-$a-dx.in1
    setp compgate-$a-dx.gain1 -1
    net compgate-$a-dx       compgate-$a-dx.out       => compgate-$a-slope.in0
    net compgate-$a-tanb     $m.slope                 => compgate-$a-slope.in1
    net compgate-$a-abs      $m.abs-mm                => compgate-$a-sum.in0
    net compgate-$a-slope-mm compgate-$a-slope.out    => compgate-$a-sum.in1
    net compgate-$a-target   compgate-$a-sum.out      => compgate-$a-nm.in $m.target-mm
    setp compgate-$a-nm.gain 1000000
    net compgate-$a-nm       compgate-$a-nm.out       => compgate-$a-counts.in
    net compgate-$a-counts   compgate-$a-counts.out   => axis.$a.eoffset-counts
    setp axis.$a.eoffset-scale 0.000001
    setp axis.$a.eoffset-enable 1

    # What the module reports back to compgate.
    net compgate-$a-applied  axis.$a.eoffset          => $m.applied-mm
    net compgate-$a-homed    joint.$joint.homed       => $m.homed
}
# One signal serves every module.
net compgate-machine-on motion.motion-enabled => {*}[lmap a $compgate_axes {string cat compgate-nc-$a.machine-on}]
