#!/bin/sh
# The daemon against `candump -l` on vcan, run INSIDE the vcan harness (`cargo xtask bench
# --only ingest` calls it as `cargo xtask vcan -- sh benches/ingest.sh ...`). Only /tmp is
# written (the guest's host root is read-only); results go to stdout as one line per run:
#
#   INGEST speed=S hil_wall_s=W hil_sent=N daemon_cpu_s=C daemon_rss_kb=R daemon_exit=E
#          candump_frames=M candump_cpu_s=C2 candump_rss_kb=R2
#   INGEST_MCAP speed=S TOPIC=COUNT ...   (the daemon's log read back; BENCH_PYTHON has `mcap`)
#   SESSION rss_kb=R wall_s=W exit=E window_end_s=T0 verified_s=T1 ...
#
# usage:
#   ingest.sh ref BIN_DIR
#       A CPU-bound reference run (`REF cpu_s=C`), here and (by `load`) in the guest: their ratio
#       is the guest's slowdown, for an estimate of native figures.
#   ingest.sh load BIN_DIR WALL_SECONDS SPEED...
#       For each SPEED: the daemon (`exocald calibrate --dry-run` with the shipped configuration
#       but a collection window far longer than the run, so it only ingests: decode, clock
#       model, MCAP write) and `candump -l` listen on vcan0 while `exocal-hil --speed SPEED`
#       plays WALL_SECONDS × SPEED simulated seconds of the paper scenario; then the daemon gets
#       SIGTERM (it finishes its MCAP, whose `/can/rx` count is the daemon's received frames).
#       The CPU time of each listener is read from /proc just before the hil starts and once it
#       has stopped sending: the difference is what the load cost it.
#   ingest.sh session BIN_DIR
#       One power-up session at speed 1, with the shipped configuration but a 60 s collection
#       window: `exocald calibrate` (pushing to the hil's nodes) under
#       /usr/bin/time (peak RSS), its stderr time-stamped to find the end of the collection
#       window and the moment every node's table was verified.
set -u

here=$(cd "$(dirname "$0")" && pwd)
mode=$1
bin=$2
shift 2
hz=$(getconf CLK_TCK)

# Fresh node keys, passed as the shipped units pass them (the credential `exocal-keys` in
# $CREDENTIALS_DIRECTORY) to the daemon and to the emulated nodes: the bench authenticates its
# transfers as a controller does.
credentials() {
    CREDENTIALS_DIRECTORY=/tmp/ingest-credentials
    export CREDENTIALS_DIRECTORY
    rm -rf "$CREDENTIALS_DIRECTORY"
    (
        umask 077
        mkdir -p "$CREDENTIALS_DIRECTORY"
        for name in Joint1 Joint2 Joint3 Joint4 Joint5 Joint6 Joint7 EndEffector Trigger; do
            echo "$name $(od -An -N16 -tx1 /dev/urandom | tr -d ' \n')"
        done >"$CREDENTIALS_DIRECTORY/exocal-keys"
    )
}

# CPU seconds (user + system) of a live process, from /proc/PID/stat fields 14 and 15.
cpu_s() {
    awk -v hz="$hz" '{ sub(/^.*\) /, ""); printf "%.3f", ($12 + $13) / hz }' "/proc/$1/stat"
}

# Peak RSS (kB) of a live process.
rss_kb() {
    awk '/^VmHWM:/ { print $2 }' "/proc/$1/status"
}

# Waits up to $2 tenths of a second for a file to contain text $3.
wait_for() {
    n=0
    while [ "$n" -lt "$2" ]; do
        grep -q "$3" "$1" 2>/dev/null && return 0
        sleep 0.1
        n=$((n + 1))
    done
    return 1
}

case "$mode" in
ref)
    # A CPU-bound reference (calib-core's LS on 200 samples, 40 processes) to compare this
    # machine with the harness guest: prints `REF cpu_s=C` (user + system, children included).
    t=$( { /usr/bin/time -f "%U %S" sh -c "i=0; while [ \$i -lt 40 ]; do '$bin/examples/export_dataset' --firmware-twin >/dev/null; i=\$((i + 1)); done"; } 2>&1 | tail -n 1)
    echo "REF cpu_s=$(echo "$t" | awk '{ printf "%.3f", $1 + $2 }')"
    ;;
