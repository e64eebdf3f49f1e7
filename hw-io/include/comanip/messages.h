/* comanip's shared-memory messages as C declarations (C11; C++ compatible).
 *
 * - FulcrumSample: fulcrumd's output, service "comanip/fulcrum", iceoryx2 type name
 *   "comanip::FulcrumSample", 200 bytes, alignment 8 (docs/output.md).
 * - comanip_frame_header_t: the user header of the frame service
 *   "comanip/frames/endoscope", iceoryx2 type name "comanip::FrameHeader", 72 bytes,
 *   alignment 8; the payload is the frame's pixels as a slice of bytes (docs/frames.md).
 * - CalibrationSample: comanip-calib live's output, service "comanip/calibration", iceoryx2
 *   type name "comanip::CalibrationSample", 432 bytes, alignment 8 (docs/output.md).
 * - TrackSample: comanip-track live's output, service "comanip/track", iceoryx2 type name
 *   "comanip::TrackSample", 288 bytes, alignment 8 (docs/output.md, docs/tracking.md).
 *
 * Units and frames are in each field's comment. hw-io/tests/c_layout.rs compiles this header
 * and checks every offset, the sizes and the alignments against the Rust types, and that the
 * declarations quoted in docs/output.md and docs/frames.md are the ones here.
 */
#ifndef COMANIP_MESSAGES_H
#define COMANIP_MESSAGES_H

#include <stdint.h>

#define FULCRUM_SAMPLE_VERSION 1u
#define FULCRUM_STATE_INVALID 0u
#define FULCRUM_STATE_OUTSIDE 1u
#define FULCRUM_STATE_INSIDE 2u

typedef struct FulcrumSample {
    uint32_t version;               /*   0: FULCRUM_SAMPLE_VERSION */
    uint32_t state;                 /*   4: FULCRUM_STATE_* */
    uint64_t sequence;              /*   8: cycle number since the daemon started */
    uint64_t run_id;                /*  16: random per daemon start */
    uint64_t timestamp_ns;          /*  24: SYNC instant, CLOCK_MONOTONIC, ns */
    uint32_t health;                /*  32: health flags */
    uint32_t trocar_id;             /*  36: trocar while inside, else 0 */
    double fulcrum_base_m[3];       /*  40: m, base frame */
    double residual_m;              /*  64: m */
    double fulcrum_std_m;           /*  72: m */
    double conditioning;            /*  80: dimensionless, 0..2/3 */
    double wrist_base_m[3];         /*  88: m, base frame */
    double axis_base[3];            /* 112: unit vector, base frame */
    double joints_rad[6];           /* 136: rad, joints 1..6 */
    uint16_t window_fill;           /* 184: lines */
    uint16_t window_len;            /* 186: lines */
    uint16_t fit_lines;             /* 188: lines */
    uint16_t reserved;              /* 190: zero */
    uint32_t wake_late_ns;          /* 192: ns */
    uint32_t prev_cycle_compute_ns; /* 196: ns */
} FulcrumSample;

_Static_assert(sizeof(FulcrumSample) == 200, "FulcrumSample layout");
_Static_assert(_Alignof(FulcrumSample) == 8, "FulcrumSample alignment");

#define COMANIP_FRAME_HEADER_VERSION 1u
#define COMANIP_PIXEL_GRAY8 1u /* 1 byte per pixel */
#define COMANIP_PIXEL_RGB8  2u /* R, G, B: 3 bytes per pixel, sRGB */
#define COMANIP_PIXEL_YUYV  3u /* V4L2 YUYV 4:2:2: Y0 U Y1 V per two pixels, even width */

typedef struct {
    uint32_t version;        /*  0: COMANIP_FRAME_HEADER_VERSION */
    uint32_t camera_id;      /*  4: camera rig id (0: the first endoscope) */
    uint64_t sequence;       /*  8: 0 for the publisher run's first frame, +1 per frame */
    uint64_t run_id;         /* 16: random per publisher start */
    uint64_t timestamp_ns;   /* 24: mid time of the exposure, CLOCK_MONOTONIC, ns */
    uint32_t exposure_ns;    /* 32: exposure time, ns (0: unknown) */
    uint32_t eyes;           /* 36: 1 mono, 2 stereo (left first) */
    uint32_t width;          /* 40: pixels, each eye */
    uint32_t height;         /* 44: pixels, each eye */
    uint32_t stride;         /* 48: bytes from one row to the next */
    uint32_t pixel_format;   /* 52: COMANIP_PIXEL_* */
    uint64_t payload_bytes;  /* 56: eyes * stride * height */
    uint64_t source_dropped; /* 64: frames the source lost so far (cumulative, this run) */
} comanip_frame_header_t;    /* sizeof 72, alignof 8 */

_Static_assert(sizeof(comanip_frame_header_t) == 72, "comanip_frame_header_t layout");
_Static_assert(_Alignof(comanip_frame_header_t) == 8, "comanip_frame_header_t alignment");

