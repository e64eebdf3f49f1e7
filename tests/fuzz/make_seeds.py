#!/usr/bin/env python3
"""Writes the seed corpora of the fuzz targets (tests/fuzz/corpus/<target>/) from files the
project writes. Run from the repository root after building the tools (docs/fuzzing.md):

    cargo build -p sim --bin simrobot -p comanip-calib --bin comanip-calib
    B=$CARGO_TARGET_DIR/debug   # or target/debug
    $B/simrobot generate --out /tmp/seeds/sim --cycles 1
    $B/comanip-calib generate --dataset /tmp/seeds/ds.json --truth /tmp/seeds/truth.json
    $B/comanip-calib calibrate --dataset /tmp/seeds/ds.json --out /tmp/seeds/result.json
    python3 tests/fuzz/make_seeds.py /tmp/seeds

Seeds are kept small (excerpts): the whole corpus stays a few hundred KB.
"""
import json
import os
import shutil
import struct
import sys

SRC = sys.argv[1]
OUT = "tests/fuzz/corpus"


def put(target, name, data):
    d = os.path.join(OUT, target)
    os.makedirs(d, exist_ok=True)
    if isinstance(data, str):
        data = data.encode()
    with open(os.path.join(d, name), "wb") as f:
        f.write(data)


for t in os.listdir(OUT) if os.path.isdir(OUT) else []:
    shutil.rmtree(os.path.join(OUT, t))

# --- candump: excerpts of simrobot's bus log, and hand-written odd lines --------------------
log = open(os.path.join(SRC, "sim/bus.log")).read().splitlines()
put("candump", "sim-start.log", "\n".join(log[:200]) + "\n")
mid = len(log) // 2
put("candump", "sim-mid.log", "\n".join(log[mid:mid + 400]) + "\n")
put("candump", "odd-lines.log", "\n".join([
    "(1700000000.000000) vcan0 080#01",
    "(1700000000.000100) vcan0 181#0000000000000000 R",
    "(1700000000.000200) vcan0 182#00.00.00.00.00.00.00.00 T",
    "(1700000000.000300) vcan0 183#R",
    "(1700000000.000400) vcan0 183#R8",
    "(1700000000.000500) vcan0 12345678#DEADBEEF",
    "(1700000000.000600) vcan0 123##1AA",
    "(1700000000.000700) vcan0 20000004#0000000000000000",
    "# a comment",
    "",
    "(1700000000.000800) vcan0 701#05",
    "(1700000000.000900) vcan0 083#0573010000000000",
    "(99999999999999.999999) vcan0 080#02",
]) + "\n")