load)
    wall=$1
    shift
    credentials
    config=/tmp/ingest-exocald.toml
    "$bin/exocald" check-config --print-default |
        sed 's/^min_duration_s = .*/min_duration_s = 86000.0/; s/^max_duration_s = .*/max_duration_s = 86400.0/' >"$config"
    sh "$0" ref "$bin"
    for speed in "$@"; do
        w=/tmp/ingest-$speed
        rm -rf "$w"
        mkdir -p "$w/log" "$w/flash" "$w/candump"
        seconds=$(awk -v w="$wall" -v s="$speed" 'BEGIN { print w * s }')
        (cd "$w/candump" && exec candump -l vcan0) &
        cpid=$!
        "$bin/exocald" -c "$config" calibrate -i vcan0 -o "$w/log" --dry-run >"$w/daemon.out" 2>"$w/daemon.err" &
        dpid=$!
        # Both sockets open (the daemon says so when it starts logging).
        wait_for "$w/daemon.err" 100 "logging to" || echo "ingest.sh: the daemon did not start: $(cat "$w/daemon.err")" >&2
        sleep 0.5
        # CPU time spent while the hil plays: after minus before (start-up costs left out).
        dcpu0=$(cpu_s "$dpid" 2>/dev/null || echo nan)
        ccpu0=$(cpu_s "$cpid" 2>/dev/null || echo nan)
        # --linger 0: the hil exits when its motion ends (its nodes would answer on otherwise).
        "$bin/exocal-hil" --iface vcan0 --speed "$speed" --duration "$seconds" --linger 0 \
            --flash-dir "$w/flash" >"$w/hil.out" 2>"$w/hil.err"
        sleep 1
        dcpu=$(awk -v a="$dcpu0" -v b="$(cpu_s "$dpid" 2>/dev/null || echo nan)" 'BEGIN { printf "%.3f", b - a }')
        drss=$(rss_kb "$dpid" 2>/dev/null || echo nan)
        ccpu=$(awk -v a="$ccpu0" -v b="$(cpu_s "$cpid" 2>/dev/null || echo nan)" 'BEGIN { printf "%.3f", b - a }')
        crss=$(rss_kb "$cpid" 2>/dev/null || echo nan)
        kill -TERM "$dpid" 2>/dev/null
        kill -TERM "$cpid" 2>/dev/null
        wait "$dpid"
        dexit=$?
        wait "$cpid"
        sent=$(sed -n 's/.*frames sent \([0-9]*\).*/\1/p' "$w/hil.out" | head -n 1)
        hwall=$(sed -n 's/.*s in \([0-9.]*\) s wall.*/\1/p' "$w/hil.out" | head -n 1)
        cframes=$(cat "$w"/candump/*.log 2>/dev/null | wc -l)
        echo "INGEST speed=$speed hil_wall_s=${hwall:-nan} hil_sent=${sent:-nan}" \
            "daemon_cpu_s=$dcpu daemon_rss_kb=$drss daemon_exit=$dexit" \
            "candump_frames=$cframes candump_cpu_s=$ccpu candump_rss_kb=$crss"
        # The daemon's MCAP log, read back with the python reader: messages per topic.
        for f in "$w"/log/*.mcap; do
            [ -e "$f" ] || continue
            if counts=$("${BENCH_PYTHON:-python3}" "$here/mcap_counts.py" "$f"); then
                echo "INGEST_MCAP speed=$speed ${counts#MCAP }"
            fi
        done
        if [ "$dexit" != 75 ]; then
            echo "ingest.sh: speed $speed: the daemon exited with $dexit, not 75 (interrupted); its stderr ends with:" >&2
            tail -n 5 "$w/daemon.err" >&2
        fi
    done
    ;;
session)
    credentials
    w=/tmp/session
    rm -rf "$w"
    mkdir -p "$w/log" "$w/flash"
    # The shipped configuration with a fixed 60 s collection window (stop-when-good-enough off).
    config=/tmp/session-exocald.toml
    "$bin/exocald" check-config --print-default |
        sed -e 's/^min_duration_s = .*/min_duration_s = 60.0/' \
            -e 's/^stop_at_expected_error/# stop_at_expected_error/' >"$config"
    t0=$(date +%s.%N)
    # Time-stamp every stderr line of the daemon (seconds since t0).
    # (Also shown live on stderr; the daemon is stopped after ${SESSION_LIMIT_S:-900} s.)
    (/usr/bin/time -f "TIME %e %M" timeout "${SESSION_LIMIT_S:-900}" "$bin/exocald" -c "$config" calibrate -i vcan0 -o "$w/log" 2>&1 >"$w/daemon.out"
        echo "EXIT $?") |
        while IFS= read -r line; do
            printf '%s %s\n' "$(date +%s.%N)" "$line" | tee -a "$w/daemon.err" >&2
        done &
    spid=$!
    wait_for "$w/daemon.err" 100 "logging to" || echo "ingest.sh: the daemon did not start" >&2
    sleep 0.5
    # The hil outlives the session: after its motion its nodes keep answering (the table
    # transfers after the window) until the SIGTERM below.
    "$bin/exocal-hil" --iface vcan0 --speed 1 --duration 600 --flash-dir "$w/flash" >"$w/hil.out" 2>"$w/hil.err" &
    hpid=$!
    wait "$spid"
    kill -TERM "$hpid" 2>/dev/null
    wait "$hpid" 2>/dev/null
    rel() { awk -v t0="$t0" '{ printf "%.3f", $1 - t0 }'; }
    # The daemon's own record of the session: its /events, time-stamped in the log (ns).
    for f in "$w"/log/*.mcap; do
        [ -e "$f" ] && "${BENCH_PYTHON:-python3}" "$here/mcap_counts.py" --events "$f" >>"$w/events"
    done
    cat "$w/events" >&2
    ev() { grep -m 1 "$1" "$w/events" | awk -v t0="$t0" '{ printf "%.3f", $2 / 1e9 - t0 }'; }
    window=$(ev "collection done")
    validated=$(ev "held-out pose error")
    verified=$(ev "every node holds its new table")
    time_line=$(grep -m 1 " TIME " "$w/daemon.err")
    exit_code=$(grep -m 1 " EXIT " "$w/daemon.err" | awk '{ print $3 }')
    echo "SESSION exit=${exit_code:-nan} rss_kb=$(echo "$time_line" | awk '{ print $4 }') wall_s=$(echo "$time_line" | awk '{ print $3 }')" \
        "window_end_s=${window:-nan} validated_s=${validated:-nan} verified_s=${verified:-nan}"
    ;;
*)
    echo "usage: ingest.sh load BIN_DIR SECONDS SPEED... | ingest.sh session BIN_DIR" >&2
    exit 2
    ;;
esac
