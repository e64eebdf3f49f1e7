#!/usr/bin/env bash
# run-in-vcan.sh: run a command where SocketCAN vcan interfaces exist, and return its exit code.
#
# Usage: tests/hil/run-in-vcan.sh [--ifaces vcan0,vcan1] [--timeout SECS] [--rw DIR]... -- <command> [args...]
#
# * If the host kernel has vcan (an interface of CAN type among --ifaces exists, or
#   `ip link add ... type vcan` works), the interfaces are created/brought up on the host and the
#   command runs natively.
# * Otherwise (the usual case here: the host kernel has no CONFIG_CAN at all) the command runs inside a
#   user-mode-linux (UML) guest that boots with the host root filesystem read-only over hostfs, loads
#   can/can-raw/can-dev/vcan, brings the interfaces up and runs the command with the caller's
#   environment and working directory. See docs/hil.md and tests/hil/guest-init.sh.
#
# Exit code: the command's own. 124 = the command hit --timeout. 125 = harness failure (bad usage,
# missing packages that cannot be installed, VM did not start, no exit code came back, watchdog): it is
# never turned into 0 or a skip.
#
# Environment knobs (all optional):
#   HIL_UML_MEM=1024M        guest memory (UML mem=)
#   HIL_UML_KERNEL=path      UML kernel (default /usr/bin/linux.uml)
#   HIL_UML_FAST_BOOT=0      do not pass the boot-time savers (see the boot command below)
#   HIL_UML_CMDLINE="..."    extra kernel parameters (e.g. "loglevel=8 initcall_debug")
#   HIL_BOOT_TIMEOUT=120     seconds allowed from launch until the command starts, else 125
#   HIL_OVERLAY_DIRS="/tmp /var/tmp"  host dirs given a private writable copy-on-write view in the guest
#   HIL_ENV_DROP="A B"       extra caller variables NOT to pass into the guest
#   HIL_RESULTS_PARENT=dir   where the per-run results dir is created (default ${TMPDIR:-/tmp})
#   HIL_KEEP_RESULTS=1       keep the results dir (always kept on a harness failure)
#   HIL_FORCE_UML=1          use the UML guest even if the host has vcan
#   HIL_QUIET=1              no [hil] status lines on stderr (errors are still printed)
#   HIL_STREAM=0             print the guest's stdout/stderr after the run instead of live
set -euo pipefail

HERE=$(cd -- "$(dirname -- "${BASH_SOURCE[0]}")" && pwd)
readonly HERE
readonly HARNESS_FAIL=125

log() { [[ ${HIL_QUIET:-0} == 1 ]] || printf '[hil] %s\n' "$*" >&2; }
die() { printf '[hil] ERROR: %s\n' "$*" >&2; exit "$HARNESS_FAIL"; }

usage() {
    cat <<'EOF'
Usage: run-in-vcan.sh [--ifaces vcan0,vcan1] [--timeout SECS] [--rw DIR]... -- <command> [args...]

  --ifaces LIST   comma-separated vcan interfaces to create and bring up (default: vcan0)
  --timeout SECS  kill the command after SECS seconds, exit code 124 (default: 600; 0 = none)
  --rw DIR        (UML only) mount host directory DIR read-write in the guest (repeatable);
                  everything else of the host root is read-only, /tmp and /var/tmp are private.

Exit code: the command's; 124 on timeout; 125 on a harness failure. See docs/hil.md.
EOF
}

# ---------------------------------------------------------------------------------------------------
# Arguments
# ---------------------------------------------------------------------------------------------------
# Paths that go on the kernel command line, into hostfs/overlay mount options and into an fstab
# must not contain separators (space , : =) or escapes.
plain_path() { [[ $1 =~ ^/[A-Za-z0-9_./+@-]*$ ]]; }

