#!/usr/bin/env bash
# smoke.sh: proves tests/hil/run-in-vcan.sh works. Run by hand: tests/hil/smoke.sh
#
# Cases (each one is one run-in-vcan.sh invocation, timed):
#   can-frames     candump in the background on vcan0; 1000 frames at 1 kHz (cangen -g 1), a burst of
#                  1000 (cangen -g 0 -p), 1 cansend, plus a CAN FD frame on vcan1; all must arrive,
#                  in order, with the right payloads.
#   false          `false` -> exit code 1
#   exit-3         `bash -c 'exit 3'` -> 3
#   not-found      a missing command -> 127
#   timeout        `--timeout 2 -- sleep 30` -> 124
#   env-argv-cwd   caller env (RUST_LOG, RUST_BACKTRACE, CARGO_TARGET_DIR, a multi-line value), awkward
#                  argv, a cwd under /tmp, writable /tmp /var/tmp /dev/shm, read-only root
#   streams        200000 stdout lines and a stderr line arrive intact, on the right streams
#   python-afcan   /usr/bin/python3 and PATH's python3: AF_CAN raw socket bound to vcan0, send + recv
#   c-afcan        a dynamically linked C program built here with gcc into /tmp: same, in C
#   rw-mount       --rw DIR: a file written in the guest appears on the host
#   native-path    run-in-vcan.sh run inside the guest, where the kernel has vcan, takes the native
#                  path: creates vcan7, exit code 4 and a native --timeout (124) come through
#   vm-fails       HIL_UML_KERNEL=/bin/false (VM cannot start) -> 125, never 0
#   setup-fails    --ifaces lo (cannot be created as vcan) -> 125 with the guest's reason
#   parallel       3 concurrent invocations, 500 frames each: all pass (unique results dir + umid)
#   sigint         SIGINT to the harness while the guest runs -> 130 and no UML process left behind
#   timer-1khz     (informational, not asserted) lateness of a 1 kHz clock_nanosleep(TIMER_ABSTIME) loop
#
# Exit code: 0 if every case passed, 1 otherwise. Prints per-invocation timings at the end.
set -euo pipefail

HERE=$(cd -- "$(dirname -- "${BASH_SOURCE[0]}")" && pwd)
RUN=$HERE/run-in-vcan.sh
WORK=$(mktemp -d "${TMPDIR:-/tmp}/hil-smoke.XXXXXX")
trap 'rm -rf -- "$WORK"' EXIT

failures=0
declare -a summary=()

# run_case NAME EXPECTED_RC [run-in-vcan.sh args...]: run it, keep stdout/stderr in $WORK/NAME.{out,err},
# record the wall time and the harness's boot/total timing line, check the exit code.
run_case() {
    local name=$1 want=$2 rc t0 t1 wall timing
    shift 2
    t0=$EPOCHREALTIME
    rc=0
    "$RUN" "$@" > "$WORK/$name.out" 2> "$WORK/$name.err" || rc=$?
    t1=$EPOCHREALTIME
    wall=$(awk -v a="${t0/,/.}" -v b="${t1/,/.}" 'BEGIN { printf "%.2f", b - a }')
    timing=$(grep -o 'boot->cmd [0-9.]*s' "$WORK/$name.err" | head -n1 || true)
    summary+=("$(printf '%-14s rc=%-3s wall=%6ss  %s' "$name" "$rc" "$wall" "${timing:-}")")
    if [[ $rc != "$want" ]]; then
        fail "$name: exit code $rc, expected $want"
        sed 's/^/    | /' "$WORK/$name.out" | tail -n 20 >&2
        sed 's/^/    | /' "$WORK/$name.err" | tail -n 20 >&2
        return 1
    fi
    return 0
}
fail() { printf 'FAIL %s\n' "$*" >&2; failures=$((failures + 1)); }
# expect_line NAME STREAM(out|err) LINE: the captured stream must contain exactly this line.
expect_line() {
    if grep -Fxq -- "$3" "$WORK/$1.$2"; then return 0; fi
    fail "$1: std$2 has no line '$3'"
    sed 's/^/    | /' "$WORK/$1.$2" | tail -n 20 >&2
    return 1
}
pass() { printf 'ok   %s\n' "$*"; }
# expect NAME STREAM(out|err) REGEX: the captured stream must contain a line matching REGEX.
expect() {
    if grep -Eq -- "$3" "$WORK/$1.$2"; then return 0; fi
    fail "$1: std$2 has no line matching /$3/"
    sed 's/^/    | /' "$WORK/$1.$2" | tail -n 20 >&2
    return 1
}

