#!/usr/bin/env python3
"""The bad-input campaign of issue 34, reproducible: damaged session logs and oversized text
inputs against an `exocald` binary, with exit codes, peak RSS and time per run.

Usage: fuzz/campaign.py EXOCALD DEMO.mcap WORKDIR [--seed N] [--big]

DEMO.mcap is a finished session log (`exocald demo --speed 1000000 -o DIR` writes one). From it,
with a seeded generator, the script writes 284 mutated logs — 100 single bit flips, 60
truncations, 60 insertions of 1-16 random bytes, 64 overwrites of 8 bytes (lengths and sizes
set to 0xFF.., random or 0) — and runs `exocald offline` and `exocald recover` on each, then the
special inputs: the log's first 34 KB (unfinished) and 41 mutations of it, its candump export
with the first 3,000 lines (every node's first 0.3 s) at time 0, CSV samples of 200,000 rows
(and, with --big, 5,000,000 rows): the log's aligned samples repeated, time running on, when
the mcap Python packages are there (tests/requirements.txt), else a synthetic sweep. Every run has a 300-s
timeout and a 4 GiB address-space cap (`prlimit --as`), so a runaway shows as 134 (abort) or as
a timeout instead of taking the machine. Prints one line per class: exit codes with counts,
the largest peak RSS and the longest time.
"""

import argparse
import collections
import json
import math
import os
import random
import subprocess
import sys

CAP_BYTES = 4 << 30
TIMEOUT_S = 300


def run(exe, args, work):
    """Exit code (or 'timeout'), peak RSS (MiB), wall time (s), last stderr line."""
    timing = os.path.join(work, "time.txt")
    cmd = ["prlimit", f"--as={CAP_BYTES}", "/usr/bin/time", "-o", timing, "-f", "%e %M",
           exe] + args
    try:
        p = subprocess.run(cmd, capture_output=True, timeout=TIMEOUT_S, cwd=work)
    except subprocess.TimeoutExpired:
        return "timeout", float("nan"), TIMEOUT_S, ""
    code = p.returncode
    wall, rss = float("nan"), float("nan")
    try:
        with open(timing) as f:
            lines = f.read().strip().splitlines()
        # /usr/bin/time says "Command terminated by signal N" first when the child was killed.
        for line in lines:
            if line.startswith("Command terminated by signal"):
                code = 128 + int(line.split()[-1])
        wall, kb = lines[-1].split()
        wall, rss = float(wall), int(kb) / 1024
    except (OSError, ValueError, IndexError):
        pass
    err = p.stderr.decode(errors="replace").strip().splitlines()
    # A panic's or an abort's own line, else the last one (the error exocald names).
    said = [l for l in err if "panicked at" in l or "memory allocation" in l] + err[-1:]
    return code, rss, wall, (said[0] if said else "")


def mutants(data, rng):
    out = []
    for i in range(100):
        b = bytearray(data)
        pos = rng.randrange(len(b))
        b[pos] ^= 1 << rng.randrange(8)
        out.append((f"flip-{i:03}", bytes(b)))
    for i in range(60):
        out.append((f"trunc-{i:03}", data[: rng.randrange(len(data))]))
    for i in range(60):
        pos = rng.randrange(len(data))
        ins = bytes(rng.randrange(256) for _ in range(rng.randint(1, 16)))
        out.append((f"insert-{i:03}", data[:pos] + ins + data[pos:]))
    for i in range(64):
        b = bytearray(data)
        pos = rng.randrange(len(b) - 8)
        fill = [b"\xff" * 8, bytes(rng.randrange(256) for _ in range(8)), b"\x00" * 8][i % 3]
        b[pos : pos + 8] = fill
        out.append((f"overwrite-{i:03}", bytes(b)))
    return out


RANGES_DEG = [(-90, 90), (-120, 30), (-10, 100), (0, 150), (-20, 30), (-30, 40), (-90, 90)]


def csv_rows(path, n):
    """n CSV samples at 100 Hz: every joint sweeping 90 % of its default range (so the
    recording meets the session rules and is calibrated), an arbitrary pose."""
    with open(path, "w") as f:
        f.write("t,q1,q2,q3,q4,q5,q6,q7,x,y,z,qw,qx,qy,qz\n")
        for k in range(n):
            t = k * 0.01
            q = [math.radians((lo + hi) / 2 + 0.45 * (hi - lo) * math.sin((0.3 + 0.07 * j) * t + j))
                 for j, (lo, hi) in enumerate(RANGES_DEG)]
            a = 0.2 * math.sin(0.1 * t)
            f.write(f"{t:.2f}," + ",".join(f"{x:.6f}" for x in q)
                    + f",0.3,0.1,-0.2,{math.cos(a):.9f},{math.sin(a):.9f},0,0\n")


