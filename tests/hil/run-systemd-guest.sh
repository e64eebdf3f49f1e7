#!/usr/bin/env bash
# run-systemd-guest.sh: boot a qemu guest with systemd as PID 1 (Debian's kernel, the host's Debian
# userland as the root file system), install the comanip .deb there and check its units under the
# real service manager (tests/hil/systemd-guest-test.sh, docs/systemd.md "Under a real systemd").
#
# Usage: tests/hil/run-systemd-guest.sh COMANIP.deb [RESULTS_DIR]
#
# The root: the host's / over 9p, read-only, under an overlay whose upper layer is a tmpfs (the guest
# installs the package and creates users there; nothing reaches the host), with an empty tmpfs on
# /tmp (the host's /tmp/iceoryx2 would be stale state in the guest). The kernel, its 9p modules and
# the busybox initramfs come from run-in-qemu.sh's cache (filled by running it once when missing);
# the overlay module is added here. The guest boots `systemd.unit=comanip-guest-test.service`: a
# oneshot unit (sysinit, basic.target and nothing of the host's multi-user.target) that runs the
# checks, writes RESULTS_DIR/{test.log,rc} and powers the guest off.
#
# Exit code: the checks' (0 = all passed); 125 = harness failure (no kernel, the guest did not
# come up, no rc came back within HIL_SYSTEMD_TIMEOUT seconds, default 900).
set -euo pipefail

HERE=$(cd -- "$(dirname -- "${BASH_SOURCE[0]}")" && pwd)
readonly HERE
die() { printf '[systemd-guest] ERROR: %s\n' "$*" >&2; exit 125; }
log() { printf '[systemd-guest] %s\n' "$*" >&2; }

(($# >= 1)) || die "usage: $0 COMANIP.deb [RESULTS_DIR]"
deb=$(realpath -e -- "$1") || die "no such package: $1"
R=${2:-$(mktemp -d "${TMPDIR:-/tmp}/systemd-guest.XXXXXXXX")}
mkdir -p "$R"
R=$(realpath -e -- "$R")
[[ $R =~ ^/[A-Za-z0-9_./+@-]*$ ]] || die "results dir path '$R' has characters qemu cannot take"
timeout_s=${HIL_SYSTEMD_TIMEOUT:-900}

cache_root=${HIL_QEMU_CACHE:-${XDG_CACHE_HOME:-${HOME:-/root}/.cache}/comanip-hil-qemu}
kdir=$(find "$cache_root" -mindepth 1 -maxdepth 1 -name 'linux-image-*' -type d 2>/dev/null | sort -V | tail -n 1)
if [[ -z $kdir || ! -s $kdir/vmlinux ]]; then
    log "no cached guest kernel: preparing it with run-in-qemu.sh (once)"
    HIL_QUIET=1 "$HERE/run-in-qemu.sh" --timeout 60 -- true || die "run-in-qemu.sh could not prepare the kernel"
    kdir=$(find "$cache_root" -mindepth 1 -maxdepth 1 -name 'linux-image-*' -type d | sort -V | tail -n 1)
fi
kver=$(< "$kdir/kver")

# The initramfs: run-in-qemu's (static busybox, 9p modules) + overlay + our first stage.
work=$(mktemp -d "${TMPDIR:-/tmp}/systemd-guest-initramfs.XXXXXX")
trap 'rm -rf -- "$work"; [[ -n ${qemu_pid:-} ]] && kill -KILL "$qemu_pid" 2>/dev/null; true' EXIT
mkdir "$work/ir"
(cd "$work/ir" && cpio -id --quiet < "$kdir/initramfs.cpio") || die "cannot unpack $kdir/initramfs.cpio"
# overlay for the root; can, can-raw and vcan for the daemon's CAN sockets (the guest has no
# module tree of its own: the host root's /lib/modules is not this kernel's).
for want in overlay can can-raw vcan; do
    while read -r f; do
        m=${f##*/}
        m=${m%%.ko*}
        grep -qx "$m" "$work/ir/mods/order" && continue
        case $f in
            *.ko) cp "$f" "$work/ir/mods/$m.ko" ;;
            *.ko.xz) xz -dc "$f" > "$work/ir/mods/$m.ko" ;;
            *.ko.zst) zstd -qdc "$f" > "$work/ir/mods/$m.ko" ;;
            *) die "unsupported module file $f" ;;
        esac
        echo "$m" >> "$work/ir/mods/order"
    done < <(modprobe -d "$kdir/root" -S "$kver" --show-depends "$want" 2>/dev/null | awk '$1 == "insmod" { print $2 }')