# --- acquisition: the bus log as operations (comanip_fuzz::acquisition) -----------------------
def ops_from_log(lines, max_cycles):
    out = bytearray()
    last_us = None
    cycles = 0
    in_cycle = False
    for line in lines:
        parts = line.split()
        if len(parts) < 3 or "#" not in parts[2]:
            continue
        ts = parts[0].strip("()")
        s, us = ts.split(".")
        t = int(s) * 1_000_000 + int(us)
        ident, data = parts[2].split("#", 1)
        if data.startswith("#") or data.startswith("R"):
            continue
        step = 0 if last_us is None else min(31, max(0, (t - last_us) // 50))
        last_us = t
        cid = int(ident, 16)
        if cid == 0x080:
            if in_cycle:
                out += bytes([4 | (step << 3), 0])
                step = 0
                cycles += 1
                if cycles >= max_cycles:
                    break
            out += bytes([0 | (step << 3)])
            in_cycle = True
            continue
        payload = bytes.fromhex(data.replace(".", ""))
        op = 1 if in_cycle else 2
        out += bytes([op | (step << 3)]) + struct.pack("<I", cid) + bytes([0, len(payload)]) + payload.ljust(8, b"\0")
    return bytes(out)

put("acquisition", "sim-start.bin", ops_from_log(log, 300))
# The instrument inside: a stretch long enough for the detector to decide (about 1500 cycles).
put("acquisition", "sim-mid.bin", ops_from_log(log[mid - 3000:], 1500))
hb = b"".join(bytes([7, 2, n, 0]) + b"\0" * 7 for n in range(3))
cyc = bytes([0]) + b"".join(bytes([6, 0, n]) + struct.pack("<ii", 1000 * n, -1000 * n) for n in range(3)) + bytes([4 | (20 << 3), 0])
put("acquisition", "heartbeats-and-cycles.bin", hb + cyc * 20)
put("acquisition", "emcy-and-clock-jump.bin", hb + cyc * 3 + bytes([6, 3, 1]) + bytes(8) + cyc + bytes([5]) + struct.pack("<Q", 2**64 - 1000) + cyc * 3 + bytes([3]) + cyc)

# --- recording: the fixture cut to its header and first records, and damaged copies ---------
rec = open("controller/tests/fixtures/cycle-v1/fulcrumd-b0ae83fe6f31b62a-0000.rec", "rb").read()
pos = 12
frames = []
while pos + 4 <= len(rec) and len(frames) < 12:
    (n,) = struct.unpack_from("<I", rec, pos)
    frames.append((pos, pos + 4 + n + 4))
    pos += 4 + n + 4
small = rec[: frames[-1][1]]
put("recording", "fixture-head.rec", small)
put("recording", "fixture-cut.rec", small[:-7])
bad_crc = bytearray(small); bad_crc[frames[3][1] - 1] ^= 0xFF
put("recording", "fixture-bad-crc.rec", bytes(bad_crc))
v2 = bytearray(small); v2[10] = 2
put("recording", "fixture-version-2.rec", bytes(v2))
put("recording", "header-only.rec", rec[: frames[0][1]])
put("recording", "preamble-only.rec", rec[:12])

# --- configurations -------------------------------------------------------------------------
put("fulcrumd_toml", "fulcrumd.toml", open("configs/fulcrumd.toml").read())
put("fulcrumd_toml", "small.toml", "[loop]\nperiod_us = 2000\n[detector]\nsample_period_s = 0.002\nmode = \"paper\"\n[bus]\nother_node_ids = [4, 5]\n")
put("simrobot_toml", "simrobot.toml", open("configs/simrobot.toml").read())
put("simrobot_toml", "small.toml", "[scenario]\nseed = 1\ncycles = 4\ninside_s = [4.0, 5.0]\noutside_s = [1.6, 2.2]\n")

# --- calibration files ----------------------------------------------------------------------
ds = json.load(open(os.path.join(SRC, "ds.json")))
ds["observations"] = ds["observations"][:6]
put("calib_json", "dataset.json", json.dumps(ds, indent=1))
put("calib_json", "truth.json", open(os.path.join(SRC, "truth.json")).read())
put("calib_json", "result.json", open(os.path.join(SRC, "result.json")).read())
k = ds["intrinsics"]
lines = {"format": "comanip-shaft-lines", "version": 1, "detector": "ours", "intrinsics": k, "images": [
    {"file": "frame_000000_left.png", "shafts": [{"centreline": [0.6, 0.8, -300.0], "contours": [[0.6, 0.8, -290.0], [0.6, 0.8, -310.0]],
     "ends_px": [[100.0, 300.0], [400.0, 75.0]], "confidence": 0.9}], "detect_ms": 3.5},
    {"file": "frame_000001_left.png", "shafts": [], "error": "unreadable", "detect_ms": 0.0}]}
put("calib_json", "lines.json", json.dumps(lines, indent=1))

# --- camera YAML (the formats parse_intrinsics_yaml reads; the simrobot writer's) ------------
ros = "image_width: 640\nimage_height: 480\ncamera_name: endoscope_left\ncamera_matrix:\n  rows: 3\n  cols: 3\n  data: [320.0, 0.0, 319.5, 0.0, 321.0, 239.5, 0.0, 0.0, 1.0]\ndistortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [-0.1, 0.01, 0.0, 0.0, 0.0]\nrectification_matrix:\n  rows: 3\n  cols: 3\n  data: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]\nprojection_matrix:\n  rows: 3\n  cols: 4\n  data: [320.0, 0.0, 319.5, 0.0, 0.0, 321.0, 239.5, 0.0, 0.0, 0.0, 1.0, 0.0]\n"
put("camera_yaml", "ros-left.yaml", ros)
put("camera_yaml", "ros-stereo.yaml", ros + "\0" + ros.replace("endoscope_left", "endoscope_right").replace("319.5, 0.0, 0.0, 321.0", "319.5, -1.6, 0.0, 321.0"))
put("camera_yaml", "opencv.yaml", "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 320., 0., 319.5, 0., 321., 239.5, 0., 0., 1. ]\ndistortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n   data: [ -0.1, 0.01, 0., 0., 0. ]\n")
put("camera_yaml", "ros-msg.yaml", "header:\n  seq: 0\nheight: 480\nwidth: 640\ndistortion_model: plumb_bob\nD: [-0.1, 0.01, 0.0, 0.0, 0.0]\nK: [320.0, 0.0, 319.5, 0.0, 321.0, 239.5, 0.0, 0.0, 1.0]\n")

# --- ipc samples (FulcrumSample, 200 bytes each) -----------------------------------------------
def sample(state, seq, health=0, run=0x1234, f=(0.1, 0.2, 0.3)):
    return (struct.pack("<IIQQQII", 1, state, seq, run, 1_000_000 * seq, health, 1 if state == 2 else 0)
            + struct.pack("<3d3d3d3d6d", *f, 1e-4, 2e-4, 0.3, 0.1, 0.2, 0.3, 0.0, 0.6, 0.8, 0.1, -0.2, 0.3, -0.4, 0.5, -0.6)
            + struct.pack("<HHHHII", 100, 128, 300, 0, 1000, 20000))
assert len(sample(1, 0)) == 200
put("ipc_sample", "in-order.bin", sample(1, 0, f=(0, 0, 0)) + sample(2, 1) + sample(2, 2))
put("ipc_sample", "gap-restart-invalid.bin", sample(2, 5) + sample(2, 9) + sample(0, 3, health=0x0402) + sample(1, 0, run=7))

# --- frame headers (72 bytes + payload length) ----------------------------------------------
def header(eyes, w, h, stride, fmt, payload, version=1):
    return struct.pack("<IIQQQIIIIIIQQ", version, 0, 7, 0xABCD, 123456789, 5000, eyes, w, h, stride, fmt, payload, 0) + struct.pack("<I", payload)
put("frame_header", "stereo-rgb.bin", header(2, 640, 480, 1920, 2, 2 * 1920 * 480))
put("frame_header", "mono-gray.bin", header(1, 160, 120, 160, 1, 160 * 120))
put("frame_header", "yuyv-padded.bin", header(1, 320, 240, 704, 3, 704 * 240))

# --- detectors: small images with a dark band (a shaft) on a lighter background --------------
def image(w, h, band):
    px = bytearray()
    for y in range(h):
        for x in range(w):
            d = abs((x - w / 2) * 0.8 + (y - h / 2) * 0.6)
            v = 40 if d < band else 200
            px += bytes([v, v + 10, v + 20 if v < 200 else 230])
    return bytes([w - 1, h - 1, 0, 0]) + bytes(px)
put("detectors", "band-48x40.bin", image(48, 40, 5))
put("detectors", "band-64x64-distorted.bin", bytes([63, 63, 1, 0]) + image(64, 64, 8)[4:])
put("detectors", "flat.bin", bytes([31, 23, 2, 0, 128]))