def aligned_samples(log):
    """The demo log's aligned samples (`/aligned`), or None without the mcap Python packages
    (tests/requirements.txt)."""
    try:
        from mcap.reader import make_reader
        from mcap_protobuf.decoder import DecoderFactory
    except ImportError:
        return None
    out = []
    with open(log, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, _, _, m in reader.iter_decoded_messages(topics=["/aligned"]):
            out.append([m.t] + list(m.joints) + list(m.position) + list(m.orientation_wxyz))
    return out


def csv_from(samples, path, n):
    """n CSV rows: the session's aligned samples over and over, time running on (a long
    session of real kinematics, which the pipeline calibrates)."""
    period = samples[1][0] - samples[0][0]
    span = samples[-1][0] - samples[0][0] + period
    with open(path, "w") as f:
        f.write("t,q1,q2,q3,q4,q5,q6,q7,x,y,z,qw,qx,qy,qz\n")
        for k in range(n):
            s = samples[k % len(samples)]
            t = s[0] + (k // len(samples)) * span
            f.write(",".join(repr(x) for x in [t] + s[1:]) + "\n")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("exe")
    ap.add_argument("demo")
    ap.add_argument("work")
    ap.add_argument("--seed", type=int, default=34)
    ap.add_argument("--big", action="store_true")
    a = ap.parse_args()
    exe = os.path.abspath(a.exe)
    os.makedirs(a.work, exist_ok=True)
    work = os.path.abspath(a.work)
    data = open(a.demo, "rb").read()
    rng = random.Random(a.seed)
    results = collections.defaultdict(list)

    def offline(name, path, cls):
        r = run(exe, ["offline", "-i", path, "--report", os.path.join(work, "r.html")], work)
        results[cls].append((name,) + r)

    for name, b in mutants(data, rng):
        path = os.path.join(work, name + ".mcap")
        with open(path, "wb") as f:
            f.write(b)
        cls = name.split("-")[0]
        offline(name, path, "offline " + cls)
        out = os.path.join(work, "recovered.mcap")
        r = run(exe, ["recover", path, out], work)
        results["recover " + cls].append((name,) + r)
        for p in (path, out):
            if os.path.exists(p):
                os.remove(p)

    # The log's first 34 KB (a daemon killed in its first chunk), as it is and with 40 of the
    # mutations above.
    head = data[:34_000]
    for name, b in [("unfinished-34k", head)] + mutants(head, rng)[::7]:
        cut = os.path.join(work, name + "-34k.mcap")
        with open(cut, "wb") as f:
            f.write(b)
        offline(name, cut, "unfinished 34 KB log")
        out = os.path.join(work, "recovered.mcap")
        r = run(exe, ["recover", cut, out], work)
        results["recover unfinished 34 KB log"].append((name,) + r)
        for p in (cut, out):
            if os.path.exists(p):
                os.remove(p)

    export = os.path.join(work, "demo.log")
    run(exe, ["offline", "-i", a.demo, "--report", os.path.join(work, "r.html"),
              "--export-candump", export], work)
    if os.path.exists(export):
        lines = open(export).read().splitlines()
        # The first 3,000 lines (every node's first 0.3 s: enough for a clock fit) at time 0.
        for i in range(3000):
            lines[i] = "(0.000000)" + lines[i][lines[i].index(")") + 1:]
        zero = os.path.join(work, "time0.log")
        with open(zero, "w") as f:
            f.write("\n".join(lines) + "\n")
        offline("time0", zero, "candump at time 0")

    sizes = [200_000] + ([5_000_000] if a.big else [])
    samples = aligned_samples(a.demo)
    for n in sizes:
        path = os.path.join(work, f"rows-{n}.csv")
        if samples:
            csv_from(samples, path, n)
        else:
            csv_rows(path, n)
        offline(f"rows-{n}", path, f"CSV {n:,} rows")
        os.remove(path)

    summary = {}
    for cls, rs in results.items():
        codes = collections.Counter(str(r[1]) for r in rs)
        rss = max((r[2] for r in rs if not math.isnan(r[2])), default=float("nan"))
        wall = max((r[3] for r in rs if not math.isnan(r[3])), default=float("nan"))
        summary[cls] = {"runs": len(rs), "codes": dict(sorted(codes.items())),
                        "max_rss_mib": round(rss, 1), "max_s": round(wall, 2)}
        bad = [r for r in rs if str(r[1]) in ("101", "134", "137", "timeout")]
        print(f"{cls}: {len(rs)} runs, exit {dict(sorted(codes.items()))}, "
              f"peak RSS {rss:.1f} MiB, longest {wall:.2f} s")
        for r in bad[:3]:
            print(f"    {r[0]}: {r[1]}: {r[4][:200]}")
    with open(os.path.join(work, "summary.json"), "w") as f:
        json.dump(summary, f, indent=1)


if __name__ == "__main__":
    sys.exit(main())
