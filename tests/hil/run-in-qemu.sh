#!/usr/bin/env bash
# run-in-qemu.sh: run a command inside a qemu guest that boots Debian's own kernel (with its full
# module tree: media drivers such as `vivid`), and return the command's exit code.
#
# Usage: tests/hil/run-in-qemu.sh [--modprobe 'NAME [PARAM=VALUE...]']... [--timeout SECS] [--rw DIR]...
#                                 -- <command> [args...]
#
# Why qemu and not user-mode-linux (run-in-vcan.sh): the host kernel has no V4L2 devices, and the
# UML module tree has no media drivers at all. Debian's distribution kernel has `vivid` (a virtual
# V4L2 capture device); it boots in qemu by software emulation (TCG: /dev/kvm is not usable here).
#
# What it does (docs/hil.md, "qemu guest"):
#   1. installs what is missing (qemu-system-x86, busybox-static, cpio, kmod, xz-utils) with apt-get;
#   2. fetches the kernel package that `linux-image-amd64` depends on (`apt-get download`), unpacks it
#      with `dpkg -x` into a cache dir, runs `depmod` on its module tree, extracts the uncompressed
#      vmlinux from vmlinuz (qemu boots it through PVH: no decompression under emulation) and builds a
#      small busybox initramfs that loads the 9p modules. All cached per kernel version;
#   3. boots `qemu-system-x86_64 -accel tcg` with the host root shared read-only over 9p (the guest
#      chroots into it, so host-built binaries run at their host paths), a per-run results dir R
#      shared read-write, and each --rw DIR shared read-write at its own path;
#   4. the guest (tests/hil/qemu-guest-init.sh) loads each --modprobe module from the unpacked tree,
#      runs the command with the caller's environment and working directory, and writes its exit
#      code into R; the host returns it.
#
# Exit code: the command's own. 124 = the command hit --timeout. 125 = harness failure (bad usage,
# packages missing and not installable, no kernel, the VM did not start, a module did not load, no
# exit code came back, watchdog): it is never turned into 0 or a skip.
#
# Environment knobs (all optional):
#   HIL_QEMU_MEM=1024        guest memory, MiB
#   HIL_QEMU_CACHE=dir       cache of unpacked kernels (default ${XDG_CACHE_HOME:-$HOME/.cache}/comanip-hil-qemu)
#   HIL_QEMU_KERNEL_PKG=name kernel package (default: what linux-image-amd64 depends on; else the newest cached)
#   HIL_QEMU_CMDLINE="..."   extra kernel parameters (e.g. "loglevel=8")
#   HIL_BOOT_TIMEOUT=120     seconds allowed from launch until the command starts, else 125
#   HIL_RESULTS_PARENT=dir   where the per-run results dir is created (default ${TMPDIR:-/tmp})
#   HIL_KEEP_RESULTS=1       keep the results dir (always kept on a harness failure)
#   HIL_QUIET=1              no [hil] status lines on stderr (errors are still printed)
#   HIL_STREAM=0             print the guest's stdout/stderr after the run instead of live
#   HIL_ENV_DROP="A B"       extra caller variables NOT to pass into the guest
set -euo pipefail

HERE=$(cd -- "$(dirname -- "${BASH_SOURCE[0]}")" && pwd)
readonly HERE
readonly HARNESS_FAIL=125

log() { [[ ${HIL_QUIET:-0} == 1 ]] || printf '[hil] %s\n' "$*" >&2; }
die() { printf '[hil] ERROR: %s\n' "$*" >&2; exit "$HARNESS_FAIL"; }

usage() {
    cat <<'EOF'
Usage: run-in-qemu.sh [--modprobe 'NAME [PARAM=VALUE...]']... [--timeout SECS] [--rw DIR]... -- <command> [args...]

  --modprobe SPEC  load module NAME (and its dependencies) with these parameters in the guest
                   before the command (repeatable), e.g. --modprobe 'vivid n_devs=1 node_types=1'
  --timeout SECS   kill the command after SECS seconds, exit code 124 (default: 600; 0 = none)
  --rw DIR         share host directory DIR read-write at the same path in the guest (repeatable);
                   everything else of the host root is read-only; /tmp and /var/tmp are private
                   overlays on the host's (writes stay in the guest); /run and /dev/shm are empty tmpfs.

Exit code: the command's; 124 on timeout; 125 on a harness failure. See docs/hil.md.
EOF
}

