#!/bin/bash
# Runs inside the power-loss VM (tests/powerloss/run.sh): this machine's root under a
# tmpfs overlay, the test's ext4 disk at /data, a tmpfs at /run.
# Usage: guest.sh PHASE CHECKOUT
#   1: record for RECORD_S, write a model with calibrate, cut the power about 1 s later
#   2: check what the disk holds after the cut; restart the gateway
set -u
P=$1
W=$2/target/powerloss
CG=$W/compgate
CFG=$W/gw.toml
DB=/data/rec/compgate.db
OUT=/data/out/model.toml
RECORD_S=15
COMMIT_INTERVAL_MS=500
export RUST_LOG=info
ms() { date +%s%3N; }
newest() { sqlite3 -readonly "$DB" 'SELECT max(t_unix_ms) FROM readings' 2>/dev/null; }
# wait_for SECONDS COMMAND...: until COMMAND succeeds; false if it never did.
wait_for() {
    local end=$(($(ms) + $1 * 1000))
    shift
    until "$@"; do
        (($(ms) < end)) || return 1
        sleep 0.2
    done
}
listening() { (exec 3<>/dev/tcp/127.0.0.1/$1) 2>/dev/null; }
# start_gateway N: a broker with a subscriber, the simulated plant, then the gateway;
# its log prefixed GWN on the console and kept in /run/gwN.log. The subscriber prints
# each message it gets as "PL-MSG: topic t_unix_ms" on the console, which the host
# keeps across the cut (run.sh counts what boot 2 published again).
start_gateway() {
    /usr/sbin/mosquitto -p 18830 >"/run/mosquitto$1.log" 2>&1 &
    wait_for 20 listening 18830 || echo "PL-NOTE: the broker does not listen"
    mosquitto_sub -p 18830 -q 1 -v -t 'compgate/#' |
        sed -un 's/^\([^ ]*\) .*"t_unix_ms":\([0-9]*\).*/PL-MSG: \1 \2/p' |
        tee "/run/msgs$1.log" >/dev/console &
    "$CG" sim --config "$CFG" >"/run/sim$1.log" 2>&1 &
    wait_for 20 listening 15021 || echo "PL-NOTE: the simulated plant does not listen"
    "$CG" run --config "$CFG" > >(tee "/run/gw$1.log" | sed -u "s/^/GW$1: /" >/dev/console) 2>&1 &
    GW=$!
}

case $P in
1)
    echo 1 >/proc/sys/kernel/sysrq
    mkdir -p /data/rec /data/out
    t0=$(ms)
    start_gateway 1
    recorded() { [[ -n $(newest) ]]; }
    wait_for 30 recorded || echo "PL-NOTE: no reading recorded after 30 s"
    left=$((RECORD_S * 1000 - ($(ms) - t0) - 1000))
    ((left > 0)) && sleep "$((left / 1000)).$(printf %03d $((left % 1000)))"
    "$CG" calibrate --data "$W/m.csv" --out /run/model.toml >/dev/null 2>&1
    if ! "$CG" calibrate --data "$W/m.csv" --out "$OUT" >/run/calibrate.log 2>&1; then
        echo "PL-NOTE: calibrate failed: $(tail -1 /run/calibrate.log)"
    fi
    echo "PL-BOOT1: calibrate printed: $(tail -1 /run/calibrate.log)"
    sleep 1
    last=$(newest)
    echo "PL-BOOT1: recorded $(sqlite3 -readonly "$DB" 'SELECT count(*) FROM readings' 2>&1) readings in $((($(ms) - t0) / 1000)) s, the newest ${last:+$(($(ms) - last)) ms ago}"
    # The line boot 2 compares with: the time of the cut, the model's size and sum.
    echo "PL-CUT: $(ms) $(wc -c </run/model.toml) $(sha256sum </run/model.toml | cut -d' ' -f1)"
    echo b >/proc/sysrq-trigger
    sleep 10
    echo "PL-ERROR: still running after the power cut"
    ;;
2)
    read -r _ cut size sum <"$W/boot1.txt"
    passed=0 failed=0
    check() { # check OK NAME DETAIL
        if [[ $1 == 0 ]]; then
            passed=$((passed + 1))
            echo "PL-CHECK: ok: $2: $3"
        else
            failed=$((failed + 1))
            echo "PL-CHECK: FAILED: $2: $3"
        fi
    }
    ls -la /data/rec /data/out
    if [[ -e $DB ]]; then
        integrity=$(sqlite3 "$DB" 'PRAGMA integrity_check' 2>&1 | head -3 | tr '\n' ' ')
    else
        integrity="no database file"
    fi
    [[ $integrity == "ok " ]]
    check $? "the database is intact after the power cut" "integrity_check: $integrity"

    last=$(newest)
    if [[ -n $last ]]; then
        lag=$((cut - last))
        n=$(sqlite3 -readonly "$DB" 'SELECT count(*) FROM readings')
        ((lag <= COMMIT_INTERVAL_MS + 1000))
        check $? "readings lost at most commit_interval_s + 1 s" \
            "the newest of $n readings is $lag ms before the cut (at most $((COMMIT_INTERVAL_MS + 1000)))"
    else
        check 1 "readings lost at most commit_interval_s + 1 s" "no reading kept"
    fi
    echo "PL-INFO: NC jobs kept: $(sqlite3 -readonly "$DB" "SELECT count(*) || coalesce(', the newest ' || ($cut - max(t_unix_ms)) || ' ms before the cut', '') FROM jobs" 2>&1)"

    if [[ -e $OUT ]]; then
        have="$(wc -c <"$OUT") bytes, sha256 $(sha256sum <"$OUT" | cut -c1-16)"
    else
        have="missing"
    fi
    [[ -e $OUT && $(wc -c <"$OUT") == "$size" && $(sha256sum <"$OUT" | cut -d' ' -f1) == "$sum" ]]
    check $? "the model calibrate wrote 1 s before the cut is complete" \
        "$OUT: $have; written: $size bytes, sha256 ${sum:0:16}"

    t2=$(ms)
    start_gateway 2
    after() { [[ $(newest) -gt $t2 ]]; }
    wait_for 30 after
    check $? "the gateway starts again and records" \
        "$(sqlite3 -readonly "$DB" "SELECT count(*) FROM readings WHERE t_unix_ms > $t2") readings since its start"
    # The outbox's backlog is out (run.sh compares it with boot 1's) once a message
    # recorded after this start arrived.
    published() { awk -v t="$t2" '$3 > t { f = 1 } END { exit !f }' /run/msgs2.log; }
    wait_for 30 published || echo "PL-NOTE: no message recorded in boot 2 reached the subscriber"

    # A disk error: ext4 (errors=remount-ro) turns the file system read-only under the
    # running gateway. Its commit error names that, not only "disk I/O error".
    echo 1 >/sys/fs/ext4/vda/trigger_fs_error
    named() { grep -q 'recorder commit failed.*read-only' /run/gw2.log; }
    wait_for 10 named
    check $? "a file system gone read-only is named in the recorder's error" \
        "$(grep -m1 -o 'recorder commit failed.*' /run/gw2.log | cut -c1-400)"
    kill -TERM "$GW"
    wait "$GW" 2>/dev/null
    echo "PL-RESULT: $passed passed, $failed failed"
    ;;
esac
