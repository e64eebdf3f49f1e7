#!/usr/bin/env python3
"""A guidance-force module's side of comanip in Python: read fulcrumd's FulcrumSample from
shared memory with the `iceoryx2` package (PyPI, 0.10, the version of the Rust crate fulcrumd
is built with) and act only on valid samples.

    python3 -m pip install iceoryx2==0.10.0
    fulcrumd &                                   # or: systemctl start fulcrumd
    python3 fulcrum_subscriber.py                # prints each state change
    python3 fulcrum_subscriber.py --service comanip/fulcrum --count 5000 --jsonl samples.jsonl

The message is a ctypes mirror of `FulcrumSample` in hw-io/include/comanip/messages.h
(installed as /usr/include/comanip/messages.h): 200 bytes, alignment 8, native byte order,
iceoryx2 type name "comanip::FulcrumSample". Units and frames as in docs/output.md: metres and
radians, the fulcrum in the robot base frame. The service capacities below must be fulcrumd's
(`[output] subscriber_buffer`, default 64; `--buffer`): whichever side starts first creates the
services, and a mismatch is refused on the side that comes second.

Exit codes: 0 done; 1 iceoryx2 error; 2 bad command line; 3 `--expect-in-order` and a sample
was missed, refused, or came from another daemon run.
"""

import argparse
import ctypes
import json
import sys
import time

import iceoryx2 as iox2

FULCRUM_SAMPLE_VERSION = 1
STATE_INVALID, STATE_OUTSIDE, STATE_INSIDE = 0, 1, 2
STATE_NAMES = {STATE_INVALID: "INVALID", STATE_OUTSIDE: "outside", STATE_INSIDE: "INSIDE"}

# Health flags (docs/output.md, "Health flags"): bit -> name.
HEALTH_FLAGS = [
    (0x0001, "node1-stale"), (0x0002, "node2-stale"), (0x0004, "node3-stale"),
    (0x0008, "node1-emcy"), (0x0010, "node2-emcy"), (0x0020, "node3-emcy"),
    (0x0040, "node1-heartbeat"), (0x0080, "node2-heartbeat"), (0x0100, "node3-heartbeat"),
    (0x0200, "incomplete-cycle"), (0x0400, "overrun"), (0x0800, "sync-send-failed"),
    (0x1000, "bus-error"), (0x2000, "bad-sample"), (0x4000, "detector-reset"),
]
HEALTH_INVALIDATING = 0x3BFF


class FulcrumSample(ctypes.Structure):
    """fulcrumd's output, one per 1 kHz cycle; mirrors `FulcrumSample` of messages.h."""

    _fields_ = [
        ("version", ctypes.c_uint32),                 # 0: FULCRUM_SAMPLE_VERSION
        ("state", ctypes.c_uint32),                   # 4: STATE_*
        ("sequence", ctypes.c_uint64),                # 8: cycle number since the daemon started
        ("run_id", ctypes.c_uint64),                  # 16: random per daemon start
        ("timestamp_ns", ctypes.c_uint64),            # 24: SYNC instant, CLOCK_MONOTONIC, ns
        ("health", ctypes.c_uint32),                  # 32: health flags
        ("trocar_id", ctypes.c_uint32),               # 36: trocar while inside, else 0
        ("fulcrum_base_m", ctypes.c_double * 3),      # 40: m, robot base frame
        ("residual_m", ctypes.c_double),              # 64: m
        ("fulcrum_std_m", ctypes.c_double),           # 72: m
        ("conditioning", ctypes.c_double),            # 80: dimensionless, 0..2/3
        ("wrist_base_m", ctypes.c_double * 3),        # 88: m, robot base frame
        ("axis_base", ctypes.c_double * 3),           # 112: unit vector, robot base frame
        ("joints_rad", ctypes.c_double * 6),          # 136: rad, joints 1..6
        ("window_fill", ctypes.c_uint16),             # 184: lines
        ("window_len", ctypes.c_uint16),              # 186: lines
        ("fit_lines", ctypes.c_uint16),               # 188: lines
        ("reserved", ctypes.c_uint16),                # 190: zero
        ("wake_late_ns", ctypes.c_uint32),            # 192: ns
        ("prev_cycle_compute_ns", ctypes.c_uint32),   # 196: ns
    ]

    @staticmethod
    def type_name() -> str:
        """The iceoryx2 type name; iceoryx2 also compares size (200) and alignment (8)."""
        return "comanip::FulcrumSample"


assert ctypes.sizeof(FulcrumSample) == 200 and ctypes.alignment(FulcrumSample) == 8


def health_names(bits: int) -> str:
    """The set flags as fulcrumd's log prints them: `node2-stale,overrun`, `ok` when none."""
    names = [name for mask, name in HEALTH_FLAGS if bits & mask]
    unknown = bits & ~0x7FFF
    if unknown:
        names.append(f"unknown-{unknown:#x}")
    return ",".join(names) if names else "ok"


def is_valid(s: FulcrumSample) -> bool:
    """A known state other than invalid, and the layout version this program reads."""
    return s.version == FULCRUM_SAMPLE_VERSION and s.state in (STATE_OUTSIDE, STATE_INSIDE)


def decode(s: FulcrumSample) -> dict:
    """Every field of the sample as plain Python values."""
    d = {}
    for name, ctype in FulcrumSample._fields_:
        v = getattr(s, name)
        d[name] = list(v) if hasattr(ctype, "_length_") else v
    return d


