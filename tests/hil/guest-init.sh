#!/bin/bash
# guest-init.sh: PID 1 inside the user-mode-linux (UML) guest started by run-in-vcan.sh.
#
# Do not run this on the host. run-in-vcan.sh copies it into the per-run results directory R (so it
# is executable whatever the checkout's file modes are), prepares the files it reads there, and boots
#   linux.uml ... rootfstype=hostfs rootflags=/ ro init=R/init HIL_RESULTS_HOST=R
# (unknown key=value kernel parameters become init's environment).
#
# The guest sees the host root filesystem read-only through hostfs. Files prepared by the host in R:
#   params.sh    HIL_TIMEOUT, HIL_CWD, HIL_HOSTNAME, HIL_OVERLAY_DIRS, HIL_RW_DIRS, HIL_IFACES_LIST, ...
#   skel/dev     /dev/fd, /dev/std{in,out,err} links and the /dev/shm, /dev/pts, /dev/mqueue dirs
#   fstab.base   proc, sysfs, devpts, mqueue, tmpfs on /dev/shm and on /run
#   skel/run     /run/hil (results mount point), overlay upper/work dirs (mode/owner of the host
#                dirs), /run/hil-mods/lib/modules -> /usr/lib/uml/modules (a modprobe root)
#   fstab.hil    hostfs R on /run/hil (read-write), the overlays, the --rw hostfs mounts
#   ip.batch     lo up, `link add dev vcanN type vcan`, `link set dev vcanN up`
#   env.sh       the caller's exported environment; argv: the command, NUL-separated
# and it reads back: stdout, stderr, rc (exit code), t_init_start/t_cmd_start/t_cmd_end (timestamps),
# setup-error (why setup failed). The guest writes them through the read-write hostfs mount /run/hil.
#
# Why batches (cp -a of a skeleton, mount -a, modprobe -a, ip -batch): every exec costs about 50 ms
# under UML (each guest process is a ptraced host process), so 30 separate commands cost 1.5 s.
#
# Error policy: this script never exits (PID 1 exiting panics the kernel). A setup failure is written
# to /run/hil/setup-error (when that mount exists) and to the console (R/boot.log), NO rc file is
# written, and the guest powers off; the host then fails with 125. A failure is never a skip.
#
# Deliberately no `set -e`: errors are handled explicitly so that the guest always powers off.
set -uo pipefail
shopt -s nullglob
T_INIT=$EPOCHREALTIME   # when the kernel handed over to us; written to t_init_start below

export PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
umask 022

