#!/usr/bin/env python3
"""Line segments of OpenCV's EdgeDrawing (EDLines) and LSD on every PNG of a directory.

The peers of `comanip-bench shaft` (docs/detection.md): the harness writes the rendered frames
as PNGs, runs this script once per clutter level, and pairs each image's segments with the
calibration paper's shaft pairing. This script is a benchmark tool, never a dependency of the
product: it needs the `opencv-contrib-python-headless` wheel (EdgeDrawing is in ximgproc).

    opencv_lines.py IN_DIR OUT_JSON

Output (JSON): the OpenCV version, the exact parameters, and per image (sorted by file name)
each detector's segments `[x1, y1, x2, y2]` in measured (distorted) pixels of the image as
given, the centre of the top-left pixel at (0, 0), and its time in milliseconds: the grey
conversion plus the detection, file reading and decoding excluded, the shortest of REPEATS
runs (time.perf_counter, one thread: cv2.setNumThreads(1)).
"""

import json
import os
import sys
import time

try:
    import cv2
except ImportError as e:  # the harness checks `import cv2` first; this is the fallback
    sys.stderr.write(f"opencv_lines.py: cannot import cv2 ({e}); "
                     "pip install --break-system-packages opencv-contrib-python-headless\n")
    sys.exit(3)

# EdgeDrawing (Topal & Akinlar, "Edge Drawing: a combined real-time edge and segment
# detector", J. Vis. Commun. Image R. 2012) with EDLines (Akinlar & Topal, "EDLines: a
# real-time line segment detector with a false detection control", Pattern Recognit. Lett.
# 2011): OpenCV's defaults, written out.
ED_PARAMS = {
    "EdgeDetectionOperator": 0,  # PREWITT
    "GradientThresholdValue": 20,
    "AnchorThresholdValue": 0,
    "ScanInterval": 1,
    "MinPathLength": 10,
    "Sigma": 1.0,
    "SumFlag": True,
    "NFAValidation": True,
    "MinLineLength": -1,  # -1: EDLines' own minimum from the image size
    "MaxDistanceBetweenTwoLines": 6.0,
    "LineFitErrorThreshold": 1.0,
    "MaxErrorThreshold": 1.3,
    "PFmode": False,
}

# LSD (von Gioi et al., "LSD: a fast line segment detector with a false detection control",
# IEEE TPAMI 2010): OpenCV's defaults, written out.
LSD_PARAMS = {
    "refine": 1,  # LSD_REFINE_STD
    "scale": 0.8,
    "sigma_scale": 0.6,
    "quant": 2.0,
    "ang_th": 22.5,
    "log_eps": 0.0,
    "density_th": 0.7,
    "n_bins": 1024,
}


# Each image is detected this many times and the shortest time kept (as the harness does for
# ours and the paper's: the shared machine's other tenants only ever add time).
REPEATS = 3


def make_ed():
    ed = cv2.ximgproc.createEdgeDrawing()
    p = cv2.ximgproc.EdgeDrawing.Params()
    for k, v in ED_PARAMS.items():
        setattr(p, k, v)
    ed.setParams(p)
    return ed


def make_lsd():
    p = LSD_PARAMS
    return cv2.createLineSegmentDetector(p["refine"], p["scale"], p["sigma_scale"], p["quant"], p["ang_th"],
                                         p["log_eps"], p["density_th"], p["n_bins"])


def segments(lines):
    if lines is None:
        return []
    return [[float(v) for v in l.reshape(-1)[:4]] for l in lines]


def main():
    if len(sys.argv) != 3:
        sys.stderr.write("usage: opencv_lines.py IN_DIR OUT_JSON\n")
        return 2
    in_dir, out_path = sys.argv[1], sys.argv[2]
    cv2.setNumThreads(1)
    ed = make_ed()
    lsd = make_lsd()
    images = []
    for name in sorted(f for f in os.listdir(in_dir) if f.endswith(".png")):
        bgr = cv2.imread(os.path.join(in_dir, name), cv2.IMREAD_COLOR)
        if bgr is None:
            sys.stderr.write(f"opencv_lines.py: cannot read {name}\n")
            return 1
        ed_ms, lsd_ms = float("inf"), float("inf")
        for _ in range(REPEATS):
            t0 = time.perf_counter()
            grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
            ed.detectEdges(grey)
            ed_lines = ed.detectLines()
            t1 = time.perf_counter()
            grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
            lsd_lines = lsd.detect(grey)[0]
            t2 = time.perf_counter()
            ed_ms, lsd_ms = min(ed_ms, (t1 - t0) * 1e3), min(lsd_ms, (t2 - t1) * 1e3)
        images.append({
            "file": name,
            "ed": {"segments": segments(ed_lines), "ms": ed_ms},
            "lsd": {"segments": segments(lsd_lines), "ms": lsd_ms},
        })
    out = {
        "opencv_version": cv2.__version__,
        "threads": cv2.getNumThreads(),
        "ed_params": ED_PARAMS,
        "lsd_params": LSD_PARAMS,
        "images": images,
    }
    with open(out_path, "w") as f:
        json.dump(out, f)
    return 0


if __name__ == "__main__":
    sys.exit(main())
