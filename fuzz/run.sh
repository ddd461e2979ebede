#!/usr/bin/env bash
# Runs every fuzz target for SECONDS (default 60) each, one after the other (the machine is
# shared: one core per target), and prints libFuzzer's final line per target.
# Usage: fuzz/run.sh [SECONDS] [TARGET...]
#   FUZZ_RUNS=N   stop each target after N executions instead (SECONDS still caps it)
#   (-timeout=10: an input that takes over 10 s is a finding, as a crash is)
#   FUZZ_FLAGS    cargo-fuzz build flags (default `-s none -O`: no sanitizer — the crates are
#                 `#![deny(unsafe_code)]` or safe Rust over safe dependencies — for ~3x the
#                 executions per second; use `FUZZ_FLAGS=-O` for AddressSanitizer)
# Needs the nightly toolchain and cargo-fuzz (`cargo install cargo-fuzz`).
set -euo pipefail
cd "$(dirname "$0")"
secs="${1:-60}"
shift || true
targets=("$@")
if [ ${#targets[@]} -eq 0 ]; then
  targets=(decode transfer config scenario offline_mcap offline_candump offline_csv recover)
fi
mkdir -p logs
status=0
for t in "${targets[@]}"; do
  mkdir -p "corpus/$t"
  log="logs/$t.log"
  # shellcheck disable=SC2086
  if cargo +nightly fuzz run ${FUZZ_FLAGS:--s none -O} "$t" "corpus/$t" -- \
      -max_total_time="$secs" ${FUZZ_RUNS:+-runs="$FUZZ_RUNS"} -rss_limit_mb=2048 -timeout=10 >"$log" 2>&1; then
    echo "$t: ok: $(grep -E '^(#[0-9]+|Done)' "$log" | tail -1)"
  else
    echo "$t: FAILED (see fuzz/$log and fuzz/artifacts/$t/)"
    status=1
  fi
done
exit $status
