"""Prints every signal of a DBC as cantools reads it, one tab-separated line each:

frame id (hex), extended, message, length, signal, start, length, byte order, signed, scale,
offset, minimum, maximum, unit, multiplexing (`M`, `m<value>` or `-`), VAL_ entries (`raw=name`
joined by `;`). Floats are printed with repr(), so they parse back to the same double.
"""
import sys

import cantools

db = cantools.database.load_file(sys.argv[1])
for m in db.messages:
    for s in m.signals:
        if s.is_multiplexer:
            mux = "M"
        elif s.multiplexer_ids:
            mux = ";".join(f"m{v}" for v in s.multiplexer_ids)
        else:
            mux = "-"
        choices = ";".join(f"{raw}={name}" for raw, name in (s.choices or {}).items())
        fields = [f"{m.frame_id:x}", m.is_extended_frame, m.name, m.length, s.name, s.start,
                  s.length, s.byte_order, s.is_signed, repr(s.scale), repr(s.offset),
                  repr(s.minimum), repr(s.maximum), s.unit or "", mux, choices]
        print("\t".join(str(f) for f in fields))