# ---------------------------------------------------------------------------------------------------
# can-frames: everything sent on vcan0/vcan1 is received.
# ---------------------------------------------------------------------------------------------------
cat > "$WORK/can-frames.sh" <<'GUEST'
set -euo pipefail
cd /tmp
# Wait until a raw CAN receiver is bound on IFACE (so no frame is sent before candump listens).
wait_rx() {
    local i
    for i in $(seq 200); do
        grep -Eq "^ +$1 " /proc/net/can/rcvlist_all && return 0
        sleep 0.02
    done
    echo "no receiver on $1" >&2; return 1
}
N=${FRAMES:-1000}
EXPECT0=$((2 * N + 1))
# -r 8 MiB receive buffer: the burst below is unpaced, and a receiver that is starved of CPU (several
# VMs on 2 cores) overflows the default ~200 kB socket buffer and loses frames, as SocketCAN does.
candump -L -r 8388608 -n "$EXPECT0" -T 5000 vcan0 > dump0.log & dump0=$!
candump -L -n 1 -T 5000 vcan1 > dump1.log & dump1=$!
wait_rx vcan0; wait_rx vcan1
t0=$EPOCHREALTIME
cangen vcan0 -g 1 -n "$N" -I 123 -L 8 -D i          # 1 kHz, id 0x123, incrementing payload
t1=$EPOCHREALTIME
cangen vcan0 -g 0 -p 100 -n "$N" -I 456 -L 4 -D i   # burst, poll on ENOBUFS
cansend vcan0 7FF#DEADBEEF
cansend vcan1 1F334455##1.11.22.33.44.55.66.77.88.99.AA.BB.CC   # CAN FD, extended id, BRS, 12 bytes
wait "$dump0" || echo "CANDUMP0_RC $?"
wait "$dump1" || echo "CANDUMP1_RC $?"
echo "SENT_1KHZ_SECONDS $(awk -v a="$t0" -v b="$t1" 'BEGIN { printf "%.3f", b - a }')"
echo "RECEIVED_VCAN0 $(wc -l < dump0.log) EXPECTED $EXPECT0"
echo "ID123 $(grep -c ' vcan0 123#' dump0.log) ID456 $(grep -c ' vcan0 456#' dump0.log) ID7FF $(grep -c ' vcan0 7FF#DEADBEEF$' dump0.log)"
# The 1 kHz frames must arrive in order: the first payload byte counts 00, 01, ..., FF, 00, ...
# (plain POSIX awk: mawk has no strtonum)
awk 'BEGIN { H = "0123456789ABCDEF" }
     $3 ~ /^123#/ { h = toupper(substr($3, 5, 2))
                    b = (index(H, substr(h, 1, 1)) - 1) * 16 + index(H, substr(h, 2, 1)) - 1
                    if (b != n % 256) bad++; n++ }
     END { print "ORDER_ERRORS_123", bad + 0 }' dump0.log
echo "RECEIVED_VCAN1 $(cat dump1.log | cut -d' ' -f2-)"
GUEST
if run_case can-frames 0 --ifaces vcan0,vcan1 --timeout 60 -- env FRAMES=1000 bash "$WORK/can-frames.sh"; then
    expect can-frames out '^RECEIVED_VCAN0 2001 EXPECTED 2001$' &&
        expect can-frames out '^ID123 1000 ID456 1000 ID7FF 1$' &&
        expect can-frames out '^ORDER_ERRORS_123 0$' &&
        expect can-frames out '^RECEIVED_VCAN1 vcan1 1F334455##[15]112233445566778899AABBCC$' &&
        pass "can-frames: 2001/2001 on vcan0 (1000 @1 kHz in order, 1000 burst, 1 cansend), CAN FD on vcan1;" \
            "1000 frames at 1 kHz took $(awk '/^SENT_1KHZ/ {print $2}' "$WORK/can-frames.out")s in the guest"