# ---------------------------------------------------------------------------------------------------
# Arguments
# ---------------------------------------------------------------------------------------------------
# Paths that go into qemu's -virtfs options and the guest's mount list must not contain separators.
plain_path() { [[ $1 =~ ^/[A-Za-z0-9_./+@-]*$ ]]; }

timeout_s=600
rw_dirs=()
modprobes=()
while (($#)); do
    case $1 in
        --modprobe) (($# >= 2)) || die "--modprobe needs a value"; modprobes+=("$2"); shift 2 ;;
        --modprobe=*) modprobes+=("${1#*=}"); shift ;;
        --timeout) (($# >= 2)) || die "--timeout needs a value"; timeout_s=$2; shift 2 ;;
        --timeout=*) timeout_s=${1#*=}; shift ;;
        --rw) (($# >= 2)) || die "--rw needs a value"; rw_dirs+=("$2"); shift 2 ;;
        --rw=*) rw_dirs+=("${1#*=}"); shift ;;
        -h | --help) usage; exit 0 ;;
        --) shift; break ;;
        -*) usage >&2; die "unknown option: $1" ;;
        *) break ;;
    esac
done
(($#)) || { usage >&2; die "no command given"; }

[[ $timeout_s =~ ^[0-9]+$ ]] || die "--timeout must be a whole number of seconds, got '$timeout_s'"
for m in "${modprobes[@]}"; do
    [[ $m =~ ^[A-Za-z0-9_-]+([[:space:]]+[A-Za-z0-9_.]+=[A-Za-z0-9_.,-]*)*$ ]] ||
        die "bad --modprobe '$m' (NAME [PARAM=VALUE...], values of [A-Za-z0-9_.,-])"
done
for i in "${!rw_dirs[@]}"; do
    d=$(realpath -e -- "${rw_dirs[$i]}" 2>/dev/null) || die "--rw ${rw_dirs[$i]}: no such directory"
    [[ -d $d ]] || die "--rw $d is not a directory"
    plain_path "$d" || die "--rw $d: use a path of [A-Za-z0-9_./+@-] only (qemu -virtfs syntax)"
    rw_dirs[i]=$d
done
mem=${HIL_QEMU_MEM:-1024}
[[ $mem =~ ^[0-9]+$ ]] || die "HIL_QEMU_MEM must be MiB (a whole number), got '$mem'"
boot_timeout=${HIL_BOOT_TIMEOUT:-120}
[[ $boot_timeout =~ ^[0-9]+$ ]] || die "HIL_BOOT_TIMEOUT must be whole seconds"

# ---------------------------------------------------------------------------------------------------
# Packages: install only what is missing (we are normally root; apt works). As run-in-vcan.sh.
# ---------------------------------------------------------------------------------------------------
apt_install() {
    local log_file
    [[ $(id -u) == 0 ]] || die "missing packages: $*; install them (as root: apt-get install $*)"
    command -v apt-get > /dev/null || die "missing packages: $* and no apt-get"
    log "installing missing packages: $*"
    log_file=$(mktemp "${TMPDIR:-/tmp}/hil-apt.XXXXXX")
    if ! (
        flock -w 600 9 || exit 1
        export DEBIAN_FRONTEND=noninteractive
        apt_opts=(-y -q --no-install-recommends -o DPkg::Lock::Timeout=600)
        apt-get install "${apt_opts[@]}" "$@" > "$log_file" 2>&1 ||
            { apt-get update -q >> "$log_file" 2>&1 && apt-get install "${apt_opts[@]}" "$@" >> "$log_file" 2>&1; }
    ) 9> /tmp/hil-apt.lock; then
        tail -n 30 "$log_file" >&2
        die "apt-get install $* failed (log: $log_file)"
    fi
    rm -f "$log_file"
}

ensure_tools() {
    local pkgs=()
    command -v qemu-system-x86_64 > /dev/null || pkgs+=(qemu-system-x86)
    # The busybox in the initramfs must be static (it runs before any library is reachable): the
    # `busybox` package's /bin/busybox is dynamic, `busybox-static` replaces it.
    dpkg-query -W -f='${Status}' busybox-static 2>/dev/null | grep -q 'ok installed' || pkgs+=(busybox-static)
    command -v cpio > /dev/null || pkgs+=(cpio)
    command -v depmod > /dev/null && command -v modprobe > /dev/null || pkgs+=(kmod)
    command -v xz > /dev/null || pkgs+=(xz-utils)
    command -v timeout > /dev/null || pkgs+=(coreutils)
    ((${#pkgs[@]} == 0)) || apt_install "${pkgs[@]}"
}

# ---------------------------------------------------------------------------------------------------
# The kernel: package -> cache/<pkg>/{root,vmlinux,initramfs.cpio,kver}
# ---------------------------------------------------------------------------------------------------
cache_root=${HIL_QEMU_CACHE:-${XDG_CACHE_HOME:-${HOME:-/root}/.cache}/comanip-hil-qemu}

# The modules that give the guest its 9p shares, in load order (each needs the ones before it).
readonly NINEP_MODULES="netfs fscache 9pnet virtio_ring virtio virtio_pci_legacy_dev virtio_pci_modern_dev virtio_pci 9pnet_virtio 9p"

kernel_pkg_name() {
    local pkg=${HIL_QEMU_KERNEL_PKG:-}
    if [[ -z $pkg ]]; then
        pkg=$(apt-cache depends linux-image-amd64 2>/dev/null | awk '/Depends: linux-image-/ { print $2; exit }')
    fi
    if [[ -z $pkg ]]; then
        # No apt lists (fresh machine): a cached kernel will do; else refresh the lists once.
        pkg=$(find "$cache_root" -mindepth 2 -maxdepth 2 -name kver -printf '%h\n' 2>/dev/null | sort -V | tail -n 1)
        pkg=${pkg##*/}
    fi
    if [[ -z $pkg && $(id -u) == 0 ]]; then
        log "apt-get update (no package list names the kernel of linux-image-amd64)"
        apt-get update -q > /dev/null 2>&1 || true
        pkg=$(apt-cache depends linux-image-amd64 2>/dev/null | awk '/Depends: linux-image-/ { print $2; exit }')
    fi
    [[ -n $pkg ]] || die "cannot tell which kernel package linux-image-amd64 depends on (apt-cache depends), and none is cached in $cache_root"
    [[ $pkg =~ ^[a-z0-9.+-]+$ ]] || die "odd kernel package name '$pkg'"
    echo "$pkg"
}

# prepare_kernel PKG: fills $cache_root/PKG once (under a lock; parallel runs wait).
prepare_kernel() {
    local pkg=$1 dir=$cache_root/$1 tmp deb kver vmlinuz off m f
    [[ -s $dir/kver && -s $dir/vmlinux && -s $dir/initramfs.cpio ]] && return 0
    mkdir -p "$cache_root" || die "cannot create the kernel cache $cache_root"
    exec 8> "$cache_root/.lock"
    flock -w 900 8 || die "timed out waiting for the kernel cache lock $cache_root/.lock"
    if [[ -s $dir/kver && -s $dir/vmlinux && -s $dir/initramfs.cpio ]]; then exec 8>&-; return 0; fi
    tmp=$(mktemp -d "$cache_root/.prep.XXXXXX")
    log "fetching and unpacking $pkg into $dir (once per kernel version)"
    # apt-get download writes into the current dir; as root it warns that _apt cannot read it.
    (cd "$tmp" && apt-get download -q "$pkg" > "$tmp/download.log" 2>&1) ||
        { [[ $(id -u) == 0 ]] && apt-get update -q > /dev/null 2>&1 &&
            (cd "$tmp" && apt-get download -q "$pkg" >> "$tmp/download.log" 2>&1); } ||
        { tail -n 20 "$tmp/download.log" >&2; rm -rf "$tmp"; die "apt-get download $pkg failed"; }
    deb=$(compgen -G "$tmp/*.deb" | head -n 1) || true
    [[ -n $deb ]] || { rm -rf "$tmp"; die "apt-get download $pkg left no .deb"; }
    dpkg -x "$deb" "$tmp/root" || { rm -rf "$tmp"; die "dpkg -x $deb failed"; }
    rm -f "$deb"
    vmlinuz=$(compgen -G "$tmp/root/boot/vmlinuz-*" | head -n 1) || true
    [[ -n $vmlinuz ]] || { rm -rf "$tmp"; die "$pkg has no /boot/vmlinuz-*"; }
    kver=${vmlinuz##*/vmlinuz-}
    local moddir
    for moddir in "$tmp/root/lib/modules/$kver" "$tmp/root/usr/lib/modules/$kver"; do [[ -d $moddir ]] && break; done
    [[ -d $moddir ]] || { rm -rf "$tmp"; die "$pkg has no module tree for $kver"; }
    # The guest's modprobe runs with -d <root>: it wants <root>/lib/modules/<kver>.
    if [[ $moddir == "$tmp/root/usr/lib/modules/$kver" && ! -e $tmp/root/lib/modules ]]; then
        mkdir -p "$tmp/root/lib" && ln -s ../usr/lib/modules "$tmp/root/lib/modules"
    fi
    depmod -b "$tmp/root" "$kver" || { rm -rf "$tmp"; die "depmod -b $tmp/root $kver failed"; }
    # The uncompressed kernel: the payload of vmlinuz is an xz stream (magic FD 37 7A 58 5A 00);
    # xz complains about the trailing bytes after it, so judge by the ELF magic of the result.
    off=$(LC_ALL=C grep -obUaP '\xFD7zXZ\x00' "$vmlinuz" | head -n 1 | cut -d: -f1) || true
    [[ -n $off ]] || { rm -rf "$tmp"; die "no xz stream in $vmlinuz (not an xz-compressed kernel?)"; }
    tail -c +"$((off + 1))" "$vmlinuz" | xz -dc > "$tmp/vmlinux" 2>/dev/null || true
    [[ $(head -c 4 "$tmp/vmlinux" | od -An -tx1 | tr -d ' \n') == 7f454c46 ]] ||
        { rm -rf "$tmp"; die "could not extract an ELF vmlinux from $vmlinuz"; }
    # The initramfs: static busybox, the 9p modules, and a first-stage init.
    mkdir -p "$tmp/initramfs/bin" "$tmp/initramfs/mods" "$tmp/initramfs/newroot" \
        "$tmp/initramfs/proc" "$tmp/initramfs/sys" "$tmp/initramfs/dev"
    cp /bin/busybox "$tmp/initramfs/bin/busybox"
    : > "$tmp/initramfs/mods/order"
    for m in $NINEP_MODULES; do
        f=$(modprobe -d "$tmp/root" -S "$kver" --show-depends "$m" 2>/dev/null |
            awk -v m="$m" '$1 == "insmod" { p = $2 } END { print p }')
        if [[ -z $f ]]; then
            # Built into this kernel (modprobe prints "builtin"): nothing to load.
            modprobe -d "$tmp/root" -S "$kver" --show-depends "$m" 2>/dev/null | grep -q '^builtin' && continue
            rm -rf "$tmp"; die "module $m not found in $pkg"
        fi
        case $f in
            *.ko) cp "$f" "$tmp/initramfs/mods/$m.ko" ;;
            *.ko.xz) xz -dc "$f" > "$tmp/initramfs/mods/$m.ko" ;;
            *.ko.zst) zstd -qdc "$f" > "$tmp/initramfs/mods/$m.ko" ;;
            *) rm -rf "$tmp"; die "unsupported module file $f" ;;
        esac
        echo "$m" >> "$tmp/initramfs/mods/order"
    done
    write_stage1_init > "$tmp/initramfs/init"
    chmod 0755 "$tmp/initramfs/init"
    (cd "$tmp/initramfs" && find . | LC_ALL=C sort | cpio -o -H newc --quiet > "$tmp/initramfs.cpio") ||
        { rm -rf "$tmp"; die "cpio of the initramfs failed"; }
    rm -rf "$tmp/initramfs"
    echo "$kver" > "$tmp/kver"
    rm -rf "$dir"
    mv "$tmp" "$dir" || die "cannot move $tmp to $dir"
    # One kernel is enough (each unpacked tree is about 440 MB): drop those of older packages.
    for old in "$cache_root"/linux-image-*; do
        [[ -d $old && $old != "$dir" ]] || continue
        log "removing the older cached kernel $old"
        rm -rf -- "$old"
    done
    exec 8>&-
}

# The initramfs's /init (busybox sh): 9p modules, the shares, then the second stage in the chroot.
# It must never exit (PID 1 exiting panics the kernel, and panic=-1 ends qemu: the host then reports
# "no exit code came back").
write_stage1_init() {
    cat <<'EOF'
#!/bin/busybox sh
/bin/busybox mkdir -p /sbin /usr/bin /usr/sbin
/bin/busybox --install -s
export PATH=/bin:/sbin:/usr/bin:/usr/sbin
mount -t proc proc /proc
mount -t sysfs sysfs /sys
mount -t devtmpfs devtmpfs /dev 2>/dev/null
say() { echo "[hil-guest] $*" > /dev/console; }
halt_now() { echo b > /proc/sysrq-trigger; sleep 5; reboot -f; while :; do sleep 60; done; }
for m in $(cat /mods/order); do
    [ -d /sys/module/$m ] && continue
    insmod /mods/$m.ko || { say "SETUP FAILED: insmod $m"; halt_now; }
done
opts=trans=virtio,version=9p2000.L,msize=262144
mount -t 9p -o $opts,ro,cache=loose hostroot /newroot || { say "SETUP FAILED: 9p mount of the host root"; halt_now; }
mount -t tmpfs -o mode=0755,nosuid,nodev tmpfs /newroot/run || { say "SETUP FAILED: tmpfs on /run"; halt_now; }
mkdir -p /newroot/run/hil
mount -t 9p -o $opts hilres /newroot/run/hil || { say "SETUP FAILED: 9p mount of the results dir"; halt_now; }
mount --move /dev /newroot/dev || mount -t devtmpfs devtmpfs /newroot/dev
mount --move /proc /newroot/proc
mount --move /sys /newroot/sys
exec chroot /newroot /bin/bash /run/hil/init2
say "SETUP FAILED: cannot exec the second stage (/bin/bash in the host root)"
halt_now
EOF
}

# ---------------------------------------------------------------------------------------------------
# The run
# ---------------------------------------------------------------------------------------------------
R='' qemu_pid='' tail_pids=() keep=0

# shellcheck disable=SC2317,SC2329  # invoked by `trap cleanup EXIT`
cleanup() {
    local p
    if [[ -n $qemu_pid ]] && kill -0 "$qemu_pid" 2>/dev/null; then kill -KILL "$qemu_pid" 2>/dev/null || true; fi
    disown -a 2>/dev/null || true
    for p in "${tail_pids[@]}"; do kill "$p" 2>/dev/null || true; done
    if [[ -n $R && -d $R ]]; then
        if [[ $keep == 1 || ${HIL_KEEP_RESULTS:-0} == 1 ]]; then
            printf '[hil] results kept in %s\n' "$R" >&2
        else
            rm -rf -- "$R"
        fi
    fi
}

emit_array() {
    local name=$1
    shift
    printf '%s=(' "$name"
    (($#)) && printf '%q ' "$@"
    printf ')\n'
}
usecs() { echo "${1//[.,]/}"; }
elapsed() { awk -v a="${1/,/.}" -v b="${2/,/.}" 'BEGIN { printf "%.3f", b - a }'; }

qemu_fail() {
    keep=1
    printf '[hil] ERROR: %s\n' "$*" >&2
    if [[ -s $R/setup-error ]]; then
        printf '[hil] guest setup error:\n' >&2
        sed 's/^/[hil]   /' "$R/setup-error" >&2
    fi
    if [[ -s $R/boot.log ]]; then
        printf '[hil] last lines of the guest console (%s):\n' "$R/boot.log" >&2
        tail -n 25 "$R/boot.log" | sed 's/^/[hil]   /' >&2
    fi
    exit "$HARNESS_FAIL"
}

# The guest mounts empty tmpfs on these: a module tree or a working dir there would be hidden.
# (/tmp and /var/tmp are overlays on the host dirs: visible.)
hidden_in_guest() { [[ $1 == /run || $1 == /run/* || $1 == /dev/shm || $1 == /dev/shm/* ]]; }
ensure_tools
pkg=$(kernel_pkg_name)
kdir=$cache_root/$pkg
plain_path "$kdir" || die "kernel cache path $kdir: use a path of [A-Za-z0-9_./+@-] only (HIL_QEMU_CACHE)"
hidden_in_guest "$kdir" &&
    die "kernel cache $kdir is under a dir the guest replaces with an empty tmpfs (/run, /dev/shm); set HIL_QEMU_CACHE elsewhere"
prepare_kernel "$pkg"
kver=$(< "$kdir/kver")

cwd=$(pwd -P)
hidden_in_guest "$cwd" && die "the working dir $cwd is hidden in the guest (empty tmpfs on /run, /dev/shm): run from elsewhere"
parent=$(realpath -e -- "${HIL_RESULTS_PARENT:-${TMPDIR:-/tmp}}") || die "results parent does not exist"
trap cleanup EXIT
trap 'exit 130' INT
trap 'exit 143' TERM
R=$(mktemp -d "$parent/hil-qemu.XXXXXXXX") || die "mktemp -d in $parent failed"
plain_path "$R" || die "results dir path '$R' has characters qemu cannot take (set HIL_RESULTS_PARENT)"

cp "$HERE/qemu-guest-init.sh" "$R/init2"
printf '%s\0' "$@" > "$R/argv"
{
    emit_array HIL_RW_DIRS "${rw_dirs[@]}"
    emit_array HIL_MODPROBES "${modprobes[@]}"
    printf 'HIL_TIMEOUT=%q\n' "$timeout_s"
    printf 'HIL_CWD=%q\n' "$cwd"
    printf 'HIL_HOSTNAME=%q\n' "$(hostname 2>/dev/null || echo hil)"
    printf 'HIL_KMOD_ROOT=%q\n' "$kdir/root"
    printf 'HIL_KVER=%q\n' "$kver"
} > "$R/params.sh"
drop=" _ SHLVL PWD OLDPWD SHELLOPTS BASHOPTS BASH_ENV ENV PS1 PS2 PS4 PROMPT_COMMAND
    SSH_AUTH_SOCK SSH_AGENT_PID SSH_CONNECTION SSH_CLIENT SSH_TTY DISPLAY WAYLAND_DISPLAY
    XDG_RUNTIME_DIR DBUS_SESSION_BUS_ADDRESS TMUX TMUX_PANE STY HIL_IN_GUEST HIL_MODE ${HIL_ENV_DROP:-} "
drop=" ${drop//[$'\t\n']/ } "
{
    while IFS= read -r name; do
        [[ $name =~ ^[A-Za-z_][A-Za-z0-9_]*$ ]] || continue
        [[ $drop == *" $name "* ]] && continue
        printf 'export %s=%q\n' "$name" "${!name}"
    done < <(compgen -e)
} > "$R/env.sh"
: > "$R/stdout"
: > "$R/stderr"

virtfs=(-virtfs "local,path=/,mount_tag=hostroot,security_model=none,readonly=on,multidevs=remap"
    -virtfs "local,path=$R,mount_tag=hilres,security_model=none,multidevs=remap")
n=0
for d in "${rw_dirs[@]}"; do
    virtfs+=(-virtfs "local,path=$d,mount_tag=hilrw$n,security_model=none,multidevs=remap")
    n=$((n + 1))
done
read -r -a extra <<< "${HIL_QEMU_CMDLINE:-}"
log "booting qemu (kernel $kver, tcg, ${mem} MiB, modules: ${modprobes[*]:-none}, timeout=${timeout_s}s, results $R)"
t0=$EPOCHREALTIME
# -kernel vmlinux (ELF): PVH entry, no decompressor under emulation. -no-reboot: the guest's reboot
# (and panic=-1) ends qemu. qemu's own exit status says nothing about the command: R/rc does.
qemu-system-x86_64 -accel tcg -cpu max -smp 1 -m "$mem" -M pc -nodefaults -no-user-config \
    -display none -monitor none -no-reboot -serial "file:$R/boot.log" \
    -kernel "$kdir/vmlinux" -initrd "$kdir/initramfs.cpio" \
    -append "console=ttyS0 panic=-1 quiet rdinit=/init ${extra[*]}" \
    "${virtfs[@]}" < /dev/null > "$R/qemu.out" 2>&1 &
qemu_pid=$!

if [[ ${HIL_STREAM:-1} == 1 ]]; then
    tail -s 0.1 -n +1 -f --pid="$qemu_pid" "$R/stdout" &
    tail_pids+=($!)
    tail -s 0.1 -n +1 -f --pid="$qemu_pid" "$R/stderr" >&2 &
    tail_pids+=($!)
fi

started=0 reason=''
while kill -0 "$qemu_pid" 2>/dev/null; do
    now=$EPOCHREALTIME
    if ((started == 0)) && [[ -e $R/t_cmd_start ]]; then started=1 t_started_host=$now; fi
    if ((started == 0)) && (( ($(usecs "$now") - $(usecs "$t0")) / 1000000 >= boot_timeout )); then
        reason="the guest did not start the command within ${boot_timeout}s (HIL_BOOT_TIMEOUT)"
        break
    fi
    if ((started == 1 && timeout_s > 0)) &&
        (( ($(usecs "$now") - $(usecs "$t_started_host")) / 1000000 >= timeout_s + 40 )); then
        reason="watchdog: the guest did not halt ${timeout_s}s+40s after the command started"
        break
    fi
    sleep 0.1
done
[[ -z $reason ]] || kill -KILL "$qemu_pid" 2>/dev/null || true
qemu_rc=0
wait "$qemu_pid" 2>/dev/null || qemu_rc=$?
qemu_pid=''
t_end=$EPOCHREALTIME
if [[ ${HIL_STREAM:-1} == 1 ]]; then
    for p in "${tail_pids[@]}"; do wait "$p" 2>/dev/null || true; done
    tail_pids=()
else
    cat "$R/stdout"
    cat "$R/stderr" >&2
fi

[[ -z $reason ]] || qemu_fail "$reason"
if [[ ! -e $R/rc ]]; then
    [[ -s $R/qemu.out ]] && sed 's/^/[hil] qemu: /' "$R/qemu.out" >&2
    [[ -e $R/t_cmd_start ]] && qemu_fail "the command started but no exit code came back (qemu exited with $qemu_rc)"
    qemu_fail "the VM did not start the command (qemu exited with $qemu_rc)"
fi
rc=$(< "$R/rc")
if ! [[ $rc =~ ^[0-9]+$ ]] || ((rc > 255)); then qemu_fail "garbled exit code file: '$rc'"; fi
# Guest stamps are the guest's wall clock (set from the emulated RTC, whole seconds): the boot->cmd
# split uses the host's view of when t_cmd_start appeared instead.
if [[ -n ${t_started_host:-} ]]; then
    log "qemu: boot->cmd $(elapsed "$t0" "$t_started_host")s, cmd+halt $(elapsed "$t_started_host" "$t_end")s," \
        "total $(elapsed "$t0" "$t_end")s, exit $rc"
    printf 'boot_to_cmd=%s cmd_and_halt=%s total=%s rc=%s\n' "$(elapsed "$t0" "$t_started_host")" \
        "$(elapsed "$t_started_host" "$t_end")" "$(elapsed "$t0" "$t_end")" "$rc" > "$R/timing"
fi
exit "$rc"