done
cat > "$work/ir/init" <<'EOF'
#!/bin/busybox sh
/bin/busybox mkdir -p /sbin /usr/bin /usr/sbin
/bin/busybox --install -s
export PATH=/bin:/sbin:/usr/bin:/usr/sbin
mount -t proc proc /proc
mount -t sysfs sysfs /sys
mount -t devtmpfs devtmpfs /dev 2>/dev/null
say() { echo "[systemd-guest] $*" > /dev/console; }
halt_now() { echo b > /proc/sysrq-trigger; sleep 5; reboot -f; while :; do sleep 60; done; }
for m in $(cat /mods/order); do
    [ -d /sys/module/$m ] && continue
    insmod /mods/$m.ko || { say "SETUP FAILED: insmod $m"; halt_now; }
done
opts=trans=virtio,version=9p2000.L,msize=262144
mkdir -p /lower /rw
mount -t 9p -o $opts,ro,cache=loose hostroot /lower || { say "SETUP FAILED: 9p host root"; halt_now; }
mount -t tmpfs -o mode=0755 tmpfs /rw
mkdir -p /rw/upper /rw/work
mount -t overlay overlay -o lowerdir=/lower,upperdir=/rw/upper,workdir=/rw/work /newroot ||
    { say "SETUP FAILED: overlay root"; halt_now; }
mount -t tmpfs -o mode=1777,nosuid,nodev tmpfs /newroot/tmp
mkdir -p /newroot/hilres
mount -t 9p -o $opts hilres /newroot/hilres || { say "SETUP FAILED: 9p results dir"; halt_now; }
cp /newroot/hilres/comanip-guest-test.service /newroot/etc/systemd/system/
# The host root is a container image: without this file systemd believes it runs in docker and
# ignores the kernel command line (systemd.unit=). The overlay hides it from the guest only.
rm -f /newroot/.dockerenv
mount --move /dev /newroot/dev
mount --move /proc /newroot/proc
mount --move /sys /newroot/sys
exec switch_root /newroot /lib/systemd/systemd systemd.unit=comanip-guest-test.service
say "SETUP FAILED: switch_root"
halt_now
EOF
chmod 0755 "$work/ir/init"
(cd "$work/ir" && find . | LC_ALL=C sort | cpio -o -H newc --quiet > "$work/initramfs.cpio") || die "cpio failed"

cp "$deb" "$R/comanip.deb"
cp "$HERE/systemd-guest-test.sh" "$R/systemd-guest-test.sh"
cat > "$R/comanip-guest-test.service" <<'EOF'
[Unit]
Description=comanip: the package's units under systemd (tests/hil/systemd-guest-test.sh)
After=basic.target

[Service]
Type=oneshot
ExecStart=/bin/bash /hilres/systemd-guest-test.sh
StandardOutput=file:/hilres/test.log
StandardError=inherit
EOF
rm -f "$R/rc" "$R/test.log"

log "booting qemu (kernel $kver, tcg, 2 vCPUs, systemd as PID 1; results $R)"
t0=$SECONDS
qemu-system-x86_64 -accel tcg -cpu max -smp 2 -m 1536 -M pc -nodefaults -no-user-config \
    -display none -monitor none -no-reboot -serial "file:$R/boot.log" \
    -kernel "$kdir/vmlinux" -initrd "$work/initramfs.cpio" \
    -append "console=ttyS0 panic=-1 rdinit=/init systemd.unit=comanip-guest-test.service fstab=no systemd.show_status=1 systemd.journald.forward_to_console=0 net.ifnames=0" \
    -virtfs "local,path=/,mount_tag=hostroot,security_model=none,readonly=on,multidevs=remap" \
    -virtfs "local,path=$R,mount_tag=hilres,security_model=none,multidevs=remap" \
    < /dev/null > "$R/qemu.out" 2>&1 &
qemu_pid=$!
while kill -0 "$qemu_pid" 2>/dev/null; do
    if ((SECONDS - t0 > timeout_s)); then
        kill -KILL "$qemu_pid" 2>/dev/null || true
        tail -n 30 "$R/boot.log" >&2 || true
        die "no result within ${timeout_s}s (HIL_SYSTEMD_TIMEOUT); console in $R/boot.log"
    fi
    sleep 1
done
qemu_pid=
log "guest ran $((SECONDS - t0)) s"
[[ -s $R/test.log ]] && cat "$R/test.log"
[[ -s $R/rc ]] || { tail -n 40 "$R/boot.log" >&2; die "the guest wrote no rc; console in $R/boot.log"; }
exit "$(< "$R/rc")"