fi

# ---------------------------------------------------------------------------------------------------
# Exit codes
# ---------------------------------------------------------------------------------------------------
run_case false 1 -- false && pass "false -> 1"
run_case exit-3 3 -- bash -c 'exit 3' && pass "exit 3 -> 3"
run_case not-found 127 -- /nonexistent/hil-no-such-command && pass "missing command -> 127"
if run_case timeout 124 --timeout 2 -- sleep 30; then
    expect timeout err 'timed out after 2s' && pass "--timeout 2 on sleep 30 -> 124"
fi

# ---------------------------------------------------------------------------------------------------
# env-argv-cwd: the guest command sees the caller's environment, argv and working directory.
# ---------------------------------------------------------------------------------------------------
mkdir -p "$WORK/cwd"
cat > "$WORK/env-argv-cwd.sh" <<'GUEST'
echo "PWD=$PWD"
echo "RUST_LOG=$RUST_LOG RUST_BACKTRACE=$RUST_BACKTRACE CARGO_TARGET_DIR=$CARGO_TARGET_DIR"
echo "MULTI_MD5 $(printf '%s' "$HIL_SMOKE_MULTI" | md5sum | cut -d' ' -f1)"
printf 'ARG=[%s]\n' "$@"
echo "HIL_IN_GUEST=$HIL_IN_GUEST HIL_IFACES=$HIL_IFACES"
for d in /tmp /var/tmp /dev/shm; do : > "$d/hil-smoke-probe" && echo "WRITABLE $d"; done
if : > /usr/hil-smoke-probe 2>/dev/null; then echo "ROOT_WRITABLE"; else echo "ROOT_READONLY"; fi
/usr/bin/python3 -c 'import multiprocessing.shared_memory as s; m = s.SharedMemory(create=True, size=4096); print("SHM_OK", m.name); m.close(); m.unlink()'
GUEST
multi=$'line one\nline "two" $x \\'
cd "$WORK/cwd"
# shellcheck disable=SC2016  # '$HOME' is a literal argument on purpose
if RUST_LOG=comanip=debug RUST_BACKTRACE=1 CARGO_TARGET_DIR=/work/main/target HIL_SMOKE_MULTI=$multi \
    run_case env-argv-cwd 0 -- bash "$WORK/env-argv-cwd.sh" 'a b' "it's" '$HOME' ''; then
    expect_line env-argv-cwd out "PWD=$WORK/cwd" &&
        expect_line env-argv-cwd out 'RUST_LOG=comanip=debug RUST_BACKTRACE=1 CARGO_TARGET_DIR=/work/main/target' &&
        expect_line env-argv-cwd out "MULTI_MD5 $(printf '%s' "$multi" | md5sum | cut -d' ' -f1)" &&
        expect_line env-argv-cwd out 'ARG=[a b]' && expect_line env-argv-cwd out "ARG=[it's]" &&
        expect_line env-argv-cwd out 'ARG=[$HOME]' && expect_line env-argv-cwd out 'ARG=[]' &&
        expect_line env-argv-cwd out 'HIL_IN_GUEST=1 HIL_IFACES=vcan0' &&
        expect_line env-argv-cwd out 'WRITABLE /tmp' && expect_line env-argv-cwd out 'WRITABLE /var/tmp' &&
        expect_line env-argv-cwd out 'WRITABLE /dev/shm' && expect_line env-argv-cwd out 'ROOT_READONLY' &&
        expect env-argv-cwd out '^SHM_OK ' &&
        pass "env (RUST_LOG, RUST_BACKTRACE, CARGO_TARGET_DIR, multi-line), argv quoting, cwd, writable /tmp /var/tmp /dev/shm, ro root"