class Continuity:
    """First / in_order / gap / restart from (run_id, sequence), as docs/output.md defines."""

    def __init__(self):
        self.prev = None
        self.missed = 0
        self.restarts = 0

    def next(self, s: FulcrumSample):
        """(event, missed) of this sample against the previous accepted one."""
        prev, self.prev = self.prev, (s.run_id, s.sequence)
        if prev is None:
            return "first", 0
        run_id, seq = prev
        if s.run_id != run_id or s.sequence <= seq:
            self.restarts += 1
            return "restart", 0
        if s.sequence == seq + 1:
            return "in_order", 0
        missed = s.sequence - seq - 1
        self.missed += missed
        return "gap", missed


def open_output(node, service: str, buffer: int, max_subscribers: int = 8):
    """The output's publish-subscribe and event services, opened or created with fulcrumd's
    capacities (hw_io::ipc::PublisherOptions: 1 publisher, `max_subscribers` subscribers,
    nodes = subscribers + 2, `buffer` samples per subscriber, history 0, safe overflow)."""
    name = iox2.ServiceName.new(service)
    pubsub = (
        node.service_builder(name)
        .publish_subscribe(FulcrumSample)
        .max_publishers(1)
        .max_subscribers(max_subscribers)
        .max_nodes(max_subscribers + 2)
        .subscriber_max_buffer_size(buffer)
        .history_size(0)
        .enable_safe_overflow(True)
        .open_or_create()
    )
    event = (
        node.service_builder(name)
        .event()
        .max_notifiers(1)
        .max_listeners(max_subscribers)
        .max_nodes(max_subscribers + 2)
        .open_or_create()
    )
    return pubsub, event


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--service", default="comanip/fulcrum", help="fulcrumd's [output] service")
    ap.add_argument("--buffer", type=int, default=64, help="fulcrumd's [output] subscriber_buffer")
    ap.add_argument("--count", type=int, help="exit after this many samples")
    ap.add_argument("--idle-timeout-s", type=float, help="exit when no sample came for this long (after the first)")
    ap.add_argument("--jsonl", help="write every received sample, decoded, as one JSON line to this file")
    ap.add_argument("--expect-in-order", action="store_true", help="exit 3 unless every sample came in order")
    args = ap.parse_args()
    if args.buffer < 1:
        ap.error("--buffer must be at least 1")

    iox2.set_log_level_from_env_or(iox2.LogLevel.Warn)
    # Disabled: iceoryx2 installs no signal handler; Ctrl-C ends the program as usual.
    node = (
        iox2.NodeBuilder.new()
        .signal_handling_mode(iox2.SignalHandlingMode.Disabled)
        .create(iox2.ServiceType.Ipc)
    )
    pubsub, event = open_output(node, args.service, args.buffer)
    subscriber = pubsub.subscriber_builder().buffer_size(args.buffer).create()
    listener = event.listener_builder().create()
    out = open(args.jsonl, "w", encoding="utf-8") if args.jsonl else None
    print(f"listening on {args.service!r}", file=sys.stderr, flush=True)

    cont = Continuity()
    received = rejected = 0
    last_state = None
    last_rx = None
    try:
        while args.count is None or received < args.count:
            sample = subscriber.receive()
            if sample is None:
                if last_rx is not None and args.idle_timeout_s is not None and time.monotonic() - last_rx > args.idle_timeout_s:
                    break
                # Sleep until fulcrumd's notification (or 100 ms, in case one was lost).
                listener.timed_wait(iox2.Duration.from_millis(100))
                continue
            # Copy out of shared memory, then give the chunk back at once.
            s = FulcrumSample.from_buffer_copy(sample.payload().contents)
            sample.delete()
            last_rx = time.monotonic()
            if s.version != FULCRUM_SAMPLE_VERSION:
                rejected += 1  # another layout: do not read its fields
                continue
            received += 1
            event_name, missed = cont.next(s)
            if event_name == "restart":
                print("fulcrumd restarted: estimates start afresh", file=sys.stderr)
            elif event_name == "gap":
                print(f"{missed} samples missed (reading too slowly?)", file=sys.stderr)
            if out is not None:
                line = {"event": event_name, "missed": missed, **decode(s)}
                out.write(json.dumps(line) + "\n")
            # Never use an invalid sample: its health flags say why.
            if not is_valid(s):
                continue
            if last_state != (s.state, s.trocar_id):
                if s.state == STATE_INSIDE:
                    f = s.fulcrum_base_m
                    print(f"cycle {s.sequence}: inside trocar #{s.trocar_id}, fulcrum "
                          f"({f[0]:+.4f}, {f[1]:+.4f}, {f[2]:+.4f}) m, robot base frame", flush=True)
                else:
                    print(f"cycle {s.sequence}: outside: no fulcrum to guide to", flush=True)
                last_state = (s.state, s.trocar_id)
    except KeyboardInterrupt:
        pass
    finally:
        if out is not None:
            out.close()
    print(f"received {received}, missed {cont.missed}, restarts {cont.restarts}, refused {rejected}",
          file=sys.stderr, flush=True)
    if args.expect_in_order and (cont.missed or cont.restarts or rejected):
        return 3
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except (iox2.PublishSubscribeOpenOrCreateError, iox2.EventOpenOrCreateError,
            iox2.SubscriberCreateError, iox2.ListenerCreateError, iox2.NodeCreationFailure) as e:
        print(f"fulcrum_subscriber: iceoryx2: {e!r}", file=sys.stderr)
        sys.exit(1)
