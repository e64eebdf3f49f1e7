#!/bin/bash
# qemu-guest-init.sh: PID 1 inside the qemu guest started by run-in-qemu.sh (second stage).
#
# Do not run this on the host. run-in-qemu.sh copies it into the per-run results dir R as R/init2.
# The initramfs's first stage (busybox) has loaded the 9p modules, mounted the host root read-only on
# /, a tmpfs on /run, R read-write on /run/hil (9p tag `hilres`), moved /dev, /proc and /sys, and
# chrooted here. Files it reads in R: params.sh (HIL_TIMEOUT, HIL_CWD, HIL_RW_DIRS, HIL_MODPROBES,
# HIL_KMOD_ROOT, HIL_KVER), env.sh (the caller's exported environment), argv (NUL-separated). It
# writes back: stdout, stderr, rc, t_cmd_start / t_cmd_end, setup-error.
#
# Error policy as guest-init.sh: never exit (PID 1); a setup failure goes to setup-error, no rc is
# written, the guest reboots (qemu runs with -no-reboot, so it exits) and the host fails with 125.
set -uo pipefail
shopt -s nullglob
export PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
umask 022
readonly G=/run/hil
say() { echo "[hil-guest] $*" > /dev/console; }
stamp() { echo "${EPOCHREALTIME}" > "$G/$1" 2>/dev/null || true; }
halt_now() {
    sync
    # reboot(2) with LINUX_REBOOT_CMD_RESTART; qemu's -no-reboot turns it into qemu's exit.
    echo b > /proc/sysrq-trigger 2>/dev/null
    perl -e 'syscall(169, 0xfee1dead, 672274793, 0x01234567)' 2>/dev/null
    while :; do sleep 60; done
}
fatal() {
    say "SETUP FAILED: $*"
    echo "$*" >> "$G/setup-error"
    halt_now
}

# shellcheck source=/dev/null
source "$G/params.sh" || fatal "cannot read $G/params.sh"

# --- mounts: devpts, /dev/shm, /tmp, /var/tmp (empty tmpfs: the host's are not visible), --rw shares -----
mkdir -p /dev/pts /dev/shm
mount -t devpts -o gid=5,mode=620,ptmxmode=666 devpts /dev/pts 2>/dev/null
mount -t tmpfs -o mode=1777,nosuid,nodev shm /dev/shm || fatal "tmpfs on /dev/shm"
# /tmp and /var/tmp: overlays whose lower layer is the host dir (host-built files there stay
# visible, e.g. a CARGO_TARGET_DIR under /tmp) and whose upper layer is a tmpfs (writes stay in
# the guest), as in the UML guest; an empty tmpfs when overlayfs is not available.
modprobe -q -d "$HIL_KMOD_ROOT" -S "$HIL_KVER" overlay 2>/dev/null
n=0
for d in /tmp /var/tmp; do
    n=$((n + 1))
    mkdir -p "/run/hil-ovl/$n/upper" "/run/hil-ovl/$n/work"
    chmod 1777 "/run/hil-ovl/$n/upper"
    mount -t overlay overlay -o "lowerdir=$d,upperdir=/run/hil-ovl/$n/upper,workdir=/run/hil-ovl/$n/work" "$d" 2>/dev/null ||
        mount -t tmpfs -o mode=1777 tmpfs "$d" || fatal "tmpfs on $d"
done
[[ -e /dev/fd ]] || ln -s /proc/self/fd /dev/fd
n=0
for d in "${HIL_RW_DIRS[@]}"; do
    mkdir -p "$d" 2>/dev/null   # a --rw dir under /tmp: its mount point in the empty tmpfs
    mount -t 9p -o trans=virtio,version=9p2000.L,msize=262144 "hilrw$n" "$d" 2> /run/hil-mount.err ||
        fatal "9p mount of --rw $d: $(< /run/hil-mount.err)"
    n=$((n + 1))
done
[[ -n ${HIL_HOSTNAME:-} ]] && echo "$HIL_HOSTNAME" > /proc/sys/kernel/hostname

# --- modules from the unpacked Debian kernel package (modprobe resolves the dependencies) ---------------
for spec in "${HIL_MODPROBES[@]}"; do
    read -r -a words <<< "$spec"
    modprobe -d "$HIL_KMOD_ROOT" -S "$HIL_KVER" "${words[@]}" 2> /run/hil-modprobe.err ||
        fatal "modprobe $spec: $(< /run/hil-modprobe.err)"
done
# Device nodes appear through devtmpfs; give udev-less drivers a moment (bounded).
if ((${#HIL_MODPROBES[@]})); then udevadm settle -t 5 > /dev/null 2>&1 || true; fi

# --- the command ----------------------------------------------------------------------------------------
stamp t_cmd_start
(
    set +u
    while read -r v; do unset "$v"; done <<< "$(compgen -e)"
    # shellcheck source=/dev/null
    source "$G/env.sh" || { echo "[hil-guest] cannot load $G/env.sh" >&2; exit 125; }
    export PATH=${PATH:+$PATH:}/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
    export HOME=${HOME:-/root} HIL_IN_GUEST=1 HIL_MODE=qemu
    if [[ -n ${TMPDIR:-} && ! -w $TMPDIR ]]; then export TMPDIR=/tmp; fi
    cd -- "$HIL_CWD" || { echo "[hil-guest] cannot cd to $HIL_CWD inside the guest" >&2; exit 125; }
    mapfile -d '' -t argv < "$G/argv"
    exec timeout --kill-after=10 "$HIL_TIMEOUT" "${argv[@]}"
) < /dev/null >> "$G/stdout" 2>> "$G/stderr"
rc=$?
stamp t_cmd_end
((rc == 124)) && echo "[hil-guest] command timed out after ${HIL_TIMEOUT}s (exit 124)" >> "$G/stderr"
echo "$rc" > "$G/rc" || say "ERROR: cannot write the exit code"
halt_now