fi
cd - > /dev/null
# The guest's writes to /tmp are private: nothing leaked to the host's /tmp.
if [[ -e /tmp/hil-smoke-probe ]]; then fail "guest write to /tmp leaked to the host"; fi

# ---------------------------------------------------------------------------------------------------
# streams: large stdout, stderr kept apart.
# ---------------------------------------------------------------------------------------------------
if run_case streams 0 -- bash -c 'seq 1 200000; echo "to-stderr" >&2'; then
    if [[ $(wc -l < "$WORK/streams.out") == 200000 && $(tail -n1 "$WORK/streams.out") == 200000 ]] &&
        [[ $(seq 1 200000 | md5sum) == $(md5sum < "$WORK/streams.out") ]] &&
        grep -Fxq to-stderr "$WORK/streams.err" && ! grep -q to-stderr "$WORK/streams.out"; then
        pass "streams: 200000 stdout lines byte-exact, stderr separate"
    else
        fail "streams: stdout not intact ($(wc -l < "$WORK/streams.out") lines)"
    fi
fi

# ---------------------------------------------------------------------------------------------------
# python-afcan: an ordinary host binary (python3) uses SocketCAN in the guest.
# ---------------------------------------------------------------------------------------------------
cat > "$WORK/afcan.py" <<'PY'
import socket, struct, sys
fmt = "=IB3x8s"                                   # struct can_frame
rx = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
rx.bind(("vcan0",))
tx = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
tx.bind(("vcan0",))
tx.send(struct.pack(fmt, 0x321, 4, b"\x01\x02\x03\x04".ljust(8, b"\x00")))
rx.settimeout(5)
can_id, dlc, data = struct.unpack(fmt, rx.recv(16))
print(f"PY_AFCAN {sys.executable} id=0x{can_id:x} dlc={dlc} data={data[:dlc].hex()}")
PY
if run_case python-afcan 0 -- bash -c "/usr/bin/python3 $WORK/afcan.py && python3 $WORK/afcan.py"; then
    expect python-afcan out '^PY_AFCAN /usr/bin/python3 id=0x321 dlc=4 data=01020304$' &&
        [[ $(grep -c '^PY_AFCAN .* id=0x321 dlc=4 data=01020304$' "$WORK/python-afcan.out") == 2 ]] &&
        pass "python3 AF_CAN raw socket on vcan0: $(cut -d' ' -f2 "$WORK/python-afcan.out" | paste -sd' ')"
fi

# ---------------------------------------------------------------------------------------------------
# c-afcan: a dynamically linked C program compiled on the host into /tmp.
# ---------------------------------------------------------------------------------------------------
if command -v gcc > /dev/null; then
    cat > "$WORK/afcan.c" <<'C'
#include <linux/can.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <stdio.h>
#include <string.h>
#include <sys/socket.h>
#include <unistd.h>

static int open_bound(const char *ifname) {
    int s = socket(PF_CAN, SOCK_RAW, CAN_RAW);
    if (s < 0) { perror("socket(PF_CAN)"); return -1; }
    struct sockaddr_can addr = { .can_family = AF_CAN, .can_ifindex = (int)if_nametoindex(ifname) };
    if (addr.can_ifindex == 0 || bind(s, (struct sockaddr *)&addr, sizeof addr) < 0) { perror("bind"); return -1; }
    return s;
}

