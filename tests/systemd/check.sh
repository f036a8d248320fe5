#!/usr/bin/env bash
# Runs inside the VM that tests/systemd/run.sh boots, under a real systemd as PID 1:
# installs compgate with deploy/install.sh and checks the unit in its sandbox, against
# the simulated plant in a unit of its own. Prints one `SD-CHECK:` line per check and
# an `SD-RESULT:` line; run.sh reads them off the serial console.
set -uo pipefail
cd "$(dirname "$0")/../.."
work=/run/sd-check
mkdir -p "$work"
passed=0
failed=0
ok() {
    echo "SD-CHECK: ok $1"
    passed=$((passed + 1))
}
bad() {
    echo "SD-CHECK: FAILED $1: $2"
    failed=$((failed + 1))
}
# until SECONDS CMD...: true once CMD succeeds, polled every 0.5 s.
until_s() {
    local end=$((SECONDS + $1))
    shift
    while ! "$@" >/dev/null 2>&1; do
        ((SECONDS < end)) || return 1
        sleep 0.5
    done
}
journal() { journalctl -u compgate -o cat --no-pager "$@"; }
prop() { systemctl show -p "$1" --value compgate; }
readings() { sqlite3 "file:/var/lib/compgate/compgate.db?mode=ro" "SELECT COUNT(*) FROM readings"; }
metric() { curl -sf http://127.0.0.1:19464/metrics | grep "^$1" | awk '{s += $2} END {print s + 0}'; }

# The demo's plant on fixed ports (the unit refuses port 0), recorded and served.
sed -e 's/127.0.0.1:0"/127.0.0.1:15020"/' -e '/^\[nc_modules.nc_x\]/,/^\[/ s/15020/15021/' \
    config/demo.toml >"$work/compgate.toml"
cat >>"$work/compgate.toml" <<'EOF'

[recorder]
commit_interval_s = 0.2
retention_interval_s = 1

[metrics]
bind = "127.0.0.1:19464"
EOF
systemd-run --quiet --unit=compgate-plant target/systemd/plant/compgate sim --config "$work/compgate.toml"
if until_s 60 bash -c 'ss -ltn | grep -q ":15021 "'; then ok "the simulated plant listens"; else bad "the simulated plant listens" "$(journalctl -u compgate-plant -o cat | tail -5)"; fi

# ---- install: validate, user, config, unit, enable, start (Type=notify: READY=1)
# No cargo on systemd's PATH: install.sh takes the binary built before, and says so.
if deploy/install.sh "$work/compgate.toml" >"$work/install.log" 2>&1 &&
    grep -q "cargo not found; installing target/production/release/compgate as built before" "$work/install.log"; then
    ok "install.sh installs the binary built before and starts the service"
else
    bad "install.sh installs the binary built before and starts the service" "$(tail -20 "$work/install.log")"
fi
[[ $(systemctl is-active compgate) == active && $(systemctl is-enabled compgate) == enabled ]] &&
    ok "active and enabled" || bad "active and enabled" "$(systemctl is-active compgate) $(systemctl is-enabled compgate)"
id -nG compgate | grep -qw dialout && ok "user compgate in dialout" || bad "user compgate in dialout" "$(id compgate)"
pid=$(prop MainPID)

# ---- running in the sandbox: STATUS=, the recorder, the metrics, the NC
if until_s 60 bash -c "systemctl show -p StatusText --value compgate | grep -q 'ain1 up'"; then
    ok "STATUS= says the device is up: $(prop StatusText)"
else
    bad "STATUS= says the device is up" "$(prop StatusText)"
fi
if until_s 60 bash -c '(( $(sqlite3 "file:/var/lib/compgate/compgate.db?mode=ro" "SELECT COUNT(*) FROM readings") > 0 ))'; then
    ok "readings recorded in the state directory ($(readings))"
else
    bad "readings recorded in the state directory" "$(ls -la /var/lib/compgate; journal | tail -5)"
fi
mode=$(stat -c '%U %a' /var/lib/compgate/compgate.db)
[[ $mode == "compgate 600" ]] && ok "database owned by compgate, mode 600 (UMask)" || bad "database owned by compgate, mode 600" "$mode"
if until_s 60 bash -c '(( $(curl -sf http://127.0.0.1:19464/metrics | grep "^compgate_nc_jobs_total.*result=\"ok\"" | wc -l) > 0 ))'; then
    ok "an NC job landed (metrics: $(metric 'compgate_nc_jobs_total{.*result="ok"') ok)"
else
    bad "an NC job landed" "$(curl -s http://127.0.0.1:19464/metrics | grep nc_jobs; journal | tail -5)"
fi
journal | grep -qi "permission denied\|operation not permitted\|bad system call" &&
    bad "no sandbox refusal in the journal" "$(journal | grep -i 'denied\|not permitted\|system call' | head -3)" ||
    ok "no sandbox refusal in the journal"

# ---- a device down and back: a WARN at journal priority 4, named in STATUS=
systemctl stop compgate-plant
# What `journalctl -u compgate` shows an operator: the line itself names the device.
if until_s 30 bash -c "journalctl -u compgate -p warning -o cat | grep 'device link down' | grep -q ain1"; then
    ok "device down is a journal warning naming the device"
else
    bad "device down is a journal warning naming the device" "$(journal -p warning | tail -3)"
fi
until_s 20 bash -c "systemctl show -p StatusText --value compgate | grep -q 'ain1 down'" &&
    ok "STATUS= names the device down" || bad "STATUS= names the device down" "$(prop StatusText)"
systemd-run --quiet --unit=compgate-plant target/systemd/plant/compgate sim --config "$work/compgate.toml"
until_s 60 bash -c "journalctl -u compgate -o cat | grep -q 'device link up again'" &&
    ok "device back is logged" || bad "device back is logged" "$(journal | tail -3)"

# ---- reload: a bad config fails `systemctl reload` (validated in the unit's
# sandbox), the running gateway keeps its config; a good one is taken without a restart
cp /etc/compgate/compgate.toml "$work/good.toml"
sed -i 's/^poll_interval_s = 0.5/poll_interval_s = -1/' /etc/compgate/compgate.toml
if systemctl reload compgate 2>/dev/null; then
    bad "a bad config fails systemctl reload" "reload succeeded"
else
    ok "a bad config fails systemctl reload"
fi
journalctl -u compgate -o cat | grep -q "devices.ain1.poll_interval_s" &&
    ok "the journal names the bad key" || bad "the journal names the bad key" "$(journal | tail -5)"
[[ $(prop MainPID) == "$pid" && $(systemctl is-active compgate) == active ]] &&
    ok "still running after the refused reload" || bad "still running after the refused reload" "pid $pid -> $(prop MainPID)"
sed 's/^poll_interval_s = 0.5/poll_interval_s = 0.25/' "$work/good.toml" >/etc/compgate/compgate.toml
if systemctl reload compgate && until_s 30 bash -c "journalctl -u compgate -o cat | grep -q 'configuration reloaded'"; then
    ok "a good config is reloaded"
else
    bad "a good config is reloaded" "$(journal | tail -5)"
fi
[[ $(prop MainPID) == "$pid" ]] && ok "reloaded in the same process" || bad "reloaded in the same process" "pid $pid -> $(prop MainPID)"

# ---- serial ports: a UART of an allowed driver group opens; a port of a group the
# unit does not list (virtio's hvc console) is refused by the device policy, with the
# hint, until a drop-in allows it, as docs/deployment.md says
chmod 666 /dev/hvc0 # so the device policy, not the tty group, is what refuses it
rtu_device() { # rtu_device NAME PATH
    cat <<EOF

[devices.$1]
transport = "rtu"
serial_path = "$2"
unit_id = 1
timeout_s = 0.2
retries = 0
poll_interval_s = 1.0

[channels.T_$1]
device = "$1"
register = "input"
address = 0
data_type = "u16"
scaling = { kind = "transmitter", adc_full_scale_counts = 4095, adc_full_scale_ma = 24.0, range_min_degc = -50.0, range_max_degc = 150.0 }
EOF
}
{ rtu_device uart /dev/ttyS1; rtu_device hvc /dev/hvc0; } >>/etc/compgate/compgate.toml
systemctl reload compgate || bad "serial devices reload" "$(journal | tail -5)"
# serial_down NAME [journalctl args]: the journal's first "link down" line of device
# NAME; fails while there is none.
serial_down() {
    local name=$1
    shift
    local line
    # Tested for a line, not by the pipe's status: head's early exit fails it (pipefail).
    line=$(journalctl -u compgate -o cat "$@" | grep "device link down" | grep "device=$name " | head -1)
    [[ -n $line ]] && echo "$line"
}
# expect_down CHECK NAME PATTERN [journalctl args]: device NAME goes down within 30 s
# with a line that matches the glob PATTERN.
expect_down() {
    local check=$1 name=$2 pattern=$3 line
    shift 3
    if ! until_s 30 serial_down "$name" "$@"; then
        bad "$check" "$(journal | grep -i "$name" | tail -3)"
    elif line=$(serial_down "$name" "$@") && [[ $line == $pattern ]]; then
        ok "$check"
    else
        bad "$check" "$line"
    fi
}
expect_down "/dev/ttyS1 opens in the sandbox (no module on it: no reply)" uart '*kind="timeout"*'
expect_down "a port of another driver group is refused, naming DeviceAllow=" hvc \
    '*operation not permitted*DeviceAllow=*'
mkdir -p /etc/systemd/system/compgate.service.d
printf '[Service]\nDeviceAllow=char-hvc rw\n' >/etc/systemd/system/compgate.service.d/hvc.conf
systemctl daemon-reload
since=$(date '+%Y-%m-%d %H:%M:%S')
systemctl restart compgate
expect_down "a drop-in with its DeviceAllow= opens it" hvc '*kind="timeout"*' --since "$since"

# ---- a restart on a config that does not validate: ExecStartPre refuses it, systemd
# tries again every RestartSec= (Restart=on-failure), the journal naming the key each
# time, and the gateway starts by itself once the file validates
sed 's/^poll_interval_s = 0.5/poll_interval_s = -1/' "$work/good.toml" >/etc/compgate/compgate.toml
named() { journalctl -u compgate -o cat | grep -c "devices.ain1.poll_interval_s"; }
n0=$(named)
if systemctl restart compgate 2>/dev/null; then
    bad "a restart on a config that does not validate fails" "it started"
else
    ok "a restart on a config that does not validate fails"
fi
r0=$(prop NRestarts)
# Two tries more, each with its line: NRestarts counts a try before its line is written.
retried() { (($(prop NRestarts) >= r0 + 2 && $(named) >= n0 + 3)); }
if until_s 30 retried && [[ $(prop ActiveState) != failed ]]; then
    ok "systemd tries again every RestartSec=, the journal naming the key each time"
else
    bad "systemd tries again every RestartSec=, the journal naming the key each time" \
        "$(prop ActiveState) after $(prop NRestarts) restarts, key named $(($(named) - n0)) times"
fi
cp "$work/good.toml" /etc/compgate/compgate.toml
if until_s 30 systemctl is-active --quiet compgate; then
    ok "it starts by itself once the config validates"
else
    bad "it starts by itself once the config validates" "$(systemctl status --no-pager compgate | tail -5)"
fi
systemctl restart compgate
pid=$(prop MainPID)

# ---- the watchdog: a gateway that stops answering is killed and restarted, and
# keeps what it recorded
before=$(readings)
r0=$(prop NRestarts)
kill -STOP "$pid"
if until_s 90 bash -c "[[ \$(systemctl show -p NRestarts --value compgate) -gt $r0 && \$(systemctl is-active compgate) == active ]]"; then
    ok "a hung gateway is restarted by the watchdog"
else
    bad "a hung gateway is restarted by the watchdog" "$(systemctl status --no-pager compgate | tail -5)"
fi
journalctl -u compgate -o cat | grep -qi "watchdog timeout" &&
    ok "systemd names the watchdog" || bad "systemd names the watchdog" "$(journalctl -u compgate -o cat | tail -5)"
after=$(readings)
((after >= before)) && ok "nothing recorded is lost ($before readings before, $after after)" ||
    bad "nothing recorded is lost" "$before readings before, $after after"

# ---- the wall clock 400 days ahead: age retention (90 days) never follows it, so
# nothing recorded before goes. Lines are counted: clock steps confuse --since.
upto() { sqlite3 "file:/var/lib/compgate/compgate.db?mode=ro" "SELECT COUNT(*) FROM readings WHERE t_unix_ms <= $1"; }
# Set while the gateway was stopped: a start that far past the newest record waits.
systemctl stop compgate
t_ms=$(sqlite3 "file:/var/lib/compgate/compgate.db?mode=ro" "SELECT max(t_unix_ms) FROM readings")
before=$(upto "$t_ms")
date -s "+400 days" >/dev/null
systemctl start compgate
if until_s 30 bash -c "journalctl -u compgate -p warning -o cat | grep -q 'further past the newest record than retention_days'"; then
    ok "a start 400 days past the newest record is a journal warning"
else
    bad "a start 400 days past the newest record is a journal warning" "$(journal | tail -5)"
fi
sleep 3 # three retention passes
kept=$(upto "$t_ms")
((before > 0 && kept == before)) && ok "a start 400 days ahead deletes nothing ($before readings before, $kept after)" ||
    bad "a start 400 days ahead deletes nothing" "$before readings before, $kept after"
n=$(journalctl -u compgate -o cat | grep -c 'wall clock is back in line')
date -s "-400 days" >/dev/null
if until_s 30 bash -c "(( \$(journalctl -u compgate -o cat | grep -c 'wall clock is back in line') > $n ))"; then
    ok "the clock set right is taken again"
else
    bad "the clock set right is taken again" "$(journal | tail -5)"
fi
# Set by hand while it runs. Counted once a later reading is in: the readings up to
# t_ms may still wait in the recorder's queue (a count right away missed 4 of them).
t_ms=$(($(date +%s%3N) - 1))
until_s 10 bash -c "(( \$(sqlite3 'file:/var/lib/compgate/compgate.db?mode=ro' 'SELECT COUNT(*) FROM readings WHERE t_unix_ms > $t_ms') > 0 ))" ||
    bad "a reading after the mark is recorded" "$(journal | tail -5)"
before=$(upto "$t_ms")
date -s "+400 days" >/dev/null
if until_s 30 bash -c "journalctl -u compgate -p warning -o cat | grep -q 'wall clock stepped ahead'"; then
    ok "a clock step ahead is a journal warning"
else
    bad "a clock step ahead is a journal warning" "$(journal | tail -5)"
fi
sleep 3
kept=$(upto "$t_ms")
((before > 0 && kept == before)) && ok "a clock set 400 days ahead deletes nothing ($before readings before the step, $kept after)" ||
    bad "a clock set 400 days ahead deletes nothing" "$before readings before the step, $kept after"
ahead=$(metric compgate_recorder_clock_ahead_seconds)
awk -v a="$ahead" 'BEGIN { exit !(a > 399 * 86400 && a < 401 * 86400) }' &&
    ok "the metrics say how far the clock is ahead ($ahead s)" || bad "the metrics say how far the clock is ahead" "$ahead s"
date -s "-400 days" >/dev/null

# ---- updating: install.sh run again. The engineer has tuned the installed config
# (edit and reload); the plant's config of the first install, given again, is refused
# with the difference, and nothing is installed or restarted.
sed -i 's/^poll_interval_s = 0.5/poll_interval_s = 0.25/' /etc/compgate/compgate.toml
systemctl reload compgate
cp /etc/compgate/compgate.toml "$work/tuned.toml"
pid=$(prop MainPID)
bin=$(stat -c '%i %Z' /usr/local/bin/compgate)
if ! deploy/install.sh "$work/compgate.toml" >"$work/update.log" 2>&1 &&
    grep -qx -- '+poll_interval_s = 0.5' "$work/update.log" && grep -q -- --replace-config "$work/update.log"; then
    ok "a config that differs from the installed one is refused, with the diff"
else
    bad "a config that differs from the installed one is refused, with the diff" "$(tail -5 "$work/update.log")"
fi
cmp -s "$work/tuned.toml" /etc/compgate/compgate.toml && [[ $(stat -c '%i %Z' /usr/local/bin/compgate) == "$bin" && $(prop MainPID) == "$pid" ]] &&
    ok "installed config, binary and process stay as they were" ||
    bad "installed config, binary and process stay as they were" "pid $pid -> $(prop MainPID); $(diff "$work/tuned.toml" /etc/compgate/compgate.toml | head -3)"
# The update without CONFIG.toml, over an older binary (this one with a byte appended)
# and a unit edited in full (as by systemctl edit --full).
cp /usr/local/bin/compgate "$work/older" && echo >>"$work/older" && install -m 0755 "$work/older" /usr/local/bin/compgate
sed 's/^RestartSec=2s/RestartSec=3s/' deploy/compgate.service >/etc/systemd/system/compgate.service && systemctl daemon-reload
if deploy/install.sh >"$work/update.log" 2>&1 && cmp -s "$work/tuned.toml" /etc/compgate/compgate.toml &&
    cmp -s "$work/older" /usr/local/bin/compgate.prev && [[ $(prop MainPID) != "$pid" ]]; then
    ok "an update without CONFIG.toml runs on the installed config, the binary it replaced kept as compgate.prev"
else
    bad "an update without CONFIG.toml runs on the installed config, the binary it replaced kept as compgate.prev" "$(tail -5 "$work/update.log")"
fi
if grep -qx 'RestartSec=3s' /etc/compgate/compgate.service.* && cmp -s deploy/compgate.service /etc/systemd/system/compgate.service &&
    [[ -e /etc/systemd/system/compgate.service.d/hvc.conf && -z $(find /etc/systemd/system -name 'compgate.service?*' ! -name compgate.service.d) ]]; then
    ok "the edited unit is kept as /etc/compgate/compgate.service.<date-time>, the drop-in stays"
else
    bad "the edited unit is kept as /etc/compgate/compgate.service.<date-time>, the drop-in stays" "$(ls /etc/compgate /etc/systemd/system | tr '\n' ' ')"
fi
# A relative CONFIG.toml and --replace-config: tests/deploy.rs.
# A database root made (a `compgate run` by hand): validated as the user compgate, it
# stops the update before anything is installed; the service runs on.
db=/var/lib/compgate/compgate.db
pid=$(prop MainPID)
bin=$(stat -c '%i %Z' /usr/local/bin/compgate)
chown root:root "$db" && chmod 0644 "$db"
if ! deploy/install.sh >"$work/update.log" 2>&1 &&
    grep -q "recorder.path: $db: the database is not writable: Permission denied" "$work/update.log" &&
    grep -q "does not validate: nothing installed" "$work/update.log"; then
    ok "a database the user compgate cannot write fails validation, naming it"
else
    bad "a database the user compgate cannot write fails validation, naming it" "$(tail -5 "$work/update.log")"
fi
[[ $(stat -c '%i %Z' /usr/local/bin/compgate) == "$bin" && $(prop MainPID) == "$pid" && $(systemctl is-active compgate) == active ]] &&
    ok "nothing installed: the service runs on" || bad "nothing installed: the service runs on" "pid $pid -> $(prop MainPID) $(systemctl is-active compgate)"
chown compgate:compgate "$db" && chmod 0600 "$db"
systemctl is-active --quiet compgate || { systemctl reset-failed compgate; systemctl restart compgate; }

# ---- a clean stop
if systemctl stop compgate; then ok "systemctl stop"; else bad "systemctl stop" "$(journal | tail -5)"; fi
[[ $(prop Result) == success && $(prop ExecMainStatus) == 0 ]] &&
    ok "stopped cleanly (exit 0)" || bad "stopped cleanly" "Result=$(prop Result) status=$(prop ExecMainStatus)"
journal | tail -20 | grep -q "gateway stopped" && ok "the journal says it stopped" || bad "the journal says it stopped" "$(journal | tail -3)"
ic=$(sqlite3 /var/lib/compgate/compgate.db "PRAGMA integrity_check")
[[ $ic == ok ]] && ok "database intact after the kill and the stop" || bad "database intact" "$ic"

((failed == 0)) || journalctl -u compgate -u compgate-plant --no-pager | tail -80
echo "SD-RESULT: $passed passed, $failed failed"
