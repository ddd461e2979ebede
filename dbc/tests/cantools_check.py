"""Decodes frames encoded by Rust with cantools and compares every signal with what Rust meant.

Input lines: `<id hex> <data hex> <name>=<value>,...`, value a float or `Invalid`.
Exit status 0 only if every frame decodes, names the same signals, and agrees within half a step.
"""
import sys

import cantools

db = cantools.database.load_file(sys.argv[1])
bad = 0
n = 0
for line in open(sys.argv[2]):
    ident, data, expected = line.split()
    ident = int(ident, 16)
    data = bytes.fromhex(data)
    want = dict(kv.split("=") for kv in expected.split(","))
    msg = db.get_message_by_frame_id(ident)
    got = msg.decode(data, decode_choices=True, scaling=True)
    n += 1
    if set(got) != set(want):
        print(f"{msg.name}: signals {sorted(got)} != {sorted(want)}")
        bad += 1
        continue
    for name, value in want.items():
        sig = msg.get_signal_by_name(name)
        g = got[name]
        if value == "Invalid":
            ok = str(g) == "Invalid"
        else:
            g = float(getattr(g, "value", g)) if not isinstance(g, (int, float)) else float(g)
            if sig.choices and not isinstance(got[name], (int, float)):
                g = float(got[name].value) * sig.scale + sig.offset
            ok = abs(g - float(value)) <= sig.scale / 2 + 1e-12
        if not ok:
            print(f"{msg.name}.{name}: cantools {got[name]!r}, rust {value}")
            bad += 1
print(f"cantools checked {n} frames, {bad} mismatches")
sys.exit(1 if bad or n == 0 else 0)