int main(void) {
    int rx = open_bound("vcan0"), tx = open_bound("vcan0");
    if (rx < 0 || tx < 0) return 2;
    struct can_frame f = { .can_id = 0x42, .can_dlc = 2, .data = { 0xab, 0xcd } }, g;
    if (write(tx, &f, sizeof f) != sizeof f) { perror("write"); return 3; }
    if (read(rx, &g, sizeof g) != sizeof g) { perror("read"); return 4; }
    printf("C_AFCAN id=0x%x dlc=%d data=%02x%02x\n", g.can_id, g.can_dlc, g.data[0], g.data[1]);
    return g.can_id == 0x42 && g.data[1] == 0xcd ? 0 : 5;
}
C
    gcc -O2 -Wall -o "$WORK/afcan" "$WORK/afcan.c"
    if ! LC_ALL=C readelf -d "$WORK/afcan" | grep -q 'NEEDED.*libc.so'; then
        fail "c-afcan: $WORK/afcan is not dynamically linked against libc"
    elif run_case c-afcan 0 -- "$WORK/afcan"; then
        expect c-afcan out '^C_AFCAN id=0x42 dlc=2 data=abcd$' &&
            pass "dynamically linked C program from /tmp: AF_CAN send/recv on vcan0"
    fi
else
    fail "c-afcan: gcc not found"
fi

# ---------------------------------------------------------------------------------------------------
# timer-1khz: informational; HIL tests must not assert timings (see docs/hil.md).
# ---------------------------------------------------------------------------------------------------
if command -v gcc > /dev/null; then
    cat > "$WORK/timer.c" <<'C'
#include <stdio.h>
#include <time.h>
int main(void) {
    enum { N = 3000, PERIOD_NS = 1000000 };
    struct timespec next, now;
    long late, sum = 0, max = 0, over1ms = 0;
    clock_gettime(CLOCK_MONOTONIC, &next);
    for (int i = 0; i < N; i++) {
        next.tv_nsec += PERIOD_NS;
        if (next.tv_nsec >= 1000000000) { next.tv_nsec -= 1000000000; next.tv_sec++; }
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &next, NULL);
        clock_gettime(CLOCK_MONOTONIC, &now);
        late = (now.tv_sec - next.tv_sec) * 1000000000L + (now.tv_nsec - next.tv_nsec);
        sum += late; if (late > max) max = late; if (late > 1000000) over1ms++;
    }
    printf("TIMER_1KHZ n=%d mean_late_us=%ld max_late_us=%ld late_over_1ms=%ld\n", N, sum / N / 1000, max / 1000, over1ms);
    return 0;
}
C
    gcc -O2 -o "$WORK/timer" "$WORK/timer.c"
    if run_case timer-1khz 0 -- "$WORK/timer"; then
        pass "timer (informational): $(grep '^TIMER_1KHZ' "$WORK/timer-1khz.out")"
    fi
fi

# ---------------------------------------------------------------------------------------------------
# rw-mount: --rw DIR is written through to the host.
# ---------------------------------------------------------------------------------------------------
mkdir -p "$WORK/rw"
if run_case rw-mount 0 --rw "$WORK/rw" -- bash -c "echo from-guest > $WORK/rw/report.txt"; then
    if [[ $(cat "$WORK/rw/report.txt" 2>/dev/null) == from-guest ]]; then
        pass "--rw: guest file visible on the host"
    else
        fail "rw-mount: $WORK/rw/report.txt not written through"
    fi
fi

# ---------------------------------------------------------------------------------------------------
# native-path: inside the guest the kernel has vcan, so a nested run-in-vcan.sh runs natively.
# ---------------------------------------------------------------------------------------------------
# shellcheck disable=SC2016  # expanded by the guest's bash
if run_case native-path 0 -- bash -c '
    "$0" --ifaces vcan0,vcan7 -- bash -c "echo mode=\$HIL_MODE; ip -br link show vcan7; exit 4"
    echo "NATIVE_RC $?"
    "$0" --timeout 1 -- sleep 5
    echo "NATIVE_TIMEOUT_RC $?"' "$RUN"; then
    expect_line native-path out 'mode=native' && expect native-path out '^vcan7 +UNKNOWN +<NOARP,UP,LOWER_UP>' &&
        expect_line native-path out 'NATIVE_RC 4' && expect_line native-path out 'NATIVE_TIMEOUT_RC 124' &&
        expect native-path err 'host kernel has vcan: running natively' &&
        pass "native path (host with vcan): vcan7 created and up, exit 4 and timeout 124 propagated"