ifaces_csv=vcan0
timeout_s=600
rw_dirs=()
while (($#)); do
    case $1 in
        --ifaces) (($# >= 2)) || die "--ifaces needs a value"; ifaces_csv=$2; shift 2 ;;
        --ifaces=*) ifaces_csv=${1#*=}; shift ;;
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
IFS=, read -r -a ifaces <<< "$ifaces_csv"
((${#ifaces[@]})) || die "--ifaces is empty"
for i in "${ifaces[@]}"; do
    [[ $i =~ ^[A-Za-z0-9_.-]{1,15}$ ]] || die "bad interface name '$i' (1-15 of [A-Za-z0-9_.-])"
done
for i in "${!rw_dirs[@]}"; do
    d=$(realpath -e -- "${rw_dirs[$i]}" 2>/dev/null) || die "--rw ${rw_dirs[$i]}: no such directory"
    [[ -d $d ]] || die "--rw $d is not a directory"
    plain_path "$d" || die "--rw $d: use a path of [A-Za-z0-9_./+@-] only (hostfs/fstab syntax)"
    rw_dirs[i]=$d
done

# ---------------------------------------------------------------------------------------------------
# Packages: install only what is missing (we are normally root; apt works).
# ---------------------------------------------------------------------------------------------------
apt_install() {
    local log_file
    [[ $(id -u) == 0 ]] || die "missing packages: $*; install them (as root: apt-get install $*)"
    command -v apt-get > /dev/null || die "missing packages: $* and no apt-get"
    log "installing missing packages: $*"
    log_file=$(mktemp "${TMPDIR:-/tmp}/hil-apt.XXXXXX")
    # flock: parallel invocations must not race on dpkg; Lock::Timeout covers other apt users.
    if ! (
        flock -w 600 9 || exit 1
        export DEBIAN_FRONTEND=noninteractive
        apt_opts=(-y -q -o DPkg::Lock::Timeout=600)
        # Only fall back to `apt-get update` when the plain install fails (e.g. stale/empty lists).
        apt-get install "${apt_opts[@]}" "$@" > "$log_file" 2>&1 ||
            { apt-get update -q >> "$log_file" 2>&1 && apt-get install "${apt_opts[@]}" "$@" >> "$log_file" 2>&1; }
    ) 9> /tmp/hil-apt.lock; then
        tail -n 30 "$log_file" >&2
        die "apt-get install $* failed (log: $log_file)"
    fi
    rm -f "$log_file"
}

# ensure_tools MODE: MODE is native or uml.
ensure_tools() {
    local mode=$1 pkgs=()
    command -v ip > /dev/null || pkgs+=(iproute2)
    command -v candump > /dev/null && command -v cansend > /dev/null && command -v cangen > /dev/null ||
        pkgs+=(can-utils)
    if [[ $mode == uml ]]; then
        # The UML kernel and its module tree both come from user-mode-linux.
        if [[ -z ${HIL_UML_KERNEL:-} ]]; then
            if [[ ! -x /usr/bin/linux.uml ]] ||
                ! compgen -G "/usr/lib/uml/modules/*/kernel/drivers/net/can/vcan.ko*" > /dev/null; then
                pkgs+=(user-mode-linux)
            fi
        fi
        # The guest loads modules with the host's modprobe (insmod as the fallback): both from kmod.
        command -v modprobe > /dev/null && command -v insmod > /dev/null || pkgs+=(kmod)
        command -v timeout > /dev/null || pkgs+=(coreutils)
    fi
    ((${#pkgs[@]} == 0)) || apt_install "${pkgs[@]}"
}

# ---------------------------------------------------------------------------------------------------
# Native path: the host kernel has vcan.
# ---------------------------------------------------------------------------------------------------
host_has_vcan() {
    local i probe
    [[ ${HIL_FORCE_UML:-0} == 1 ]] && return 1
    command -v ip > /dev/null || return 1
    # An existing CAN-type interface (ARPHRD_CAN = 280) among the requested ones proves CAN support.
    for i in "${ifaces[@]}"; do
        [[ $(cat "/sys/class/net/$i/type" 2>/dev/null) == 280 ]] && return 0
    done
    # Otherwise try to create a throwaway vcan (loading the module first if the host has one).
    command -v modprobe > /dev/null && modprobe -q vcan 2>/dev/null || true
    probe=hilprobe$((RANDOM % 100000))
    if ip link add dev "$probe" type vcan 2>/dev/null; then
        ip link del dev "$probe" 2>/dev/null || true
        return 0
    fi
    return 1
}

run_native() {
    local i
    for i in "${ifaces[@]}"; do
        if [[ ! -e /sys/class/net/$i ]]; then
            ip link add dev "$i" type vcan || die "ip link add dev $i type vcan failed"
        fi
        ip link set dev "$i" up || die "ip link set dev $i up failed"
    done
    log "host kernel has vcan: running natively on ${ifaces_csv}"
    export HIL_IN_GUEST=0 HIL_MODE=native HIL_IFACES=$ifaces_csv
    if ((timeout_s > 0)); then
        exec timeout --kill-after=10 "$timeout_s" "$@"
    fi
    exec "$@"
}

# ---------------------------------------------------------------------------------------------------
# UML path
# ---------------------------------------------------------------------------------------------------
R='' uml_pid='' wrapper_pid='' tail_pids=() keep=0

# shellcheck disable=SC2329  # invoked by `trap cleanup EXIT`
cleanup() {
    local p
    # The VM (its whole process group: UML runs each guest process as a host process).
    if [[ -n $uml_pid ]] && kill -0 "$uml_pid" 2>/dev/null; then
        kill -KILL -- "-$uml_pid" 2>/dev/null || kill -KILL "$uml_pid" 2>/dev/null || true
    fi
    # disown first: no "Terminated" job notices for what we kill on the way out.
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

# emit_array NAME [values...]: a bash array assignment for params.sh (an empty array stays empty:
# `printf %q` with no arguments would emit '' and create one empty element).
emit_array() {
    local name=$1
    shift
    printf '%s=(' "$name"
    (($#)) && printf '%q ' "$@"
    printf ')\n'
}

# Microseconds since the epoch from an EPOCHREALTIME value (its decimal point follows the locale).
usecs() { echo "${1//[.,]/}"; }

# Seconds (3 decimals) between two EPOCHREALTIME-style stamps.
elapsed() { awk -v a="${1/,/.}" -v b="${2/,/.}" 'BEGIN { printf "%.3f", b - a }'; }

# Harness failure in the UML path: explain, show the evidence, keep the results dir, exit 125.
uml_fail() {
    keep=1
    printf '[hil] ERROR: %s\n' "$*" >&2
    if [[ -s $R/setup-error ]]; then
        printf '[hil] guest setup error:\n' >&2
        sed 's/^/[hil]   /' "$R/setup-error" >&2
    fi
    if [[ -s $R/boot.log ]]; then
        printf '[hil] last lines of the UML console (%s):\n' "$R/boot.log" >&2
        grep -v '^ *\[<' "$R/boot.log" | tail -n 25 | sed 's/^/[hil]   /' >&2
    fi
    exit "$HARNESS_FAIL"
}

# UML cannot run on this host: Debian's UML 6.1 kernel fails to set the guest's floating-point
# registers through ptrace when the host's FPU state is larger than it handles (AVX-512 hosts,
# e.g. AMD Zen 4): its init dies before the command ("ptrace set fp regs failed, errno = 14").
# Run the command in the qemu guest instead (run-in-qemu.sh: Debian's own kernel, which has vcan),
# with the same interfaces, timeout and --rw dirs; HIL_MODE=qemu. Slower (software emulation), so
# measure timing on the host as always; the behaviour and counts are the same.
run_qemu_fallback() {
    log "UML cannot run on this host (ptrace set fp regs failed: an FPU state it does not handle, e.g. AVX-512): falling back to the qemu guest (run-in-qemu.sh)"
    local -a args=(--modprobe can_raw --modprobe vcan --timeout "$timeout_s")
    local d
    for d in "${rw_dirs[@]}"; do args+=(--rw "$d"); done
    rm -rf -- "$R"
    export HIL_FALLBACK_IFACES=$ifaces_csv
    # shellcheck disable=SC2016 # expanded in the guest
    exec "$HERE/run-in-qemu.sh" "${args[@]}" -- bash -c '
        set -e
        IFS=, read -r -a ifs <<< "$HIL_FALLBACK_IFACES"
        ip link set dev lo up
        for i in "${ifs[@]}"; do ip link add dev "$i" type vcan; ip link set dev "$i" up; done
        export HIL_IFACES=$HIL_FALLBACK_IFACES
        unset HIL_FALLBACK_IFACES
        exec "$@"' hil-vcan "$@"
}

run_uml() {
    local kernel=${HIL_UML_KERNEL:-/usr/bin/linux.uml}
    local mem=${HIL_UML_MEM:-1024M}
    local boot_timeout=${HIL_BOOT_TIMEOUT:-120}
    local parent=${HIL_RESULTS_PARENT:-${TMPDIR:-/tmp}}
    local name t0 now started=0 reason='' rc cwd umid uml_rc
    local -a overlay_dirs

    [[ $mem =~ ^[0-9]+[KMG]?$ ]] || die "HIL_UML_MEM must look like 1024M, got '$mem'"
    [[ $boot_timeout =~ ^[0-9]+$ ]] || die "HIL_BOOT_TIMEOUT must be whole seconds"
    [[ -x $kernel ]] || die "UML kernel $kernel is not executable"
    cwd=$(pwd -P)
    read -r -a overlay_dirs <<< "${HIL_OVERLAY_DIRS-/tmp /var/tmp}"
    for i in "${!overlay_dirs[@]}"; do
        d=$(realpath -e -- "${overlay_dirs[$i]}" 2>/dev/null) && [[ -d $d ]] ||
            die "HIL_OVERLAY_DIRS: ${overlay_dirs[$i]} is not a directory"
        plain_path "$d" || die "HIL_OVERLAY_DIRS: $d: use a path of [A-Za-z0-9_./+@-] only"
        [[ $d != / ]] || die "HIL_OVERLAY_DIRS: / cannot be overlaid"
        overlay_dirs[i]=$d
    done

    trap cleanup EXIT
    trap 'exit 130' INT
    trap 'exit 143' TERM

    # Unique per invocation: results dir, and from it UML's umid (uml_dir is inside it too, so
    # parallel runs never share ~/.uml/<umid> or an mconsole socket).
    parent=$(realpath -e -- "$parent") || die "results parent $parent does not exist"
    R=$(mktemp -d "$parent/hil-run.XXXXXXXX") || die "mktemp -d in $parent failed"
    # The path goes on the kernel command line and into a hostfs mount option: keep it plain.
    plain_path "$R" || die "results dir path '$R' has characters UML cannot take (set HIL_RESULTS_PARENT)"
    umid=hil-${R##*.}
    mkdir "$R/uml"

    # --- Files the guest reads (see the header of guest-init.sh) ---
    cp "$HERE/guest-init.sh" "$R/init" && chmod 0755 "$R/init"
    printf '%s\0' "$@" > "$R/argv"

    # /dev extras (devtmpfs has no /dev/fd; bash process substitution needs it) and mount points.
    mkdir -p "$R/skel/dev/shm" "$R/skel/dev/pts" "$R/skel/dev/mqueue"
    chmod 1777 "$R/skel/dev/shm"
    ln -s /proc/self/fd "$R/skel/dev/fd"
    ln -s /proc/self/fd/0 "$R/skel/dev/stdin"
    ln -s /proc/self/fd/1 "$R/skel/dev/stdout"
    ln -s /proc/self/fd/2 "$R/skel/dev/stderr"
    # /dev/shm and /run are tmpfs: iceoryx2 (and POSIX shm) need a writable /dev/shm.
    printf '%s\n' \
        'proc   /proc       proc   nosuid,nodev,noexec         0 0' \
        'sysfs  /sys        sysfs  nosuid,nodev,noexec         0 0' \
        'devpts /dev/pts    devpts gid=5,mode=620,ptmxmode=666 0 0' \
        'mqueue /dev/mqueue mqueue nosuid,nodev,noexec         0 0' \
        'shm    /dev/shm    tmpfs  mode=1777,nosuid,nodev      0 0' \
        'tmpfs  /run        tmpfs  mode=0755,nosuid,nodev      0 0' > "$R/fstab.base"
    # /run contents: results mount point, a modprobe root, overlay upper/work dirs.
    mkdir -p "$R/skel/run/hil" "$R/skel/run/lock" "$R/skel/run/hil-mods/lib"
    ln -s /usr/lib/uml/modules "$R/skel/run/hil-mods/lib/modules"
    # hostfs's mount option is the host path; the overlay's upper dir gives the merged dir its
    # mode/owner, so copy them from the host dir (/tmp is 1777).
    {
        printf 'hostfs /run/hil hostfs %s 0 0\n' "$R"
        n=0
        for d in "${overlay_dirs[@]}"; do
            n=$((n + 1))
            mkdir -p "$R/skel/run/hil-ovl/$n/upper" "$R/skel/run/hil-ovl/$n/work"
            chmod --reference="$d" "$R/skel/run/hil-ovl/$n/upper"
            chown --reference="$d" "$R/skel/run/hil-ovl/$n/upper"
            printf 'overlay %s overlay lowerdir=%s,upperdir=/run/hil-ovl/%s/upper,workdir=/run/hil-ovl/%s/work 0 0\n' \
                "$d" "$d" "$n" "$n"
        done
        for d in "${rw_dirs[@]}"; do printf 'hostfs %s hostfs %s 0 0\n' "$d" "$d"; done
    } > "$R/fstab.hil"
    {
        echo "link set dev lo up"
        for i in "${ifaces[@]}"; do
            echo "link add dev $i type vcan"
            echo "link set dev $i up"
        done
    } > "$R/ip.batch"
    {
        emit_array HIL_IFACES_LIST "${ifaces[@]}"
        emit_array HIL_OVERLAY_DIRS "${overlay_dirs[@]}"
        emit_array HIL_RW_DIRS "${rw_dirs[@]}"
        printf 'HIL_TIMEOUT=%q\n' "$timeout_s"
        printf 'HIL_CWD=%q\n' "$cwd"
        printf 'HIL_HOSTNAME=%q\n' "$(hostname 2>/dev/null || echo hil)"
        printf 'HIL_MODULES_DIR=%q\n' "${HIL_MODULES_DIR:-}"
    } > "$R/params.sh"
    # The caller's exported environment, minus variables that only make sense on the host.
    local drop=" _ SHLVL PWD OLDPWD SHELLOPTS BASHOPTS BASH_ENV ENV PS1 PS2 PS4 PROMPT_COMMAND
        SSH_AUTH_SOCK SSH_AGENT_PID SSH_CONNECTION SSH_CLIENT SSH_TTY DISPLAY WAYLAND_DISPLAY
        XDG_RUNTIME_DIR DBUS_SESSION_BUS_ADDRESS TMUX TMUX_PANE STY HIL_IN_GUEST HIL_MODE ${HIL_ENV_DROP:-} "
    drop=" ${drop//[$'\t\n']/ } "   # one line; every name is now surrounded by spaces
    {
        while IFS= read -r name; do
            [[ $name =~ ^[A-Za-z_][A-Za-z0-9_]*$ ]] || continue
            [[ $drop == *" $name "* ]] && continue
            printf 'export %s=%q\n' "$name" "${!name}"
        done < <(compgen -e)
        printf 'export HIL_IFACES=%q\n' "$ifaces_csv"
    } > "$R/env.sh"
    : > "$R/stdout"
    : > "$R/stderr"

    # --- Boot ---
    # con0 = the guest console -> boot.log (stdin /dev/null: UML must never touch the caller's tty).
    # setsid: the VM gets its own process group, so cleanup can kill every process of it at once.
    log "booting UML (mem=$mem, ifaces=$ifaces_csv, timeout=${timeout_s}s, results $R)"
    t0=$EPOCHREALTIME
    # Boot-time savers (measured: kernel boot 1.9 s -> 0.45 s), HIL_UML_FAST_BOOT=0 turns them off:
    #  - initcall_blacklist=raid6_select_algo: skips the 0.8 s RAID-6 algorithm benchmark (only
    #    md raid456 / btrfs raid56 would need it, neither is used in the guest);
    #  - pty.legacy_count=0: no 256 legacy BSD ptys (0.5 s of devtmpfs nodes); Unix98 ptys
    #    (/dev/ptmx, openpty) still work.
    local -a fast_boot=(initcall_blacklist=raid6_select_algo pty.legacy_count=0) extra=()
    [[ ${HIL_UML_FAST_BOOT:-1} == 1 ]] || fast_boot=()
    read -r -a extra <<< "${HIL_UML_CMDLINE:-}"   # extra kernel parameters, for debugging
    # The wrapper subshell waits for UML and exits with its status: when UML dies from a signal
    # (watchdog kill, guest panic -> SIGABRT) bash would otherwise print a "Killed ..." job notice.
    # Its stderr goes to /dev/null; UML's own output goes to boot.log.
    (
        setsid "$kernel" mem="$mem" root=/dev/root rootfstype=hostfs rootflags=/ ro \
            init="$R/init" HIL_RESULTS_HOST="$R" \
            con=null con0=fd:0,fd:1 ssl=null umid="$umid" uml_dir="$R/uml" quiet \
            "${fast_boot[@]}" "${extra[@]}" \
            < /dev/null > "$R/boot.log" 2>&1 &
        echo "$!" > "$R/uml.pid.tmp" && mv "$R/uml.pid.tmp" "$R/uml.pid"
        wait "$!"
    ) 2> /dev/null &
    wrapper_pid=$!
    # setsid execs in place (the child is no group leader), so this pid is also UML's process group.
    until [[ -s $R/uml.pid ]]; do
        kill -0 "$wrapper_pid" 2>/dev/null || [[ -s $R/uml.pid ]] || die "could not launch $kernel"
        sleep 0.01
    done
    uml_pid=$(< "$R/uml.pid")

    # --- Output: live (tail follows the files that hostfs writes through to the host) ---
    if [[ ${HIL_STREAM:-1} == 1 ]]; then
        tail -s 0.1 -n +1 -f --pid="$uml_pid" "$R/stdout" &
        tail_pids+=($!)
        tail -s 0.1 -n +1 -f --pid="$uml_pid" "$R/stderr" >&2 &
        tail_pids+=($!)
    fi

    # --- Watchdog: boot must finish within boot_timeout; the guest's own `timeout` must fire first,
    #     this is the backstop for a hung guest (40 s grace after --timeout: 10 s kill-after + 30). ---
    while kill -0 "$uml_pid" 2>/dev/null; do
        now=$EPOCHREALTIME
        if ((started == 0)) && [[ -e $R/t_cmd_start ]]; then
            started=1
            t_started_host=$now
        fi
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
    if [[ -n $reason ]]; then
        kill -KILL -- "-$uml_pid" 2>/dev/null || true
    fi
    uml_rc=0
    wait "$wrapper_pid" || uml_rc=$?   # UML's exit status (128+N if killed by signal N)
    uml_pid='' wrapper_pid=
    local t_end=$EPOCHREALTIME

    # Drain the live output (tail exits on its own once the VM is gone), or print it now.
    if [[ ${HIL_STREAM:-1} == 1 ]]; then
        for p in "${tail_pids[@]}"; do wait "$p" 2>/dev/null || true; done
        tail_pids=()
    else
        cat "$R/stdout"
        cat "$R/stderr" >&2
    fi

    [[ -z $reason ]] || uml_fail "$reason"
    if [[ ! -e $R/rc ]]; then
        if [[ -e $R/t_cmd_start ]]; then
            uml_fail "the command started but no exit code came back (UML exited with $uml_rc)"
        fi
        if grep -q 'ptrace set fp regs failed' "$R/boot.log" 2> /dev/null; then
            run_qemu_fallback "$@"
        fi
        uml_fail "the VM did not start the command (UML exited with $uml_rc)"
    fi
    rc=$(< "$R/rc")
    if ! [[ $rc =~ ^[0-9]+$ ]] || ((rc > 255)); then uml_fail "garbled exit code file: '$rc'"; fi

    # --- Timings (guest stamps use the same wall clock as the host: UML reads the host's clock) ---
    if [[ -e $R/t_cmd_start && -e $R/t_cmd_end ]]; then
        local ts te
        ts=$(< "$R/t_cmd_start") te=$(< "$R/t_cmd_end")
        printf 'boot_to_cmd=%s cmd=%s halt=%s total=%s rc=%s\n' \
            "$(elapsed "$t0" "$ts")" "$(elapsed "$ts" "$te")" "$(elapsed "$te" "$t_end")" \
            "$(elapsed "$t0" "$t_end")" "$rc" > "$R/timing"
        log "uml: boot->cmd $(elapsed "$t0" "$ts")s, cmd $(elapsed "$ts" "$te")s," \
            "halt $(elapsed "$te" "$t_end")s, total $(elapsed "$t0" "$t_end")s, exit $rc"
    fi
    exit "$rc"
}

# ---------------------------------------------------------------------------------------------------
# Main
# ---------------------------------------------------------------------------------------------------
command -v ip > /dev/null || ensure_tools native   # `ip` is needed for the probe itself
if host_has_vcan; then
    ensure_tools native
    run_native "$@"
fi
ensure_tools uml
run_uml "$@"
