#!/usr/bin/env python3
"""Writes the LAS files the reader's tests read, with the standard's byte layout spelled out
here field by field (not with lsqsurf's writer), and with header choices lsqsurf's writer does
not make: variable-length records before the points, padding after them, georeferenced
coordinates, extra bytes per point (in the 1.4 file described by an Extra Bytes record: a
scaled and offset unsigned short "Amplitude", a signed short "Deviation (dB)" and two
undocumented bytes), a 1.4 file whose legacy count is 0, 8-bit colour in the 16-bit fields,
withheld and noise points.

Point i of every file: X = x0 + 0.25 i, Y = y0 + 0.5 (i mod 10), Z = 100 + 0.01 i (units of
the file), intensity 100 i, classification 2 (ground) but 7 (noise) where i mod 10 == 3, and the
withheld flag on point 42; in the 1.4 file Amplitude 1.5 i + 2 (stored 3 i, scale 0.5, offset 2)
and Deviation -i. The tests check these formulas.

    python3 tests/data/las/make_las.py tests/data/las
"""
import struct
import sys
from pathlib import Path

N = 100
# (name, minor version, point format, record length, x0, y0, colour) — colour "16" stores
# c * 257, "8" stores c as it is; c = (i * 2) % 256, (255 - i) % 256, (i * 7) % 256.
FILES = [
    ("utm_1_2_format1.las", 2, 1, 28, 500000.0, 4000000.0, None),
    ("local_1_3_format2.las", 3, 2, 26, 10.0, 20.0, "16"),
    ("extra_1_4_format8.las", 4, 8, 38 + 6, 1.5, -2.5, "8"),
]
HEADER_SIZE = {2: 227, 3: 235, 4: 375}


def colour(i):
    return ((i * 2) % 256, (255 - i) % 256, (i * 7) % 256)


def point_record(i, fmt, length, x0, y0, scale, offset, depth, described):
    x = x0 + 0.25 * i
    y = y0 + 0.5 * (i % 10)
    z = 100 + 0.01 * i
    ints = [round((v - o) / s) for v, o, s in zip((x, y, z), offset, scale)]
    cls = 7 if i % 10 == 3 else 2
    withheld = i == 42
    rec = struct.pack("<iiiH", *ints, 100 * i)
    if fmt < 6:
        rec += struct.pack("<BBbBH", 0x09, cls | (0x80 if withheld else 0), 0, 0, 1)
        if fmt in (1, 3):
            rec += struct.pack("<d", 1000.0 + i)
    else:
        rec += struct.pack("<BBBBhHd", 0x11, 0x04 if withheld else 0, cls, 0, 0, 1, 1000.0 + i)
    if fmt in (2, 3, 5, 7, 8, 10):
        c = colour(i)
        rec += struct.pack("<HHH", *[(v * 257 if depth == "16" else v) for v in c])
    if fmt in (8, 10):
        rec += struct.pack("<H", 4000 + i)  # NIR.
    if described:
        rec += struct.pack("<Hh", 3 * i, -i)
    rec += b"\xab" * (length - len(rec))  # Extra bytes (undescribed).
    assert len(rec) == length
    return rec


def vlr(user, record_id, payload, description):
    return struct.pack("<H16sHH32s", 0, user.encode(), record_id, len(payload), description.encode()) + payload


def extra_bytes_field(data_type, options, name, scale=0.0, offset=0.0):
    """One 192-byte descriptor of the LAS 1.4 Extra Bytes record."""
    d = struct.pack("<2xBB32s4x", data_type, options, name.encode())
    d += bytes(24) + bytes(24) + bytes(24)  # No data, min, max (with their deprecated room).
    d += struct.pack("<d16xd16x", scale, offset)
    d += b"lsqsurf tests".ljust(32, b"\0")
    assert len(d) == 192
    return d


def write(path, minor, fmt, length, x0, y0, depth):
    scale = (0.01, 0.01, 0.001)
    offset = (round(x0), round(y0), 0.0)
    vlrs = vlr("LASF_Projection", 34735, struct.pack("<8H", 1, 1, 0, 1, 3072, 0, 1, 32633), "GeoKeyDirectory")
    described = minor >= 4
    if described:
        fields = extra_bytes_field(3, 0x18, "Amplitude", 0.5, 2.0) + extra_bytes_field(4, 0, "Deviation (dB)")
        fields += extra_bytes_field(0, 2, "")
        vlrs += vlr("LASF_Spec", 4, fields, "Extra Bytes Record")
    header_size = HEADER_SIZE[minor]
    padding = 2  # Some writers leave bytes between the records and the points.
    data_offset = header_size + len(vlrs) + padding
    points = b"".join(point_record(i, fmt, length, x0, y0, scale, offset, depth, described) for i in range(N))
    xs = [x0 + 0.25 * i for i in range(N)]
    ys = [y0 + 0.5 * (i % 10) for i in range(N)]
    zs = [100 + 0.01 * i for i in range(N)]
    legacy = 0 if fmt >= 6 else N
    h = b"LASF"
    h += struct.pack("<HH", 7, 0)  # File source id, global encoding.
    h += b"\x01" * 16  # GUID.
    h += struct.pack("<BB", 1, minor)
    h += b"make_las.py".ljust(32, b"\0")
    h += b"lsqsurf tests independent writer".ljust(32, b"\0")
    h += struct.pack("<HH", 200, 2024)
    h += struct.pack("<HIIBHI", header_size, data_offset, 2 if described else 1, fmt, length, legacy)
    h += struct.pack("<5I", legacy, 0, 0, 0, 0)
    h += struct.pack("<3d", *scale) + struct.pack("<3d", *offset)
    h += struct.pack("<6d", max(xs), min(xs), max(ys), min(ys), max(zs), min(zs))
    if minor >= 3:
        h += struct.pack("<Q", 0)
    if minor >= 4:
        h += struct.pack("<QIQ", 0, 0, N) + struct.pack("<15Q", N, *([0] * 14))
    assert len(h) == header_size, (len(h), header_size)
    Path(path).write_bytes(h + vlrs + b"\0" * padding + points)


def main():
    out = Path(sys.argv[1] if len(sys.argv) > 1 else ".")
    for name, minor, fmt, length, x0, y0, depth in FILES:
        write(out / name, minor, fmt, length, x0, y0, depth)


if __name__ == "__main__":
    main()
