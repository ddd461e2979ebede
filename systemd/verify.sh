#!/bin/sh
# Checks the units: `systemd-analyze verify` and the offline security score of exocald.service.
#
# Usage: systemd/verify.sh [path/to/exocald]   (default: target/release/exocald, then debug)
# verify insists that ExecStart's binary exists, so the unit is checked from a temporary copy
# whose ExecStart points at the built binary; everything else is the shipped file.
# Fails if verify reports anything or the exposure is above 1.5.
set -eu
here=$(cd "$(dirname "$0")" && pwd)
bin=${1:-}
if [ -z "$bin" ]; then
    for c in "${CARGO_TARGET_DIR:-$here/../target}/release/exocald" "${CARGO_TARGET_DIR:-$here/../target}/debug/exocald"; do
        [ -x "$c" ] && bin=$c && break
    done
fi
[ -n "$bin" ] && [ -x "$bin" ] || { echo "verify.sh: build exocald first (cargo build -p exocald)" >&2; exit 66; }
bin=$(cd "$(dirname "$bin")" && pwd)/$(basename "$bin")
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
sed "s|/usr/bin/exocald|$bin|" "$here/exocald.service" > "$tmp/exocald.service"
out=$(systemd-analyze verify "$tmp/exocald.service" 2>&1) || { echo "$out" >&2; exit 1; }
[ -z "$out" ] || { echo "verify warnings:" >&2; echo "$out" >&2; exit 1; }
echo "systemd-analyze verify: ok"
systemd-analyze security --offline=yes "$tmp/exocald.service" > "$tmp/security.txt" 2>&1 || true
grep -E '✗|Overall' "$tmp/security.txt"
score=$(sed -n 's/.*Overall exposure level for [^:]*: \([0-9.]*\).*/\1/p' "$tmp/security.txt")
[ -n "$score" ] || { cat "$tmp/security.txt" >&2; exit 1; }
awk -v s="$score" 'BEGIN { exit !(s <= 1.5) }' || { echo "exposure $score > 1.5" >&2; exit 1; }
echo "exposure $score <= 1.5: ok"
# With the live view's drop-in (exocald-live.conf): appended to the unit, its [Service] lines
# merge as a drop-in's do.
mkdir "$tmp/live"
cat "$tmp/exocald.service" "$here/exocald-live.conf" > "$tmp/live/exocald.service"
out=$(systemd-analyze verify "$tmp/live/exocald.service" 2>&1) || { echo "$out" >&2; exit 1; }
live=$(systemd-analyze security --offline=yes "$tmp/live/exocald.service" 2>&1 | sed -n 's/.*Overall exposure level for [^:]*: \([0-9.]*\).*/\1/p')
echo "exposure with the live view's drop-in (exocald-live.conf): $live"