fi

# ---------------------------------------------------------------------------------------------------
# Harness failures are loud (125), never a pass or a skip.
# ---------------------------------------------------------------------------------------------------
if HIL_UML_KERNEL=/bin/false run_case vm-fails 125 -- true; then
    expect vm-fails err 'ERROR: the VM did not start the command' && pass "VM cannot start -> 125"
fi
if run_case setup-fails 125 --ifaces lo -- true; then
    expect setup-fails err 'ip -batch failed' && pass "guest setup failure (--ifaces lo) -> 125 with reason"
fi
# The kept results dirs of those two failures are expected; remove them.
grep -ho 'results kept in [^ ]*' "$WORK/vm-fails.err" "$WORK/setup-fails.err" 2>/dev/null |
    awk '{print $4}' | while read -r d; do [[ $d == */hil-run.* ]] && rm -rf -- "$d"; done

# ---------------------------------------------------------------------------------------------------
# parallel: concurrent invocations do not collide.
# ---------------------------------------------------------------------------------------------------
pids=()
for k in 1 2 3; do
    ( run_case "parallel-$k" 0 --ifaces vcan0,vcan1 -- env FRAMES=500 bash "$WORK/can-frames.sh" > /dev/null 2>&1 ) &
    pids+=($!)
done
par_ok=1
for k in 1 2 3; do wait "${pids[$((k - 1))]}" || par_ok=0; done
for k in 1 2 3; do grep -q '^RECEIVED_VCAN0 1001 EXPECTED 1001$' "$WORK/parallel-$k.out" 2>/dev/null || par_ok=0; done
if ((par_ok)); then
    pass "3 parallel invocations, 1001/1001 frames each"
else
    fail "parallel: $(grep -h RECEIVED_VCAN0 "$WORK"/parallel-*.out 2>/dev/null | paste -sd';') (see $WORK)"
fi
for k in 1 2 3; do
    summary+=("$(printf '%-14s (concurrent)   %s' "parallel-$k" "$(grep -o 'boot->cmd [0-9.]*s.*total [0-9.]*s' "$WORK/parallel-$k.err" 2>/dev/null || true)")")
done

# ---------------------------------------------------------------------------------------------------
# sigint: interrupting the harness kills the VM and exits 130.
# ---------------------------------------------------------------------------------------------------
# A background job of a non-interactive shell starts with SIGINT ignored, and bash cannot trap a
# signal ignored on entry: restore the default disposition before exec, as a terminal's Ctrl-C
# to a foreground run would find it.
python3 -c 'import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); os.execv(sys.argv[1], sys.argv[1:])' \
    "$RUN" -- sleep 60 > "$WORK/sigint.out" 2> "$WORK/sigint.err" &
h=$!
for _ in $(seq 100); do grep -q 'results /' "$WORK/sigint.err" 2>/dev/null && break; sleep 0.1; done
resdir=$(grep -o 'results [^)]*' "$WORK/sigint.err" | awk '{print $2}')
for _ in $(seq 100); do [[ -e $resdir/t_cmd_start ]] && break; sleep 0.1; done
kill -INT "$h"
rc=0; wait "$h" || rc=$?
sleep 0.5
left=$(pgrep -f "uml_dir=$resdir/uml" || true)
if [[ $rc == 130 && -z $left && -n $resdir && ! -e $resdir ]]; then
    pass "SIGINT -> 130, VM gone, results dir removed"
else
    fail "sigint: rc=$rc leftover pids='$left' resdir=$resdir exists=$([[ -e $resdir ]] && echo yes || echo no)"
fi

# ---------------------------------------------------------------------------------------------------
echo
echo "Per-invocation timings (wall = whole run-in-vcan.sh call; boot->cmd = launch to command start):"
printf '  %s\n' "${summary[@]}"
echo
if ((failures)); then
    echo "SMOKE FAILED: $failures failure(s)"
    exit 1
fi
echo "SMOKE PASSED"