readonly G=/run/hil                          # the results dir, read-write, inside the guest
HOST_R=${HIL_RESULTS_HOST:-${0%/*}}          # the results dir's host path (readable via the ro root)

say() { echo "[hil-guest] $*"; }   # PID 1's stdout is the UML console -> R/boot.log on the host

# Timestamp files with bash's own clock (no fork): seconds.micros since the epoch. UML takes its
# wall clock from the host's, so these compare with host time stamps.
stamp() { echo "${EPOCHREALTIME}" > "$G/$1" 2>/dev/null || true; }

# mounted PATH: is PATH a mount point? (reads /proc/mounts with builtins only)
mounted() {
    local _dev mnt _rest
    while read -r _dev mnt _rest; do [[ $mnt == "$1" ]] && return 0; done < /proc/mounts
    return 1
}

poweroff_now() {
    # hostfs writes through to the host at write() time; sync anyway for anything else.
    sync
    # reboot(MAGIC1, MAGIC2, LINUX_REBOOT_CMD_POWER_OFF); 169 = reboot on x86_64. perl-base is
    # Essential in Debian; /sbin/poweroff here is systemctl, which wants a running systemd.
    perl -e 'syscall(169, 0xfee1dead, 672274793, 0x4321fedc)' 2>/dev/null
    echo o > /proc/sysrq-trigger 2>/dev/null     # fallback: magic SysRq power-off
    while :; do sleep 60; done                   # last resort: the host watchdog kills the VM
}

# A setup step failed: record why, never write rc, power off.
fatal() {
    say "SETUP FAILED: $*"
    mounted "$G" 2>/dev/null && echo "$*" >> "$G/setup-error"
    poweroff_now
}

# shellcheck source=/dev/null
source "$HOST_R/params.sh" || fatal "cannot read $HOST_R/params.sh"

# --- 1. /dev extras, proc, sysfs, devpts, mqueue, /dev/shm and /run tmpfs -----------------------------
# CONFIG_DEVTMPFS_MOUNT=y has mounted devtmpfs on /dev already (checked after /proc is up).
if ! cp -a "$HOST_R/skel/dev/." /dev/ 2>/dev/null; then
    mount -t devtmpfs devtmpfs /dev || fatal "mount devtmpfs on /dev"
    cp -a "$HOST_R/skel/dev/." /dev/ || fatal "populate /dev"
fi
mount -a -T "$HOST_R/fstab.base" || fatal "mount -a -T fstab.base (proc, sys, devpts, mqueue, shm, run)"
cp -a "$HOST_R/skel/run/." /run/ || fatal "populate /run"

# --- 2. kernel modules: can, can-raw, can-dev, vcan (+ overlay) ---------------------------------------
read -r KVER < /proc/sys/kernel/osrelease
modprobe_all() {   # modprobe -a resolves the order (can before can-raw, can-dev before vcan)
    modprobe -d /run/hil-mods -S "$1" -a can_raw vcan overlay 2> /run/hil-modprobe.err
}
if ! modprobe_all "$KVER"; then
    # Slow, robust path: find a module tree (this kernel's, else the newest one that has CAN modules)
    # and insmod file by file; overlay is optional. A mismatched tree fails loudly at insmod.
    say "modprobe failed ($(< /run/hil-modprobe.err)); falling back to insmod"
    MODDIR=${HIL_MODULES_DIR:-}
    if [[ -z $MODDIR ]]; then
        for d in "/usr/lib/uml/modules/$KVER" /usr/lib/uml/modules/*; do
            f=("$d"/kernel/net/can/can.ko*)
            if ((${#f[@]})); then MODDIR=$d; break; fi
        done
    fi
    [[ -n $MODDIR ]] || fatal "no UML module tree with CAN modules under /usr/lib/uml/modules (kernel $KVER)"
    for spec in can:net/can/can.ko can_raw:net/can/can-raw.ko can_dev:drivers/net/can/dev/can-dev.ko \
        vcan:drivers/net/can/vcan.ko overlay:fs/overlayfs/overlay.ko; do
        name=${spec%%:*} rel=${spec#*:}
        [[ -d /sys/module/$name ]] && continue          # built in or already loaded
        f=("$MODDIR/kernel/$rel"*)
        if ((${#f[@]} == 0)); then
            [[ $name == overlay ]] && continue
            fatal "module $rel not found under $MODDIR/kernel"
        fi
        out=$(insmod "${f[0]}" 2>&1) || { [[ $name == overlay ]] || fatal "insmod ${f[0]}: $out"; }
    done
fi

# --- 3. results channel (hostfs rw), private /tmp + /var/tmp (overlay), --rw dirs (hostfs rw) ----------
mount -a -T "$HOST_R/fstab.hil" 2>/run/hil-mount.err
mounted "$G" || fatal "hostfs mount of $HOST_R on $G failed: $(< /run/hil-mount.err)"
echo "$T_INIT" > "$G/t_init_start"
for d in "${HIL_RW_DIRS[@]}"; do
    mounted "$d" || fatal "hostfs mount of $d (--rw) failed: $(< /run/hil-mount.err)"
done
for d in "${HIL_OVERLAY_DIRS[@]}"; do
    mounted "$d" && continue
    # Fallback: an empty tmpfs. Writable, but the host's files under $d are hidden in the guest.
    say "warning: overlay on $d failed ($(< /run/hil-mount.err)); using an empty tmpfs"
    mount -t tmpfs -o mode=1777 tmpfs "$d" || fatal "mount tmpfs on $d"
done

# --- 4. network: lo and the vcan interfaces; hostname ------------------------------------------------
ip -batch "$G/ip.batch" > /run/hil-ip.err 2>&1 || fatal "ip -batch failed: $(< /run/hil-ip.err)"
[[ -n ${HIL_HOSTNAME:-} ]] && echo "$HIL_HOSTNAME" > /proc/sys/kernel/hostname

# --- 5. run the command -------------------------------------------------------------------------------
# In a subshell (a fork, no extra exec): drop PID 1's environment, load the caller's, cd to the
# caller's directory, then exec `timeout` (0 = no limit; 124 on expiry, 137 if it had to SIGKILL),
# which execs the command (127 if not found). 125 = the launch itself failed.
stamp t_cmd_start
(
    set +u
    while read -r v; do unset "$v"; done <<< "$(compgen -e)"
    # shellcheck source=/dev/null
    source "$G/env.sh" || { echo "[hil-guest] cannot load $G/env.sh" >&2; exit 125; }
    export PATH=${PATH:+$PATH:}/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
    export HOME=${HOME:-/root} HIL_IN_GUEST=1 HIL_MODE=uml
    # TMPDIR must be writable: the host's value may point into the read-only root.
    if [[ -n ${TMPDIR:-} && ! -w $TMPDIR ]]; then export TMPDIR=/tmp; fi
    cd -- "$HIL_CWD" || { echo "[hil-guest] cannot cd to $HIL_CWD inside the guest" >&2; exit 125; }
    mapfile -d '' -t argv < "$G/argv"
    exec timeout --kill-after="${HIL_KILL_AFTER:-10}" "$HIL_TIMEOUT" "${argv[@]}"
) < /dev/null >> "$G/stdout" 2>> "$G/stderr"
rc=$?
stamp t_cmd_end
((rc == 124)) && echo "[hil-guest] command timed out after ${HIL_TIMEOUT}s (exit 124)" >> "$G/stderr"

# --- 6. exit code back to the host, then power off ------------------------------------------------------
# The host reads rc only after the VM process has exited, so a plain write is enough.
echo "$rc" > "$G/rc" || say "ERROR: cannot write the exit code"
poweroff_now