#define TRACK_SAMPLE_VERSION 1u
#define TRACK_STATUS_INVALID 0u   /* input refused: see reasons; no pose */
#define TRACK_STATUS_TRACKING 1u  /* pose valid */
#define TRACK_STATUS_UNCERTAIN 2u /* pose is the best guess; spread above the limit */
#define TRACK_STATUS_LOST 3u      /* no pose */
#define TRACK_REASON_CALIBRATION_FROM_CONFIG (1u << 0)
#define TRACK_REASON_CALIBRATION_DRIFT (1u << 1)
#define TRACK_REASON_CALIBRATION_REFUSED (1u << 2)
#define TRACK_REASON_TOOL_JOINTS_STALE (1u << 3)
#define TRACK_REASON_ENDOSCOPE_JOINTS_STALE (1u << 4)
#define TRACK_REASON_NOT_FINITE (1u << 5)
#define TRACK_REASON_FRAME_FORMAT (1u << 6)
#define TRACK_REASON_FRAME_HEADER (1u << 7)
#define TRACK_REASON_TRACKER_REFUSED (1u << 8)
#define TRACK_REASON_REINITIALISED (1u << 9)
#define TRACK_REASON_SKIPPED_BEFORE (1u << 10)

typedef struct TrackSample {
    uint32_t version;              /*   0: TRACK_SAMPLE_VERSION */
    uint32_t status;               /*   4: TRACK_STATUS_* */
    uint64_t sequence;             /*   8: message number since the tracker started */
    uint64_t run_id;               /*  16: random per tracker start */
    uint64_t frame_timestamp_ns;   /*  24: the frame's mid-exposure time, ns */
    uint64_t frame_sequence;       /*  32: the frame's sequence on the frame service */
    uint64_t published_ns;         /*  40: CLOCK_MONOTONIC at publish, ns */
    uint32_t reasons;              /*  48: TRACK_REASON_* bits */
    uint32_t calibration_source;   /*  52: 0 configuration, 1 live calibration */
    uint64_t calibration_sequence; /*  56: sequence of the CalibrationSample used */
    uint64_t calibration_run_id;   /*  64: run_id of the CalibrationSample used */
    double tip_camera_m[3];        /*  72: m, left camera frame */
    double tip_camera_wxyz[4];     /*  96: unit quaternion, left camera frame */
    double tip_base_m[3];          /* 128: m, tool arm base frame */
    double tip_base_wxyz[4];       /* 152: unit quaternion, tool arm base frame */
    double jaw_rad;                /* 184: rad, each jaw */
    double spread_m;               /* 192: m, particles' tip spread; -1 undefined */
    double best_cost_px;           /* 200: px per eye; -1 undefined */
    double camera_delta[6];        /* 208: g_CB correction: rad (rotation vector), m */
    uint64_t frames_processed;     /* 256: frames with a sample */
    uint64_t frames_skipped;       /* 264: frames dropped for newer ones or lost */
    uint64_t frames_rejected;      /* 272: frames with a corrupt header */
    uint64_t frames_invalid;       /* 280: processed frames whose input was refused */
} TrackSample;

_Static_assert(sizeof(TrackSample) == 288, "TrackSample layout");
_Static_assert(_Alignof(TrackSample) == 8, "TrackSample alignment");

#define CALIBRATION_SAMPLE_VERSION 1u
#define CALIBRATION_STATE_COLLECTING 0u
#define CALIBRATION_STATE_VALID 1u
#define CALIBRATION_STATE_DRIFT 2u

typedef struct CalibrationSample {
    uint32_t version;              /*   0: CALIBRATION_SAMPLE_VERSION */
    uint32_t state;                /*   4: CALIBRATION_STATE_*: use the pose only when VALID */
    uint64_t sequence;             /*   8: message number since the publisher started */
    uint64_t run_id;               /*  16: random per publisher start */
    uint64_t timestamp_ns;         /*  24: last frame used, mid-exposure, ns */
    uint32_t observations;         /*  32: eye lines used (or collected so far) */
    uint32_t drifts;               /*  36: drift events since start */
    double translation_m[3];       /*  40: m, T_e_t: {t} origin in {e} (endoscope RCM frame) */
    double quaternion_wxyz[4];     /*  64: unit quaternion, rotation of T_e_t */
    double covariance[36];         /*  96: row-major 6x6 of (t m, phi rad) */
    double predicted_fulcrum_m;    /* 384: m, RMS at the mean fulcrum */
    double predicted_origin_m;     /* 392: m, RMS at {t}'s origin */
    double predicted_rotation_rad; /* 400: rad, RMS */
    double mean_fulcrum_m[3];      /* 408: m, {t} */
} CalibrationSample;

_Static_assert(sizeof(CalibrationSample) == 432, "CalibrationSample layout");
_Static_assert(_Alignof(CalibrationSample) == 8, "CalibrationSample alignment");

#endif /* COMANIP_MESSAGES_H */
